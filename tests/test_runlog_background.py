"""The run log written from a child process: the same file as in-process, crash safety, errors."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog import read_run_log
from tergodic_cli.runlog.background import BackgroundRunLog, LogWriterProcess, _pack, _unpack, open_run_log
from tergodic_cli.runlog.writer import RunLog, SpectralField
from test_runlog import CHILD, demo_inputs


@pytest.fixture(autouse=True)
def _fixed_wall_clock(monkeypatch):
    """One wall-clock origin for every log a test writes, so logs written one after the other compare equal."""
    monkeypatch.setattr(time, "time_ns", lambda: 1_795_000_000_123_456_789)


def _write(cls, path, inp, *, lazy_heat: bool = False, **kwargs):
    """``inp`` through ``cls`` as the explore command logs it; agent count changes half-way when inp has 'P2'."""
    n = len(inp["points"])
    basis = np.random.default_rng(1).standard_normal((n, 12)) if lazy_heat else None
    log = cls(path, config=inp["config"], seed=inp["config"]["seed"], versions=inp["versions"],
              capture_sidecar=inp["sidecar"], points=inp["points"], target=inp["target"], cloud_every=50,
              field_basis=basis, **kwargs)
    for k in range(inp["steps"]):
        step = k + 1
        metrics = {m: v[k] for m, v in inp["metrics"].items()}
        if step == 7:
            metrics["kinetic_energy"] = 1.0 / 3.0  # a non-standard metric on one step
        P, V, N = inp["P"][k], inp["V"][k], inp["N"][k]
        if step > inp["steps"] // 2:
            P, V, N = P[:1], V[:1], N[:1]  # one agent from half-way
        log.log_step(step, float(step), positions=P, velocities=V, normals=N, metrics=metrics,
                     step_ms=inp["step_ms"][k], robot=None if inp["robot"] is None else inp["robot"][k])
        if step == 4:
            log.log_event(step, float(step), "contact established")
        if step in inp["clouds"]:
            fields = dict(inp["clouds"][step])
            if lazy_heat:  # heat = Φ c + r, evaluated by the log (in the child for BackgroundRunLog)
                fields["heat"] = SpectralField(np.linspace(-1, 1, 12) * step, fields["heat"])
            log.log_cloud(step, **fields)
    log.close({"steps": inp["steps"], "ergodicity": float(inp["metrics"]["ergodicity"][-1])})


def _raw_messages(path):
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        reader = make_reader(fh)
        msgs = [(ch.topic, schema.name if schema else "", m.log_time, m.publish_time, m.sequence, m.data)
                for schema, ch, m in reader.iter_messages(log_time_order=False)]
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        att = [(a.name, a.data) for a in reader.iter_attachments()]
    meta["tergodic"].pop("created_unix")
    return msgs, meta, att


@pytest.mark.parametrize("robot", [False, True])
def test_background_writer_writes_exactly_the_inline_messages(tmp_path, robot):
    """Every message (topic, schema, times, sequence, bytes), the metadata and the attachment are identical."""
    inp = demo_inputs(steps=130, n_points=300, n_agents=3, robot=robot, seed=4)
    _write(RunLog, tmp_path / "inline.mcap", inp, lazy_heat=True)
    _write(BackgroundRunLog, tmp_path / "child.mcap", inp, lazy_heat=True)
    a, b = _raw_messages(tmp_path / "inline.mcap"), _raw_messages(tmp_path / "child.mcap")
    assert len(a[0]) == len(b[0]) > 130 * 3
    for x, y in zip(a[0], b[0]):
        assert x == y, (x[:5], y[:5])
    assert a[1] == b[1] and a[2] == b[2]
    d = read_run_log(tmp_path / "child.mcap")
    assert not d.truncated and d.steps == 130
    assert np.array_equal(d.series["ergodicity"], inp["metrics"]["ergodicity"])
    basis = np.random.default_rng(1).standard_normal((300, 12))
    heat = basis @ (np.linspace(-1, 1, 12) * 130) + inp["clouds"][130]["heat"]
    assert np.allclose(d.clouds[-1].heat, heat, rtol=1e-6, atol=1e-5)  # float32 in the message


def test_frames_round_trip_and_refuse_object_arrays():
    frame = b"".join(_pack("steps", {"rows": np.arange(12.0).reshape(2, 6), "P": np.ones((2, 1, 3), np.float32)},
                           slow={"1": {}}))
    hlen, plen = np.frombuffer(frame[:8], "<u4")
    head, arrays = _unpack(frame[8:8 + hlen], frame[8 + hlen:8 + hlen + plen])
    assert head["op"] == "steps" and head["slow"] == {"1": {}}
    assert np.array_equal(arrays["rows"], np.arange(12.0).reshape(2, 6)) and arrays["P"].dtype == np.float32
    with pytest.raises(ValueError, match="object"):
        _unpack(b'{"op": "x", "arrays": [["a", "|O", [1]]]}', b"\0" * 8)


def test_sigkilled_parent_leaves_a_truncated_log_with_what_reached_the_child(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD.replace("from tergodic_cli.runlog import RunLog",
                                    "from tergodic_cli.runlog.background import BackgroundRunLog as RunLog"))
    log = tmp_path / "run" / "run.mcap"
    proc = subprocess.Popen([sys.executable, str(script), str(log)], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "OMP_NUM_THREADS": "1"})
    try:
        deadline, last = time.monotonic() + 120, 0
        while last < 300 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            last = int(line)
        assert last >= 300, "the child did not get going"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    deadline = time.monotonic() + 30  # the writer child finishes its last chunk on its own
    d = None
    while time.monotonic() < deadline:
        try:
            d = read_run_log(log.parent)
        except TergodicError:  # the child may still be starting (empty file)
            d = None
        if d is not None and d.steps >= 280 and d.end is None:
            break
        time.sleep(0.2)
    assert d is not None
    assert d.truncated and d.end is None
    K = d.steps
    assert K >= 280  # everything handed to the child (every 20 steps) is on disk
    assert np.array_equal(d.series["step"], np.arange(1, K + 1))
    assert np.array_equal(d.series["ergodicity"], 1.0 / np.arange(1, K + 1))
    assert all(c.step % 50 == 0 and c.coverage[0] == c.step for c in d.clouds) and len(d.clouds) >= 5


def test_a_dead_writer_is_a_one_line_error_in_the_caller(tmp_path):
    inp = demo_inputs(steps=5, n_points=50)
    writer = LogWriterProcess()
    log = BackgroundRunLog(tmp_path / "run.mcap", config={}, seed=0, points=inp["points"], flush_every=1, writer=writer)
    writer.proc.kill()
    writer.proc.wait()
    with pytest.raises(TergodicError, match="log writer process stopped") as err:
        for k in range(1, 10_000):
            log.log_step(k, float(k), positions=inp["P"][0], velocities=inp["V"][0], normals=inp["N"][0],
                         metrics={"ergodicity": 1.0, "residual_ref": 1.0, "touched_fraction": 0.0}, step_ms=1.0)
            time.sleep(0.001)
    assert "\n" not in str(err.value) and "TERGODIC_LOG_WRITER=inline" in str(err.value)


def test_bad_arguments_fail_in_the_caller_before_anything_starts(tmp_path):
    inp = demo_inputs(steps=2, n_points=20)
    with pytest.raises(TergodicError, match="compression"):
        BackgroundRunLog(tmp_path / "a.mcap", config={}, seed=0, points=inp["points"], compression="gzip")
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(TergodicError, match="cannot write"):
        BackgroundRunLog(tmp_path / "dir.mcap", config={}, seed=0, points=inp["points"])
    log = BackgroundRunLog(tmp_path / "b.mcap", config={}, seed=0, points=inp["points"])
    with pytest.raises(TergodicError, match="shape"):
        log.log_cloud(1, coverage=np.zeros(3), heat=np.zeros(3), source=np.zeros(3))
    log.log_step(1, 1.0, positions=inp["P"][0], velocities=inp["V"][0], normals=inp["N"][0],
                 metrics={"ergodicity": 0.5, "residual_ref": 0.25, "touched_fraction": 0.0}, step_ms=1.0)
    log.close()
    with pytest.raises(TergodicError, match="closed"):
        log.log_step(1, 1.0, positions=np.zeros(3), velocities=np.zeros(3), normals=np.zeros(3), metrics={}, step_ms=1)
    assert not read_run_log(tmp_path / "b.mcap").truncated


def test_the_environment_switch_keeps_the_writer_in_process(tmp_path, monkeypatch):
    inp = demo_inputs(steps=2, n_points=20)
    monkeypatch.setenv("TERGODIC_LOG_WRITER", "inline")
    log = open_run_log(tmp_path / "a.mcap", config={}, seed=0, points=inp["points"])
    assert isinstance(log, RunLog)
    log.close()
    monkeypatch.delenv("TERGODIC_LOG_WRITER")
    log = open_run_log(tmp_path / "b.mcap", config={}, seed=0, points=inp["points"])
    assert isinstance(log, BackgroundRunLog)
    log.close()


def _log_step_by_step(path, kw, inp, metrics, clouds) -> None:
    """The reference log: one log_step per step, then log_cloud(step, **clouds[step]) where one is given."""
    one = RunLog(path, **kw)
    for k in range(inp["steps"]):
        one.log_step(k + 1, float(k + 1), positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                     metrics=dict(zip(("ergodicity", "residual_ref", "touched_fraction"), metrics[k])),
                     step_ms=inp["step_ms"][k])
        if k + 1 in clouds:
            one.log_cloud(k + 1, **clouds[k + 1])
    one.close({"steps": inp["steps"]})


def test_blocks_with_their_cloud_equal_step_by_step_logging(tmp_path):
    """What explore sends (a block of rows and its cloud in one frame) writes the messages of
    one log_step per step followed by log_cloud."""
    inp = demo_inputs(steps=120, n_points=200, n_agents=1, seed=9)
    n, steps = 200, inp["steps"]
    basis = np.random.default_rng(2).standard_normal((n, 6))
    kw = dict(config=inp["config"], seed=1, versions=inp["versions"], capture_sidecar=inp["sidecar"],
              points=inp["points"], target=inp["target"], cloud_every=50, field_basis=basis)
    metrics = np.column_stack([inp["metrics"][k] for k in ("ergodicity", "residual_ref", "touched_fraction")])
    cloud_at = {50, 100, 120}

    def cloud(step):
        c = inp["clouds"][step]
        return {"coverage": c["coverage"], "heat": SpectralField(np.arange(6.0) - step, c["heat"]),
                "source": c["source"]}

    _log_step_by_step(tmp_path / "one.mcap", kw, inp, metrics, {step: cloud(step) for step in cloud_at})
    blocks = BackgroundRunLog(tmp_path / "blocks.mcap", **kw)
    sent = 0
    for end in (30, 50, 100, 120):
        blocks.log_steps(np.arange(sent + 1, end + 1), np.arange(sent + 1, end + 1, dtype=float),
                         positions=inp["P"][sent:end], velocities=inp["V"][sent:end], normals=inp["N"][sent:end],
                         metrics=metrics[sent:end], step_ms=inp["step_ms"][sent:end],
                         cloud=cloud(end) if end in cloud_at else None)
        sent = end
    blocks.close({"steps": steps})
    a, b = _raw_messages(tmp_path / "one.mcap"), _raw_messages(tmp_path / "blocks.mcap")
    assert len(a[0]) == len(b[0]) == 3 * steps + 3
    assert a[0] == b[0] and a[1] == b[1]
    assert [c.step for c in read_run_log(tmp_path / "blocks.mcap").clouds] == [50, 100, 120]


def _basis_file(tmp_path, basis):
    from tergodic_cli.checked_npy import array_checksum

    path = tmp_path / "evecs.npy"
    np.save(path, np.ascontiguousarray(basis), allow_pickle=False)
    return {"path": str(path), "checksum": array_checksum(basis)}


def test_reusable_step_blocks_with_a_basis_file_equal_step_by_step_logging(tmp_path):
    """explore's fast path (a StepBlock refilled in place, Φ read by the child from the basis
    cache file, the target only when it changes) writes the messages of one log_step per step
    and log_cloud with the target each time."""
    inp = demo_inputs(steps=120, n_points=200, n_agents=2, seed=11)
    n, steps, nk = 200, inp["steps"], 6
    phi = np.random.default_rng(3).standard_normal((n, nk + 2))  # the file holds more columns than in use
    kw = dict(config=inp["config"], seed=1, versions=inp["versions"], capture_sidecar=inp["sidecar"],
              points=inp["points"], target=inp["target"], cloud_every=50, field_basis=phi[:, :nk])
    metrics = np.column_stack([inp["metrics"][k] for k in ("ergodicity", "residual_ref", "touched_fraction")])
    new_target = np.where(inp["target"] > 0, 0.0, 1.0)  # a re-capture between the 2nd and 3rd cloud
    cloud_at = {50: inp["target"], 100: inp["target"], 120: new_target}

    def coeffs(step):
        return np.arange(float(nk)) - step

    clouds = {step: dict(coverage=inp["clouds"][step]["coverage"], source=inp["clouds"][step]["source"],
                         heat=SpectralField(coeffs(step), inp["clouds"][step]["heat"]), target=target)
              for step, target in cloud_at.items()}
    _log_step_by_step(tmp_path / "one.mcap", kw, inp, metrics, clouds)

    log = BackgroundRunLog(tmp_path / "blocks.mcap", field_basis_file=_basis_file(tmp_path, phi), **kw)
    sent, target_sent = 0, inp["target"]
    for end in (30, 50, 100, 120):
        cloud = end in cloud_at
        with_target = cloud and cloud_at[end] is not target_sent
        blk = log.step_block(end - sent, 2, cloud=cloud, n_coeffs=nk if cloud else 0, with_target=with_target)
        blk.rows[:] = np.column_stack([np.arange(sent + 1, end + 1), np.arange(sent + 1, end + 1), metrics[sent:end],
                                       inp["step_ms"][sent:end]])
        blk.PVN[:] = np.stack([inp["P"][sent:end], inp["V"][sent:end], inp["N"][sent:end]])
        if cloud:
            c = inp["clouds"][end]
            blk.coverage[:], blk.source[:] = c["coverage"], c["source"]
            blk.heat_coeffs[:], blk.heat_residual[:] = coeffs(end), c["heat"]
            if with_target:
                blk.target[:] = cloud_at[end]
                target_sent = cloud_at[end]
        log.send_block(blk)
        blk.rows[:] = -1.0  # the block is free again as soon as send_block returns
        sent = end
    assert log.step_block(50, 2, cloud=True, n_coeffs=nk) is log.step_block(50, 2, cloud=True, n_coeffs=nk)
    log.close({"steps": steps})
    a, b = _raw_messages(tmp_path / "one.mcap"), _raw_messages(tmp_path / "blocks.mcap")
    assert len(a[0]) == len(b[0]) == 3 * steps + 3
    assert a[0] == b[0] and a[1] == b[1]
    d = read_run_log(tmp_path / "blocks.mcap")
    assert np.array_equal(d.clouds[-1].target, new_target.astype(np.float32))


def test_a_basis_file_changed_during_the_run_leaves_the_heat_out_with_a_warning(tmp_path):
    inp = demo_inputs(steps=50, n_points=100, n_agents=1, seed=12)
    phi = np.random.default_rng(4).standard_normal((100, 4))
    ref = _basis_file(tmp_path, phi)
    np.save(ref["path"], phi + 1e-12, allow_pickle=False)  # modified after its checksum was taken
    log = BackgroundRunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"],
                           target=inp["target"], field_basis=phi, field_basis_file=ref)
    c = inp["clouds"][50]
    metrics = np.column_stack([inp["metrics"][k] for k in ("ergodicity", "residual_ref", "touched_fraction")])
    log.log_steps(np.arange(1, 51), np.arange(1.0, 51.0), positions=inp["P"], velocities=inp["V"], normals=inp["N"],
                  metrics=metrics, step_ms=inp["step_ms"],
                  cloud={"coverage": c["coverage"], "heat": SpectralField(np.ones(4), c["heat"]), "source": c["source"]})
    log.close({"steps": 50})
    d = read_run_log(tmp_path / "run.mcap")
    assert d.steps == 50 and not d.truncated
    assert np.all(np.isnan(d.clouds[0].heat)) and np.allclose(d.clouds[0].coverage, c["coverage"], rtol=1e-6)
    assert any("heat field is not logged" in text and "checksum" in text for _, _, text in d.events)


def test_a_step_block_of_the_wrong_heat_size_is_refused(tmp_path):
    inp = demo_inputs(steps=10, n_points=50, n_agents=1, seed=13)
    log = BackgroundRunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"],
                           target=inp["target"], field_basis=np.ones((50, 3)))
    with pytest.raises(TergodicError, match="3 columns|as many"):
        log.step_block(10, 1, cloud=True, n_coeffs=5)
    blk = log.step_block(2, 1)
    blk.rows[:] = [[1, -1.0, 0, 0, 0, 0], [2, 2.0, 0, 0, 0, 0]]
    with pytest.raises(TergodicError, match="negative step or a bad time"):
        log.send_block(blk)
    log.close({"steps": 0})


def test_begin_close_lets_the_caller_work_while_the_child_finishes(tmp_path):
    inp = demo_inputs(steps=50, n_points=100, n_agents=1, seed=14)
    log = BackgroundRunLog(tmp_path / "run.mcap", config=inp["config"], seed=1, points=inp["points"],
                           target=inp["target"])
    metrics = np.column_stack([inp["metrics"][k] for k in ("ergodicity", "residual_ref", "touched_fraction")])
    log.log_steps(np.arange(1, 51), np.arange(1.0, 51.0), positions=inp["P"], velocities=inp["V"], normals=inp["N"],
                  metrics=metrics, step_ms=inp["step_ms"])
    log.begin_close({"steps": 50, "note": "first"})
    with pytest.raises(TergodicError, match="closed"):
        log.log_event(50, 50.0, "too late")
    log.close({"steps": 50, "note": "ignored: the first summary stands"})
    log.close()
    d = read_run_log(tmp_path / "run.mcap")
    assert d.steps == 50 and not d.truncated and d.stored_summary["note"] == "first"
