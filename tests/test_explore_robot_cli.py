"""The explore verb's robot and hardware options: wiring and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import REPO, assert_one_line_error, run_cli

from tergodic_cli.run import make_robot_config
from tergodic_cli.robot import RobotConfig

BOWL = REPO / "data" / "bowl"


def test_robot_options_build_the_config():
    cfg = make_robot_config(RobotConfig, {"force": 7.5, "gui": None, "object_pose": (0.5, 0.0, 0.2),
                                          "safety": {"force_limit": 12.0, "workspace_min": (0.1, -0.5, 0.0)}})
    assert cfg.force == 7.5 and cfg.gui is False and tuple(cfg.object_pose) == (0.5, 0.0, 0.2)
    assert cfg.safety.force_limit == 12.0 and tuple(cfg.safety.workspace_min) == (0.1, -0.5, 0.0)
    assert make_robot_config(RobotConfig, None) == RobotConfig()


def test_franka_without_its_sdk_gives_the_install_hint(tmp_path, monkeypatch):
    import importlib.util

    if importlib.util.find_spec("franky") is not None:
        pytest.skip("franky is installed here")
    res = run_cli("explore", BOWL, "--robot", "franka", "--robot-ip", "172.16.0.2", "--out", tmp_path / "run")
    assert_one_line_error(res, "franky", "pip install 'tergodic[franka]'")
    assert not (tmp_path / "run").exists()


def test_bad_robot_options_are_one_line_errors(tmp_path):
    assert_one_line_error(run_cli("explore", BOWL, "--robot", "pybullet", "--workspace", "1,2,3", "--out", tmp_path / "a"),
                          "--workspace")
    assert_one_line_error(run_cli("explore", BOWL, "--robot", "pybullet", "--object-pose", "x", "--out", tmp_path / "b"),
                          "--object-pose")
    assert_one_line_error(run_cli("explore", BOWL, "--robot", "scara", "--out", tmp_path / "c"), "--robot")
    assert_one_line_error(run_cli("explore", BOWL, "--dry-run", "--out", tmp_path / "d"), "--dry-run")


def test_pybullet_run_writes_the_robot_summary(tmp_path):
    res = run_cli("explore", BOWL, "--robot", "pybullet", "--force", "5", "--steps", "15", "--nk", "60", "--seed", "1",
                  "--no-log", "--out", tmp_path / "run")
    assert res.code == 0, res.err
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    for key in ("force_rms_error_rel", "tilt_deg_median", "track_mm_median", "contact_fraction", "realtime_factor",
                "ergodicity", "touched_fraction"):
        assert key in summary, key
    assert summary["config"]["steps"] == 15
