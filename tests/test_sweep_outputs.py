"""A sweep writes only its own files (issue 27): it refuses a folder it did not create, or one holding
another grid's sweep, unless --overwrite (then the new sweep replaces it whole once complete), never
mixes two grids, refuses a second sweep into a folder being written, and caps --jobs at the CPUs."""

from __future__ import annotations

import os

import pytest
from conftest import assert_one_line_error, run_cli
from test_bad_input_runs import hashes

GRID = """
steps = 15
seed = 1

[objects.bowl]
synthetic = "bowl"
marking = "X"
voxel = 0.01
agent_radius = 0.012

[grid]
start = 1
nk = [15]
alpha = [ALPHAS]
"""


def _grid(tmp_path, name: str, alphas: str):
    path = tmp_path / name
    path.write_text(GRID.replace("ALPHAS", alphas))
    return path


def sweep(grid, out, *args):
    return run_cli("sweep", grid, "--out", out, "--jobs", "1", "--no-plots", *args)


def test_a_folder_of_the_users_own_results_is_refused(tmp_path):
    """Today's bug: sweep --out into a folder holding the user's own results.csv overwrote it."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "results.csv").write_text("my,own\n1,2\n")
    before = hashes(out)
    assert_one_line_error(sweep(_grid(tmp_path, "g.toml", "5"), out), "did not write", "results.csv", "--overwrite")
    assert hashes(out) == before and sorted(p.name for p in out.iterdir()) == ["results.csv"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["g.toml", "mine"]  # no lock file, no temporary folder


def test_a_second_grid_is_refused_and_never_mixed(tmp_path):
    a, b = _grid(tmp_path, "a.toml", "5"), _grid(tmp_path, "b.toml", "10")
    out = tmp_path / "out"
    assert sweep(a, out).code == 0
    before = hashes(out)
    assert_one_line_error(sweep(b, out), "another grid", "a.toml", "--overwrite")
    assert hashes(out) == before
    again = sweep(a, out)  # the same grid (also from another file with the same content) resumes
    assert again.code == 0 and "(0 computed, 1 already done" in again.out, again.err
    (tmp_path / "a2.toml").write_text((tmp_path / "a.toml").read_text() + "# a comment\n")
    assert sweep(tmp_path / "a2.toml", out).code == 0


def test_overwrite_replaces_another_grids_sweep_whole(tmp_path):
    a, b = _grid(tmp_path, "a.toml", "5"), _grid(tmp_path, "b.toml", "10, 20")
    out = tmp_path / "out"
    assert sweep(a, out).code == 0
    res = sweep(b, out, "--overwrite")
    assert res.code == 0, res.err
    assert "(2 computed, 0 already done, 0 failed)" in res.out
    rows = (out / "results.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 and len(list((out / "runs").glob("*.json"))) == 2  # nothing of grid a is left
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.toml", "b.toml", "out"]


def test_overwrite_still_refuses_a_folder_that_is_not_a_sweeps(tmp_path):
    out = tmp_path / "home"
    out.mkdir()
    (out / "thesis.tex").write_text("mine")
    assert_one_line_error(sweep(_grid(tmp_path, "g.toml", "5"), out, "--overwrite"), "thesis.tex")
    assert (out / "thesis.tex").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == ["thesis.tex"]


def test_a_sweep_into_a_folder_being_written_is_refused(tmp_path):
    from tergodic_cli.atomic import AtomicFolder

    out = tmp_path / "out"
    holder = AtomicFolder(out, overwrite=True, what="sweep")
    holder.check(renamed=False)
    try:
        assert_one_line_error(sweep(_grid(tmp_path, "g.toml", "5"), out), "being written by another tergodic process")
    finally:
        holder.release()
    assert not out.exists()


def test_jobs_are_capped_at_the_cpus(tmp_path):
    out = tmp_path / "out"
    res = run_cli("sweep", _grid(tmp_path, "g.toml", "5"), "--out", out, "--jobs", "500", "--no-plots", "--json")
    assert res.code == 0, res.err
    cpus = os.cpu_count()
    assert f"note: --jobs 500 is more than the {cpus} CPUs; using {cpus}" in res.err
    import json

    assert json.loads((out / "sweep.json").read_text())["jobs"] == cpus
