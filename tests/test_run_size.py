"""The run's size guard (issue 27): memory and log estimated up front, a run that cannot fit refused."""

from __future__ import annotations

import numpy as np
from conftest import REPO, assert_one_line_error, run_cli

from tergodic_cli.run import estimate_run_size

SERIES = ("positions", "velocities", "normals", "accelerations", "time", "ergodicity", "residual_ref",
          "touched_fraction", "step_ms")


def test_memory_estimate_matches_the_series_a_run_keeps(tmp_path):
    res = run_cli("explore", REPO / "data" / "bowl", "--steps", "200", "--nk", "40", "--agents", "2",
                  "--out", tmp_path / "run", "--no-log")
    assert res.code == 0, res.err
    with np.load(tmp_path / "run" / "trajectory.npz", allow_pickle=False) as t:
        kept = sum(t[k].nbytes for k in SERIES)
        n = len(t["points"])
    memory, log = estimate_run_size(200, 2, n, None, robot=False)
    assert memory == kept
    assert log == 0


def test_log_estimate_is_the_size_of_a_real_log_within_a_factor_two(tmp_path):
    res = run_cli("explore", REPO / "data" / "bowl", "--steps", "300", "--nk", "40", "--out", tmp_path / "run",
                  "--log-cloud-every", "50")
    assert res.code == 0, res.err
    n = len(np.load(tmp_path / "run" / "trajectory.npz", allow_pickle=False)["points"])
    _, log = estimate_run_size(300, 1, n, 50, robot=False)
    size = (tmp_path / "run" / "run.mcap").stat().st_size
    assert size / 2 <= log <= 2 * size, (log, size)


def test_a_run_that_cannot_fit_in_memory_is_refused_before_work(tmp_path):
    res = run_cli("explore", REPO / "data" / "bowl", "--steps", str(10**13), "--out", tmp_path / "run")
    assert_one_line_error(res, "--steps", "memory", "fewer")
    assert not (tmp_path / "run").exists()


def test_an_npz_that_unpacks_beyond_the_cap_is_refused_before_unpacking(tmp_path, monkeypatch):
    """A few kilobytes of zip that unpack to 24 MB, against a cap lowered to 1 MB (the real cap is half
    the free memory): refused from the declared sizes, both as a cloud and as starts."""
    import tergodic_cli.capture.readers as readers

    monkeypatch.setattr(readers, "npz_cap", lambda: 1 << 20)
    cloud, starts = tmp_path / "bomb.npz", tmp_path / "starts.npz"
    np.savez_compressed(cloud, points=np.zeros((10**6, 3)))
    np.savez_compressed(starts, x0_arr=np.zeros((10**6, 3)))
    assert cloud.stat().st_size < 100_000
    assert_one_line_error(run_cli("capture", "--from", cloud, "--out", tmp_path / "cap"), "unpacks to", "free memory")
    assert_one_line_error(run_cli("explore", REPO / "data" / "bowl", "--starts", starts, "--out", tmp_path / "r"),
                          "unpacks to")
