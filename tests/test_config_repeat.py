"""The configs are the single source of truth: each verb option is built from a config field's Option,
and every kind of run (kinematic, closed loop, a hardware dry run) is saved in config.json and repeated
exactly by --config."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from conftest import REPO, run_cli

from tergodic_cli.config import options_of
from tergodic_cli.explore import ExploreConfig
from tergodic_cli.robot import RobotConfig
from tergodic_cli.robot.safety import SafetyConfig
from tergodic_cli.runspec import ClosedLoopSpec, HardwareSpec, LogSpec, StartSpec

BOWL = REPO / "data" / "bowl"
SOURCES = (ExploreConfig, StartSpec, LogSpec, RobotConfig, SafetyConfig, ClosedLoopSpec, HardwareSpec)


def _field_default(cls, name):
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    return f.default if f.default is not dataclasses.MISSING else None


def test_every_config_option_is_an_explore_option_with_the_fields_default():
    from tergodic_cli.commands.explore import explore

    params = explore.__signature__.parameters
    for cls in SOURCES:
        for name, opt in options_of(cls):
            assert opt.name in params, (cls.__name__, name)
            info = params[opt.name].default
            assert opt.flag.split("/")[0] in info.param_decls[0], (opt.flag, info.param_decls)
            # a parsed option (text on the command line) is None when not given: the field's default applies
            want = None if opt.parse is not None else _field_default(cls, name)
            assert info.default == want, (name, info.default, want)
            assert info.help == opt.help_text() or info.help.startswith(opt.help_text().rstrip(".")), name
    # each option once, and the old names kept (a script using them still runs)
    for flag in ("--steps", "--agents", "--fit-neighbors", "--neighbors", "--force", "--force-limit", "--workspace",
                 "--object-pose", "--gains", "--arm", "--recapture-every", "--until-clean", "--max-steps", "--robot-ip",
                 "--ft", "--ft-address", "--dry-run", "--start", "--starts", "--start-index", "--live", "--live-wait",
                 "--log-cloud-every", "--seed", "--epsilon"):
        assert sum(flag == p.default.param_decls[0].split("/")[0] for p in params.values()
                   if getattr(p.default, "param_decls", None)) == 1, flag


def test_the_help_shows_each_fields_default_and_unit_once():
    res = run_cli("explore", "--help")
    assert res.code == 0
    flat = " ".join(res.out.split())
    assert "[robot] Desired contact force along the tool axis, N. [default: 5.0]" in flat  # RobotConfig.force
    assert "Speed limit (paper: 0.003), m/s. [default: 0.003]" in flat  # ExploreConfig.v_max
    assert "[default: 0.15,-0.6,-0.01,0.85,0.6,0.9]" in flat  # SafetyConfig.workspace_min/max, from the fields
    assert "[default: 20% of --force]" in flat


def test_robot_options_map_onto_the_robot_config():
    from tergodic_cli.commands._options import values
    from tergodic_cli.run import make_robot_config

    opts = {"force": 3.0, "workspace": "0.1,-0.5,0,0.8,0.5,0.8", "gains": "paper", "object_pose": "0.5,0,0.2",
            "force_limit": 12.0}
    given = set(opts)
    rc = make_robot_config(RobotConfig, {**values(RobotConfig, opts, given), "safety": values(SafetyConfig, opts, given)})
    assert rc.force == 3.0 and rc.object_pose == (0.5, 0.0, 0.2)
    assert rc.safety.workspace_min == (0.1, -0.5, 0.0) and rc.safety.workspace_max == (0.8, 0.5, 0.8)
    assert rc.safety.force_limit == 12.0 and rc.gains.pid_wrench  # the paper's gains (V-A3): PID on the wrench


def _summary(run):
    """summary.json without what a repeat cannot share: timings, times of day and where it was written."""
    s = json.loads((run / "summary.json").read_text())

    def clean(v):
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items() if k != "ms" and not any(t in k for t in ("_ms", "_s", "seconds", "time", "files",
                                                                                     "provenance", "versions", "path", "cache_hit"))}
        if isinstance(v, list):
            return [clean(x) for x in v]
        return v

    return clean(s)


def _positions(run):
    with np.load(run / "trajectory.npz", allow_pickle=False) as t:
        return t["positions"]


def test_a_kinematic_run_repeats_from_its_config(tmp_path):
    res = run_cli("explore", BOWL, "--steps", "30", "--nk", "40", "--seed", "3", "--agents", "2", "--fit-neighbors",
                  "16", "--no-log", "--out", tmp_path / "a")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["explore"]["n_agents"] == 2 and conf["explore"]["n_neighbors"] == 16
    assert conf["closed_loop"] is None and conf["hardware"] is None
    res = run_cli("explore", BOWL, "--config", tmp_path / "a" / "config.json", "--no-log", "--out", tmp_path / "b")
    assert res.code == 0, res.err
    assert np.array_equal(_positions(tmp_path / "a"), _positions(tmp_path / "b"))
    assert _summary(tmp_path / "a") == _summary(tmp_path / "b")


@pytest.mark.long
def test_a_closed_loop_run_repeats_from_its_config(tmp_path):
    cap = tmp_path / "cap"
    res = run_cli("capture", "--source", "sim", "--object", "plate", "--width", "160", "--height", "120",
                  "--voxel", "0.006", "--out", cap)
    assert res.code == 0, res.err
    common = ("--no-log", "--nk", "40")
    res = run_cli("explore", cap, "--robot", "pybullet", "--recapture-every", "6", "--until-clean", "0.02",
                  "--max-steps", "12", "--steps", "12", "--seed", "1", *common, "--out", tmp_path / "a")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["closed_loop"] == {"recapture_every": 6, "until_clean": 0.02, "max_steps": 12}
    first = _summary(tmp_path / "a")
    assert first.get("recaptures", 0) >= 1, first  # it was a closed loop
    res = run_cli("explore", cap, "--config", tmp_path / "a" / "config.json", *common, "--out", tmp_path / "b")
    assert res.code == 0, res.err
    assert json.loads((tmp_path / "b" / "config.json").read_text())["closed_loop"] == conf["closed_loop"]
    assert np.array_equal(_positions(tmp_path / "a"), _positions(tmp_path / "b"))
    assert _summary(tmp_path / "b") == first


@pytest.fixture
def plate_capture(tmp_path_factory):
    from fakes import scenario

    from tergodic_cli.capture import save_capture

    plate = scenario.make_plate()
    folder = tmp_path_factory.mktemp("plate") / "cap"
    save_capture(plate.capture, folder)
    return plate, folder


def test_a_hardware_dry_run_is_saved_and_repeated(plate_capture, tmp_path, monkeypatch):
    pytest.importorskip("pygafro")
    from fakes import install, scenario

    plate, folder = plate_capture
    install(monkeypatch, "franky")
    bota = install(monkeypatch, "bota_driver")
    world = scenario.world(plate, monkeypatch, noise=0.0)
    monkeypatch.setattr(bota, "_WORLD", world)
    pose = ",".join(f"{v:.6f}" for v in plate.T_obj[:3, 3])
    res = run_cli("explore", folder, "--robot", "franka", "--robot-ip", scenario.ROBOT_IP, "--ft", "bota",
                  "--ft-address", "dummy", "--object-pose", pose, "--force", "4", "--start", "0.03,0.02,0",
                  "--dry-run", "--out", tmp_path / "a")
    assert res.code == 0, res.err
    assert "nothing was moved" in res.out and "press 4 N" in res.out
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["robot"] == "franka" and conf["robot_options"]["force"] == 4.0
    assert conf["hardware"] == {"robot_ip": scenario.ROBOT_IP, "ft": "bota", "ft_address": "dummy", "dry_run": True}
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == ["config.json"]  # a dry run writes nothing else
    again = run_cli("explore", folder, "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "b")
    assert again.code == 0, again.err

    def report(text):  # the plan, without the line naming the file it wrote
        return [ln for ln in text.splitlines() if not ln.startswith("wrote ")]

    assert report(again.out) == report(res.out)
    assert json.loads((tmp_path / "b" / "config.json").read_text()) == conf
    assert world.robot.moves == []  # neither run moved the arm
    # an option given beside --config wins over the saved one, in the plan and in the file it writes
    third = run_cli("explore", folder, "--config", tmp_path / "a" / "config.json", "--force", "6", "--out", tmp_path / "c")
    assert third.code == 0, third.err
    assert "press 6 N" in third.out
    assert json.loads((tmp_path / "c" / "config.json").read_text())["robot_options"]["force"] == 6.0
    assert math.isclose(json.loads((tmp_path / "c" / "config.json").read_text())["robot_options"]["object_pose"][0],
                        plate.T_obj[0, 3], abs_tol=1e-6)
