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
                         metrics={"ergodicity": 1.0, "ergodicity_ref": 1.0, "touched_fraction": 0.0}, step_ms=1.0)
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
                 metrics={"ergodicity": 0.5, "ergodicity_ref": 0.25, "touched_fraction": 0.0}, step_ms=1.0)
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


def test_blocks_with_their_cloud_equal_step_by_step_logging(tmp_path):
    """What explore sends (a block of rows and its cloud in one frame) writes the messages of
    one log_step per step followed by log_cloud."""
    inp = demo_inputs(steps=120, n_points=200, n_agents=1, seed=9)
    n, steps = 200, inp["steps"]
    basis = np.random.default_rng(2).standard_normal((n, 6))
    kw = dict(config=inp["config"], seed=1, versions=inp["versions"], capture_sidecar=inp["sidecar"],
              points=inp["points"], target=inp["target"], cloud_every=50, field_basis=basis)
    metrics = np.column_stack([inp["metrics"][k] for k in ("ergodicity", "ergodicity_ref", "touched_fraction")])
    cloud_at = {50, 100, 120}

    def cloud(step):
        c = inp["clouds"][step]
        return {"coverage": c["coverage"], "heat": SpectralField(np.arange(6.0) - step, c["heat"]),
                "source": c["source"]}

    one = RunLog(tmp_path / "one.mcap", **kw)
    for k in range(steps):
        one.log_step(k + 1, float(k + 1), positions=inp["P"][k], velocities=inp["V"][k], normals=inp["N"][k],
                     metrics=dict(zip(("ergodicity", "ergodicity_ref", "touched_fraction"), metrics[k])),
                     step_ms=inp["step_ms"][k])
        if k + 1 in cloud_at:
            one.log_cloud(k + 1, **cloud(k + 1))
    one.close({"steps": steps})
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
