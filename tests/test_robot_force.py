"""Force limits that mean overload, and the robot's own log (issue 24, items 5 and 7), on PyBullet runs.

Faults are injected at the F/T sensor (a wrapper around the simulated sensor, the edge where a real
sensor would sit): the guard, the compiled 1 kHz loop and the state machine are the real ones.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("pybullet")
pytest.importorskip("pygafro")

from conftest import run_cli  # noqa: E402
from tergodic_cli.backends.pybullet import RobotRun  # noqa: E402
from tergodic_cli.basis import compute_basis  # noqa: E402
from tergodic_cli.capture import CaptureConfig, capture_cloud  # noqa: E402
from tergodic_cli.explore import ExploreConfig, Explorer  # noqa: E402
from tergodic_cli.robot import RobotConfig, robot_explore_config  # noqa: E402
from tergodic_cli.robot.interfaces import WrenchReading  # noqa: E402
from tergodic_cli.robot.run import ContactRun  # noqa: E402
from tergodic_cli.runlog import read_run_log  # noqa: E402
from tergodic_cli.runlog import schema as S  # noqa: E402

FAST = dict(move_speed=1.6, hover_height=0.02)


@pytest.fixture(scope="module")
def plate():
    cap = capture_cloud(CaptureConfig(source="synthetic", synthetic="plate", voxel=0.005))
    return cap, compute_basis(cap.points, 40, 30)


class _Inject:
    """The F/T sensor with ``extra`` newtons added along its reading's own force direction (so the
    contact force |f| grows by about that much) on the reads where ``when(run)`` is true, for
    ``ticks`` reads (None: from then on)."""

    def __init__(self, sensor, run, extra: float, ticks: int | None, when):
        self._s, self._run, self.extra, self.ticks, self.when = sensor, run, extra, ticks, when
        self.frame_in_ee = sensor.frame_in_ee
        self.t_inj, self.done = None, 0

    def read(self):
        r = self._s.read()
        if self.ticks is not None and self.done >= self.ticks:
            return r
        if self.t_inj is None and not (r.valid and self.when(self._run)):
            return r
        if self.t_inj is None:
            self.t_inj = r.t
        w = np.array(r.wrench, dtype=float)
        n = float(np.linalg.norm(w[:3]))
        w[:3] += self.extra * (w[:3] / n if n > 0.5 else np.array([0.0, 0.0, 1.0]))
        self.done += 1
        return WrenchReading(r.t, tuple(w.tolist()), r.valid)

    def tare(self):
        self._s.tare()


def _in_explore_after(k: int):
    return lambda run: run.sm.state == "explore" and len(run.samples) >= k


def _run(plate, extra: float, ticks: int | None, steps: int = 8, **cfg):
    cap, basis = plate
    rc = RobotConfig(**FAST, **cfg)
    ec = robot_explore_config(ExploreConfig(nk=40, seed=0, agent_radius=0.008), rc.explore_dt)
    start = cap.points[np.argmin(np.linalg.norm(cap.points[:, :2] - [0.03, 0.02], axis=1))][None]
    ex = Explorer(basis, cap.target, ec, start, on_event=lambda msg: None)
    log: list = []
    run = RobotRun(cap, ex, rc, on_log=lambda kind, step, rec: log.append((kind, step, rec)))
    inj = _Inject(run.arm.sensor, run, extra, ticks, _in_explore_after(2))
    run.arm.sensor = inj
    with run:
        out = run.run(steps)
        contacts = run.scene.sponge_contacts()
    return run, out, inj, log, contacts


def _windows(log):
    return [rec for kind, _, rec in log if kind == "force"]


def test_a_single_tick_spike_under_the_impact_limit_does_not_stop(plate):
    """+20 N for one tick while pressing at 5 N: ~25 N, over the 15 N force limit (the old raw check
    stopped here) and under the 30 N impact limit: the run completes."""
    run, out, inj, log, _ = _run(plate, 20.0, 1)
    assert inj.done == 1
    assert out["stop_reason"] == "completed" and out["final_state"] == "done"
    assert 20.0 < out["force_peak_N"] < run.guard.force_impact_limit  # the spike was there, over 15 N
    assert run.guard.force_limit == 15.0
    assert max(w["force_max"] for w in _windows(log)) == out["force_peak_N"]


def test_a_sustained_overload_stops_within_the_filter_delay(plate):
    """+20 N on every tick from the third explorer step on (an overload, say a stiffer object): the
    low-passed force reaches 15 N within 18 ms (10 Hz first order, from 5 N to a 20-25 N step), and the
    run ends lifted (exit 3's "stopped", no contact)."""
    run, out, inj, log, contacts = _run(plate, 20.0, None)
    assert out["final_state"] == "stopped" and "low-passed at 10 Hz" in out["stop_reason"]
    assert run.fault.kind == "force" and run.fault.data["force"] > 15.0
    delay = run.fault.t - inj.t_inj
    assert 0.005 <= delay <= 0.018, delay
    assert contacts == []
    assert [t["to"] for t in out["transitions"]][-2:] == ["retreat", "stopped"]
    assert max(w["force_max"] for w in _windows(log)) == out["force_peak_N"]


def test_an_impact_stops_at_once(plate):
    """+40 N for one tick: over the 30 N impact limit, the run stops on that very tick."""
    run, out, inj, log, contacts = _run(plate, 40.0, 1)
    assert out["final_state"] == "stopped" and "impact limit" in out["stop_reason"]
    assert run.fault.t == inj.t_inj and run.fault.data["force_tick"] > 30.0
    assert contacts == []


def test_the_run_log_holds_every_phase_and_every_tick(plate, tmp_path, monkeypatch):
    """``tergodic explore --robot pybullet``: /robot/phase holds the transitions in order (protobuf), and
    a 25 N spike in the final retreat, after the last 5 Hz sample, is in /robot/force: the largest
    window max equals summary.json's 1 kHz peak exactly, and replay recomputes the same summary."""
    cap = tmp_path / "cap"
    assert run_cli("capture", "--synthetic", "plate", "--voxel", "0.005", "--seed", "0", "--out", cap).code == 0
    finish = ContactRun.finish

    def spiked_finish(self, reason):  # one +20 N tick at the start of the final retreat
        self.arm.sensor = _Inject(self.arm.sensor, self, 20.0, 1, lambda run: run.sm.state == "retreat")
        return finish(self, reason)

    monkeypatch.setattr(ContactRun, "finish", spiked_finish)
    run = tmp_path / "run"
    res = run_cli("explore", cap, "--robot", "pybullet", "--steps", "6", "--nk", "40", "--seed", "0", "--out", run)
    assert res.code == 0, res.err
    summary = json.loads((run / "summary.json").read_text())
    d = read_run_log(run)
    assert d.topics[S.TOPIC_ROBOT_PHASE]["schema"] == "tergodic.RobotPhase"
    assert d.topics[S.TOPIC_ROBOT_FORCE]["schema"] == "tergodic.ForceWindow"
    assert {d.topics[t]["schema_encoding"] for t in (S.TOPIC_ROBOT_PHASE, S.TOPIC_ROBOT_FORCE)} == {"protobuf"}
    assert [(p["source"], p["target"]) for p in d.phases] == [
        ("picture", "hover"), ("hover", "approach"), ("approach", "explore"), ("explore", "retreat"), ("retreat", "done")]
    ts = [p["t"] for p in d.phases]
    assert ts == sorted(ts) and ts[0] >= 0
    assert [(tr["from"], tr["to"]) for tr in summary["transitions"]] == [(p["source"], p["target"]) for p in d.phases]
    # every window in the state it ran in, back to back, and the spike after the last sample
    W = d.force_windows
    assert all(a["t_end"] == b["t_start"] for a, b in zip(W, W[1:]))
    assert {w["state"] for w in W} >= {"hover", "approach", "explore", "retreat"}
    peak = max(w["force_max"] for w in W)
    assert peak == summary["force_peak_N"] and peak > 20.0
    assert d.robot[-1]["tick_force_peak_N"] < peak  # the last 5 Hz sample missed it
    assert max(W, key=lambda w: w["force_max"])["state"] == "retreat"
    out = json.loads(run_cli("replay", run, "--json").out)
    out.pop("truncated"), out.pop("status")
    assert out == summary
    table = run_cli("replay", run).out
    assert "robot phases" in table and "retreat" in table and f"max {peak:.4g} N in retreat" in table
