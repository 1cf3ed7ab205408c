"""The robot run's headline ε is the sponge's real contacts: a round trip through the run log."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import REPO, run_cli

from tergodic_cli.capture import load_capture
from tergodic_cli.capture.filters import mean_spacing
from tergodic_cli.explore.metrics import coverage_score
from tergodic_cli.rotations import quat_to_matrix
from tergodic_cli.runlog.reader import read_run_log
from tergodic_cli.runlog.summary import compare_with_file, recompute_summary

PLATE = REPO / "data" / "plate"


@pytest.fixture(scope="module")
def plate_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("eps") / "run"
    res = run_cli("explore", PLATE, "--robot", "pybullet", "--force", "5", "--steps", "30", "--nk", "60", "--seed", "0",
                  "--out", out)
    assert res.code == 0, res.err
    return out, json.loads((out / "summary.json").read_text()), read_run_log(out / "run.mcap")


def test_headline_eps_is_the_sponges_logged_contact_points(plate_run):
    out, summary, data = plate_run
    # the contact points as logged (base frame), moved into the capture frame with the logged object pose
    contacts = []
    for s in data.robot:
        if s["in_contact"]:
            pose = np.asarray(s["object_pose"], dtype=float)
            contacts.append((np.asarray(s["contact_point"], dtype=float) - pose[:3]) @ quat_to_matrix(pose[3:]))
    contacts = np.array(contacts)
    assert len(contacts) >= 20  # pressing most of the run
    cap = load_capture(PLATE)
    target = data.clouds[-1].fields["target"]  # the target the explorer worked on
    r_a = summary["config"]["agent_radius"]
    ref = coverage_score(cap.points, target, contacts, r_a, mean_spacing(cap.points))
    assert summary["eps_source"] == "sponge contacts"
    assert summary["ergodicity"] == summary["eps_sponge"]
    assert summary["eps_sponge"] == pytest.approx(ref["ergodicity"], rel=1e-9, abs=1e-12)
    assert summary["touched_fraction"] == summary["touched_sponge"] == pytest.approx(ref["touched_fraction"], rel=1e-12)
    # the agent's ε beside it: the same score of the explorer's own positions, logged per step
    agent = coverage_score(cap.points, target, data.series["positions"], r_a, mean_spacing(cap.points))
    assert summary["eps_agent"] == pytest.approx(agent["ergodicity"], rel=1e-9, abs=1e-12)
    assert summary["eps_agent"] != summary["eps_sponge"]  # two different paths, so the labels matter
    # the series is the sponge's at every step, and the agent's is logged beside it
    assert data.series["ergodicity"][-1] == summary["eps_sponge"]
    assert data.series["ergodicity_agent"][-1] == summary["eps_agent"]
    # the replay recomputes the same summary from the log alone
    assert compare_with_file(recompute_summary(data), out / "summary.json") == ("identical", [])


def test_a_log_from_before_the_sponge_score_keeps_its_figures():
    from tergodic_cli.robot import summarize_robot

    old = [{"t_sim": 0.2 * (k + 1), "state": "explore", "in_contact": True, "force_normal": 5.0,
            "wrench_desired": [0, 0, 5.0, 0, 0, 0], "contact_ergodicity": 0.5 - 0.1 * k,
            "contact_touched_fraction": 0.1 * k, "agent_ergodicity": 0.4, "agent_touched_fraction": 0.3} for k in range(3)]
    out = summarize_robot(old)
    assert out["contact_ergodicity"] == pytest.approx(0.3) and out["agent_touched_fraction"] == 0.3
    assert "eps_sponge" not in out


def test_the_sponge_keeps_the_agents_pace(plate_run):
    """The agent is not reset to a tool trailing it by ~1 mm (it lost that much of every 3 mm step: the
    sponge moved 2.7 mm a step against the kinematic agent's 3.0): the contact point moves a full step."""
    _, summary, data = plate_run
    cps = np.array([s["contact_point"] for s in data.robot if s["in_contact"]], dtype=float)
    step = summary["config"]["v_max"] * summary["config"]["dt"]  # the agent's step at full speed, m
    assert np.median(np.linalg.norm(np.diff(cps, axis=0), axis=1)) >= 0.95 * step
