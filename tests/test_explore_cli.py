"""``tergodic explore`` end to end: artefacts, basis lookup, starts, determinism, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

from tergodic_cli.explore import summarize_run

SUMMARY_KEYS = {"steps", "ergodicity", "residual_ref", "touched_fraction", "ergodicity_at", "step_ms_median",
                "config", "seed", "versions"}


@pytest.fixture(scope="module")
def cap(tmp_path_factory):
    """A small synthetic plate with dots (≈ 1200 points at a 6 mm voxel)."""
    out = tmp_path_factory.mktemp("cap") / "plate"
    res = run_cli("capture", "--synthetic", "plate", "--marking", "dots", "--voxel", "0.006", "--out", out)
    assert res.code == 0, res.err
    return out


def _explore(cap, out, *extra):
    return run_cli("explore", cap, "--out", out, "--nk", "40", "--agent-radius", "0.012", "--no-log", *extra)


def _cache_entries(cache) -> int:
    return len(list((cache / "basis").glob("*/basis.json"))) if (cache / "basis").exists() else 0


def test_explore_from_a_fresh_capture_writes_trajectory_and_summary(cap, tmp_path, isolated_cache):
    run = tmp_path / "run"
    res = _explore(cap, run, "--steps", "60", "--start", "random", "--seed", "3")
    assert res.code == 0, res.err
    summary = json.loads((run / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(summary)
    assert summary["steps"] == 60 and summary["seed"] == 3 and summary["config"]["seed"] == 3
    assert summary["ergodicity_at"] == {"200": None, "500": None, "1000": None}
    assert summary["basis"]["cache_hit"] is False and _cache_entries(isolated_cache) == 1
    with np.load(run / "trajectory.npz", allow_pickle=False) as t:
        n = len(t["points"])
        assert t["positions"].shape == (60, 1, 3) and t["velocities"].shape == (60, 1, 3)
        assert t["normals"].shape == (60, 1, 3)
        np.testing.assert_allclose(np.linalg.norm(t["normals"], axis=2), 1.0, atol=1e-12)
        assert t["coverage"].shape == t["heat"].shape == t["target"].shape == (n,)
        assert t["ergodicity"].shape == (60,)
        # The summary is a pure function of the stored series.
        again = summarize_run({k: t[k] for k in ("ergodicity", "residual_ref", "touched_fraction", "step_ms")},
                              summary["config"], {k: summary[k] for k in summary if k not in (
                                  "steps", "ergodicity", "residual_ref", "touched_fraction", "ergodicity_at",
                                  "residual_ref_at", "touched_fraction_at", "step_ms_median", "seed", "config")})
        assert again == summary
    assert "explored 60 steps" in res.out


def test_json_output_equals_summary_file(cap, tmp_path):
    run = tmp_path / "run"
    res = _explore(cap, run, "--steps", "20", "--json")
    assert res.code == 0, res.err
    assert json.loads(res.out) == json.loads((run / "summary.json").read_text())


def test_logged_run_writes_an_mcap_log(cap, tmp_path):
    pytest.importorskip("tergodic_cli.runlog")
    run = tmp_path / "run"
    res = run_cli("explore", cap, "--out", run, "--nk", "40", "--agent-radius", "0.012", "--steps", "30",
                  "--log-cloud-every", "10")
    assert res.code == 0, res.err
    assert (run / "run.mcap").stat().st_size > 0
    assert "run.mcap" in json.loads((run / "summary.json").read_text())["files"]


def test_a_larger_cached_basis_is_reused_and_a_smaller_one_is_not(cap, tmp_path, isolated_cache):
    assert run_cli("precompute", cap, "--nk", "60").code == 0
    res = _explore(cap, tmp_path / "a", "--steps", "5", "--json")
    assert res.code == 0, res.err
    assert json.loads(res.out)["basis"]["cache_hit"] is True
    assert json.loads(res.out)["config"]["nk"] == 40
    assert _cache_entries(isolated_cache) == 1  # nothing new computed
    res = run_cli("explore", cap, "--out", tmp_path / "b", "--nk", "80", "--agent-radius", "0.012", "--steps", "5",
                  "--no-log", "--json")
    assert res.code == 0, res.err
    assert json.loads(res.out)["basis"]["cache_hit"] is False  # 60 < 80: computed
    assert _cache_entries(isolated_cache) == 2


def test_seeded_cli_runs_are_bit_identical(cap, tmp_path):
    arrays = []
    for name, seed in (("a", "7"), ("b", "7"), ("c", "8")):
        assert _explore(cap, tmp_path / name, "--steps", "40", "--seed", seed).code == 0
        with np.load(tmp_path / name / "trajectory.npz", allow_pickle=False) as t:
            arrays.append({k: t[k] for k in ("positions", "velocities", "coverage", "heat", "ergodicity")})
    for k in arrays[0]:
        assert np.array_equal(arrays[0][k], arrays[1][k]), k
    assert not np.array_equal(arrays[0]["positions"], arrays[2]["positions"])


def test_starts_file_and_index_and_several_agents(cap, tmp_path):
    with np.load(cap / "cloud.npz", allow_pickle=False) as c:
        pts = c["points"]
    starts = tmp_path / "x0.npz"
    np.savez(starts, x0_arr=pts[[10, 200, 400]] + np.array([0, 0, 0.001]))
    res = _explore(cap, tmp_path / "run", "--steps", "10", "--starts", starts, "--start-index", "1", "--agents", "2")
    assert res.code == 0, res.err
    with np.load(tmp_path / "run" / "trajectory.npz", allow_pickle=False) as t:
        np.testing.assert_allclose(t["start"], pts[[200, 400]] + [0, 0, 0.001])
        assert t["positions"].shape == (10, 2, 3)


@pytest.mark.parametrize("kind", ["x0", "starts", "npy", "csv"])
def test_starts_in_every_accepted_form_give_the_same_start(cap, tmp_path, kind):
    with np.load(cap / "cloud.npz", allow_pickle=False) as c:
        rows = c["points"][[10, 200]]
    path = tmp_path / {"npy": "s.npy", "csv": "s.csv"}.get(kind, "s.npz")
    if kind == "npy":
        np.save(path, rows)
    elif kind == "csv":
        np.savetxt(path, rows, delimiter=",", fmt="%.9f")
    else:
        np.savez(path, **{kind: rows})
    res = _explore(cap, tmp_path / "run", "--steps", "2", "--starts", path, "--start-index", "1")
    assert res.code == 0, res.err
    with np.load(tmp_path / "run" / "trajectory.npz", allow_pickle=False) as t:
        np.testing.assert_allclose(t["start"][0], rows[1], atol=1e-9)


def test_starts_of_the_wrong_shape_are_one_line(cap, tmp_path):
    path = tmp_path / "flat.npy"
    np.save(path, np.zeros(6))
    assert_one_line_error(_explore(cap, tmp_path / "r", "--starts", path), "(n, 3)")


def test_start_slightly_off_is_projected_with_a_warning(cap, tmp_path):
    with np.load(cap / "cloud.npz", allow_pickle=False) as c:
        p = c["points"][100] + np.array([0.0, 0.0, 0.008])
    res = _explore(cap, tmp_path / "run", "--steps", "3", "--start", ",".join(f"{v:.6f}" for v in p))
    assert res.code == 0, res.err
    assert "projected" in res.err


def test_small_agent_radius_warns(cap, tmp_path):
    res = run_cli("explore", cap, "--out", tmp_path / "run", "--nk", "40", "--agent-radius", "0.002", "--steps", "3",
                  "--no-log")
    assert res.code == 0, res.err
    assert "below the point spacing" in res.err


@pytest.mark.parametrize("args, needle", [
    (("--alpha", "0"), "alpha"),
    (("--alpha", "-3"), "alpha"),
    (("--alpha", "ten"), "alpha"),
    (("--alpha", "50:10@0"), "alpha"),
    (("--start", "5,5,5"), "from the cloud"),
    (("--start", "999999"), "index"),
    (("--start", "1,2"), "--start"),
    (("--agent-radius", "0"), "agent-radius"),
    (("--agent-radius", "7.5"), "millimetres"),
    (("--v-max", "3"), "millimetres"),
    (("--a-max", "30"), "millimetres"),
    (("--steps", "0"), "steps"),
    (("--diffusion", "magic"), "diffusion"),
    (("--integrator", "magic"), "integrator"),
    (("--coverage-norm", "marking"), "coverage-norm"),
    (("--robot", "hovercraft"), "robot"),
    (("--nk", "100000"), "nk"),
    (("--start-index", "2"), "--starts"),
])
def test_bad_input_is_one_line_and_exit_2_with_nothing_written(cap, tmp_path, args, needle):
    run = tmp_path / "run"
    res = run_cli("explore", cap, "--out", run, "--nk", "40", "--agent-radius", "0.012", "--steps", "5", "--no-log",
                  *args)
    assert_one_line_error(res, needle)
    assert not (run / "summary.json").exists() and not (run / "trajectory.npz").exists()


def test_coverage_norm_is_recorded_and_changes_the_run(cap, tmp_path):
    runs = {}
    for norm in ("target", "cloud"):
        res = _explore(cap, tmp_path / norm, "--steps", "150", "--start", "0", "--coverage-norm", norm)
        assert res.code == 0, res.err
        runs[norm] = json.loads((tmp_path / norm / "summary.json").read_text())
        assert runs[norm]["config"]["coverage_norm"] == norm
    default = _explore(cap, tmp_path / "default", "--steps", "1", "--start", "0")
    assert json.loads((tmp_path / "default" / "summary.json").read_text())["config"]["coverage_norm"] == "cloud", \
        default.err
    with np.load(tmp_path / "target" / "trajectory.npz") as a, np.load(tmp_path / "cloud" / "trajectory.npz") as b:
        assert np.abs(a["positions"] - b["positions"]).max() > 1e-3  # the agents went different ways


def test_bad_starts_files(cap, tmp_path):
    assert_one_line_error(_explore(cap, tmp_path / "r", "--starts", tmp_path / "missing.npz"), "does not exist")
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, points=np.zeros((2, 3)))
    assert_one_line_error(_explore(cap, tmp_path / "r", "--starts", wrong), "x0_arr")
    good = tmp_path / "good.npz"
    np.savez(good, x0_arr=np.zeros((2, 3)))
    assert_one_line_error(_explore(cap, tmp_path / "r", "--starts", good, "--start-index", "5"), "start-index")
    assert_one_line_error(_explore(cap, tmp_path / "r", "--starts", good, "--start", "random"), "both")


def test_empty_target_is_refused(tmp_path):
    from tergodic_cli.capture import Capture, save_capture
    from tergodic_cli.capture.synthetic import generate_synthetic

    cloud = generate_synthetic("plate", "dots", seed=0, spacing=0.006)
    save_capture(Capture(cloud.points, cloud.colors, np.zeros(len(cloud.points)), {"kind": "test"}), tmp_path / "cap")
    assert_one_line_error(_explore(tmp_path / "cap", tmp_path / "run"), "empty")


@pytest.mark.slow
def test_reference_bunny_start_0(reference, tmp_path):
    capture = tmp_path / "bunny"
    res = run_cli("capture", "--from", reference / "bun270_X.ply", "--voxel", "0.003", "--voxel-rule", "all",
                  "--out", capture)
    assert res.code == 0, res.err
    res = run_cli("explore", capture, "--out", tmp_path / "run", "--starts", reference / "starts" / "bun270_X.npz",
                  "--start-index", "0", "--neighbors", "40", "--steps", "1000", "--no-log", "--json")
    assert res.code == 0, res.err
    summary = json.loads(res.out)
    assert SUMMARY_KEYS <= set(summary)
    assert summary["capture"]["n_target"] == 210
    # 206 of the 210 target points; the other 4 are two stray pairs 3-6 cm off the X (docs/explore.md).
    assert summary["touched_fraction"] >= 0.98
    assert summary["ergodicity"] < 0.468  # the authors' code under the same score (issue 13)
    assert summary["off_surface_fraction"] == 0.0 and summary["step_max_m"] <= 0.003 * (1 + 1e-9)


def test_a_run_repeats_exactly_from_its_config_and_options_given_beside_it_override(cap, tmp_path):
    res = _explore(cap, tmp_path / "a", "--steps", "120", "--seed", "7", "--alpha", "20")
    assert res.code == 0, res.err
    conf = json.loads((tmp_path / "a" / "config.json").read_text())
    assert conf["explore"]["seed"] == 7 and conf["explore"]["alpha"] == "20" and conf["starts"]["start"] is None
    res = run_cli("explore", cap, "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "b", "--no-log")
    assert res.code == 0, res.err
    res = run_cli("explore", cap, "--config", tmp_path / "a" / "config.json", "--out", tmp_path / "c", "--no-log",
                  "--steps", "60")
    assert res.code == 0, res.err
    with np.load(tmp_path / "a" / "trajectory.npz") as a, np.load(tmp_path / "b" / "trajectory.npz") as b, \
            np.load(tmp_path / "c" / "trajectory.npz") as c:
        assert np.array_equal(a["positions"], b["positions"])  # the same trajectory, bit for bit
        assert len(c["positions"]) == 60 and np.array_equal(a["positions"][:60], c["positions"])
    assert json.loads((tmp_path / "c" / "config.json").read_text())["explore"]["steps"] == 60


@pytest.mark.parametrize("content, needle", [(None, "does not exist"), ("{not json", "not readable JSON"),
                                             ('{"kind": "other"}', "not a run config"),
                                             ('{"kind": "tergodic.run_config", "explore": {"stepz": 3}}', "unknown key 'stepz'")])
def test_a_bad_config_is_one_line(cap, tmp_path, content, needle):
    path = tmp_path / "config.json"
    if content is not None:
        path.write_text(content)
    res = run_cli("explore", cap, "--config", path, "--out", tmp_path / "run", "--no-log")
    assert_one_line_error(res, needle)
    assert not (tmp_path / "run").exists()
