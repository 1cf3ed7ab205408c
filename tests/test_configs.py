"""Loadable configs: each stage's config.json beside its artefact repeats it; options given beside --config override it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import REPO, assert_one_line_error, run_cli

from tergodic_cli.basis import BasisConfig
from tergodic_cli.capture import CaptureConfig
from tergodic_cli.config import from_dict, to_dict
from tergodic_cli.backends.pybullet.camera import SimCameraConfig
from tergodic_cli.capture.textured import SimObjectConfig
from tergodic_cli.errors import TergodicError
from tergodic_cli.explore import ExploreConfig
from tergodic_cli.robot import RobotConfig
from tergodic_cli.robot.controller import ControllerGains

BOWL = REPO / "data" / "bowl"


@pytest.mark.parametrize("cfg", [
    ExploreConfig(alpha="50:10@200", epsilon=300.0, normal_hint=(0.0, 1.0, 0.0)),
    RobotConfig(force=4.0, object_pose=(0.5, 0.0, 0.2), gains=ControllerGains(kp=1.5, k_rot=(1.0, 2.0, 3.0))),
    CaptureConfig(crop=(-0.1, -0.1, 0.0, 0.1, 0.1, 0.2), outliers=(20, 2.0), colour_depth=16),
    BasisConfig(nk=80, neighbors=40),
    SimObjectConfig(pose=(0.5, 0.0, 0.0, 0.0, 0.0, 90.0)),
    SimCameraConfig(pose=(0.3, 0.0, 0.6, 0.5, 0.0, 0.0), width=320),
])
def test_every_stage_config_round_trips_through_json(cfg):
    d = json.loads(json.dumps(to_dict(cfg)))
    again = from_dict(type(cfg), d)
    assert again == cfg and type(again) is type(cfg)
    assert from_dict(type(cfg), {}) == type(cfg)()  # missing keys keep their defaults


@pytest.mark.parametrize("d, needle", [({"forse": 5.0}, "unknown key 'forse'"), ({"force": "5"}, "force is not a number"),
                                       ({"gains": {"k_trans": [1.0, 2.0]}}, "gains.k_trans needs 3 values"),
                                       ({"safety": 3}, "safety is not a JSON object"),
                                       ({"solver_iterations": 2.5}, "solver_iterations is not an int")])
def test_a_bad_config_names_the_key(d, needle):
    with pytest.raises(TergodicError, match=needle.replace("[", r"\[")):
        RobotConfig.from_dict(d)


def _arrays(folder):
    with np.load(folder / "cloud.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_a_capture_repeats_from_its_config_and_options_override_it(tmp_path):
    res = run_cli("capture", "--synthetic", "plate", "--marking", "dots", "--seed", "3", "--noise", "0.001",
                  "--voxel", "0.006", "--out", tmp_path / "a")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["kind"] == "tergodic.capture_config" and conf["capture"]["seed"] == 3
    assert conf["capture"]["noise"] == 0.001 and conf["capture"]["marking"] == "dots"
    assert run_cli("capture", "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "b").code == 0
    assert run_cli("capture", "--config", tmp_path / "a" / "config.json", "--seed", "4", "--out", tmp_path / "c").code == 0
    a, b, c = (_arrays(tmp_path / n) for n in "abc")
    assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)  # the same capture, bit for bit
    assert not np.array_equal(a["points"], c["points"])  # another noise draw
    conf_c = json.loads((tmp_path / "c" / "config.json").read_text())
    assert conf_c["capture"]["seed"] == 4 and conf_c["capture"]["noise"] == 0.001  # the rest as saved


def test_a_sim_capture_repeats_with_its_camera_and_object(tmp_path):
    res = run_cli("capture", "--source", "sim", "--object", "plate", "--width", "160", "--height", "120",
                  "--object-pose", "0.5,0.02,0", "--voxel", "0.006", "--out", tmp_path / "a")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["camera"]["width"] == 160 and conf["object"]["pose"] == [0.5, 0.02, 0.0]
    assert run_cli("capture", "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "b").code == 0
    assert run_cli("capture", "--config", tmp_path / "a" / "config.json", "--object-pose", "0.5,-0.02,0",
                   "--out", tmp_path / "c").code == 0
    a, b, c = (_arrays(tmp_path / n) for n in "abc")
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not np.array_equal(a["points"], c["points"])


def test_a_basis_entry_carries_its_config_and_precompute_repeats_it(tmp_path):
    cap = tmp_path / "cap"
    assert run_cli("capture", "--synthetic", "plate", "--voxel", "0.006", "--out", cap).code == 0
    res = run_cli("precompute", cap, "--nk", "30", "--neighbors", "20", "--cache-dir", tmp_path / "c1", "--json")
    assert res.code == 0, res.err
    entry = tmp_path / "c1" / "basis" / json.loads(res.out)["key"]
    conf = json.loads((entry / "config.json").read_text())
    assert conf["kind"] == "tergodic.basis_config" and conf["basis"]["nk"] == 30 and conf["basis"]["neighbors"] == 20
    again = run_cli("precompute", cap, "--config", entry / "config.json", "--cache-dir", tmp_path / "c2", "--json")
    assert again.code == 0, again.err
    assert json.loads(again.out)["key"] == entry.name  # the same basis (the key hashes every parameter)
    other = run_cli("precompute", cap, "--config", entry / "config.json", "--nk", "20", "--cache-dir", tmp_path / "c2",
                    "--json")
    assert other.code == 0 and json.loads(other.out)["config"] == {**conf["basis"], "nk": 20}


def _positions(run):
    with np.load(run / "trajectory.npz", allow_pickle=False) as t:
        return t["positions"]


@pytest.mark.long
def test_a_pybullet_run_repeats_with_its_robot_options_and_an_override_changes_it(tmp_path):
    common = ("--no-log", "--nk", "60")
    res = run_cli("explore", BOWL, "--robot", "pybullet", "--force", "3", "--steps", "12", "--seed", "1", *common,
                  "--out", tmp_path / "a")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["robot"] == "pybullet" and conf["robot_options"]["force"] == 3.0
    assert conf["robot_options"]["gains"] == ControllerGains().to_dict()  # the whole robot config, gains and limits
    assert "force_limit_factor" in conf["robot_options"]["safety"]
    cfg_path = tmp_path / "a" / "config.json"
    res = run_cli("explore", BOWL, "--config", cfg_path, *common, "--out", tmp_path / "b")
    assert res.code == 0, res.err
    res = run_cli("explore", BOWL, "--config", cfg_path, "--force", "8", *common, "--out", tmp_path / "c")
    assert res.code == 0, res.err
    a, b, c = (_positions(tmp_path / n) for n in "abc")
    assert len(a) == 12 and np.array_equal(a, b)  # the same trajectory, bit for bit
    assert not np.array_equal(a, c)
    assert json.loads((tmp_path / "c" / "config.json").read_text())["robot_options"]["force"] == 8.0


@pytest.mark.parametrize("verb, content, needle", [
    ("capture", "{not json", "not readable JSON"),
    ("capture", '{"kind": "tergodic.run_config"}', "not a capture config"),
    ("capture", '{"kind": "tergodic.capture_config", "capture": {"voxle": 0.003}}', "unknown key 'voxle'"),
    ("precompute", '{"kind": "tergodic.basis_config", "basis": {"nk": "many"}}', "nk is not an int"),
    ("explore", '{"kind": "tergodic.run_config", "explore": {}, "robot": "pybullet", "robot_options": {"forse": 5}}',
     "unknown key 'forse'"),
    ("explore", '{"kind": "tergodic.run_config", "explore": {"steps": 2.5}}', "steps is not an int"),
    # issue 27: accepted before
    ("precompute", '{"kind": "tergodic.basis_config", "version": 1, "basis": {"solver": "magic"}}',
     "unknown basis solver 'magic'"),
    ("precompute", '{"kind": "tergodic.basis_config", "version": 99, "basis": {}}', "version 99"),
    ("explore", '{"kind": "tergodic.run_config", "version": 99, "explore": {}}', "version 99"),
    ("capture", '{"kind": "tergodic.capture_config", "version": 1, "capture": {}, "format_version": 99}',
     "unknown key 'format_version'"),
    ("explore", '{"kind": "tergodic.run_config", "version": 1, "explore": {}, "explorer": {}}', "unknown key 'explorer'"),
    ("explore", '{"kind": "tergodic.run_config", "version": 1, "explore": {"seed": -4}}', "--seed must be"),
])
def test_a_bad_config_is_one_line_and_writes_nothing(tmp_path, verb, content, needle):
    path = tmp_path / "config.json"
    path.write_text(content)
    args = {"capture": ("capture",), "precompute": ("precompute", BOWL), "explore": ("explore", BOWL, "--no-log")}[verb]
    res = run_cli(*args, "--config", path, *(() if verb == "precompute" else ("--out", tmp_path / "out")))
    assert_one_line_error(res, needle)
    assert not (tmp_path / "out").exists()
