"""``tergodic sweep``: a tiny grid run in-process, on a local process pool and on a local Ray
cluster gives identical results; runs resume; the table matches a direct explorer run; bad
grids are refused with one line."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

from tergodic_cli.sweep import load_grid, read_table, run_sweep
from tergodic_cli.sweep.runner import TIMING_COLUMNS

GRID = """
steps = 40
seed = 3

[objects.plate]
synthetic = "plate"
marking = "dots"
voxel = 0.006
agent_radius = 0.012

[objects.bowl]
synthetic = "bowl"
marking = "X"
voxel = 0.006
neighbors = 25
agent_radius = 0.012
a_max = 0.006

[grid]
start = 2
nk = [20, 40]
alpha = [5, "50:10@20"]
"""


@pytest.fixture
def grid(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text(GRID)
    return path


def _strip(rows):
    return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows]


def _series(out):
    with np.load(out / "series.npz", allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _same(out_a, out_b):
    assert _strip(read_table(out_a / "results.csv")) == _strip(read_table(out_b / "results.csv"))
    a, b = _series(out_a), _series(out_b)
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k


def test_grid_expands_to_objects_x_starts_x_options(grid):
    g = load_grid(grid)
    assert g.n_runs == 2 * 2 * 2 * 2
    assert [o.name for o in g.objects] == ["plate", "bowl"]
    assert g.options == {"nk": [20, 40], "alpha": ["5", "50:10@20"]}
    assert g.objects[1].neighbors == 25 and g.objects[1].explore == {"agent_radius": 0.012, "a_max": 0.006}


def test_tiny_sweep_in_process_and_on_a_process_pool_agree_and_resume(grid, tmp_path):
    one = run_sweep(grid, tmp_path / "one", jobs=1, plots=False)
    assert (one.n_runs, one.computed, one.skipped, one.failed) == (16, 16, 0, [])
    rows = read_table(tmp_path / "one" / "results.csv")
    assert len(rows) == 16 and {r["object"] for r in rows} == {"plate", "bowl"}
    assert all(r["steps"] == 40 and 0 < r["residual_ref"] <= 1 for r in rows)
    assert _series(tmp_path / "one")["ergodicity"].shape == (16, 40)
    pool = run_sweep(grid, tmp_path / "pool", jobs=2, plots=True)
    assert pool.computed == 16, pool.failed
    _same(tmp_path / "one", tmp_path / "pool")
    for name in ("eps_vs_nk.png", "eps_t.png", "eps_t_alpha.png"):
        assert (tmp_path / "pool" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert not (tmp_path / "pool" / "eps_vs_alpha.png").exists()  # one numeric α (the other is a schedule)
    # A crash loses nothing finished: drop three runs (as if the sweep died before them) and
    # the table; the rerun computes exactly those three and rebuilds the same table.
    runs = sorted((tmp_path / "one" / "runs").glob("*.json"))
    for p in runs[:3]:
        p.unlink()
    (tmp_path / "one" / "results.csv").unlink()
    again = run_sweep(grid, tmp_path / "one", jobs=1, plots=False)
    assert (again.computed, again.skipped) == (3, 13)
    _same(tmp_path / "one", tmp_path / "pool")


def test_a_table_row_is_the_explorer_run_it_names(grid, tmp_path):
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture import load_capture
    from tergodic_cli.explore import ExploreConfig, Explorer

    run_sweep(grid, tmp_path / "s", jobs=1, plots=False)
    row = next(r for r in read_table(tmp_path / "s" / "results.csv")
               if r["object"] == "bowl" and r["nk"] == 20 and r["alpha"] == "50:10@20" and r["start"] == 1)
    cap = load_capture(tmp_path / "s" / "objects" / "bowl")
    basis, _ = get_basis(cap.points, BasisConfig(nk=40, neighbors=25))
    cfg = ExploreConfig(steps=40, nk=20, alpha="50:10@20", agent_radius=0.012, a_max=0.006, seed=3, basis_neighbors=25)
    ex = Explorer(basis.truncated(20), cap.target, cfg, np.array([[row["start_x"], row["start_y"], row["start_z"]]]))
    for _ in range(40):
        ex.step()
    m = ex.metrics()
    assert row["ergodicity"] == m["ergodicity"] and row["residual_ref"] == m["residual_ref"]
    assert row["touched_fraction"] == m["touched_fraction"]
    # Random starts are seeded cloud points.
    assert np.min(np.linalg.norm(cap.points - [row["start_x"], row["start_y"], row["start_z"]], axis=1)) == 0.0


def test_the_sweep_verb_writes_the_table_and_reports_counts(grid, tmp_path):
    res = run_cli("sweep", grid, "--out", tmp_path / "cli", "--jobs", "1", "--no-plots", "--json")
    assert res.code == 0, res.err
    summary = json.loads(res.out)
    assert (summary["runs"], summary["computed"], summary["failed"]) == (16, 16, 0)
    assert {"results.csv", "series.npz", "sweep.json"} <= set(summary["files"])
    res = run_cli("sweep", grid, "--out", tmp_path / "cli", "--jobs", "1", "--no-plots")
    assert res.code == 0 and "0 computed, 16 already done" in res.out


def test_parquet_table_equals_the_csv(grid, tmp_path):
    pq = pytest.importorskip("pyarrow.parquet")
    run_sweep(grid, tmp_path / "p", jobs=1, plots=False, parquet=True)
    table = pq.read_table(tmp_path / "p" / "results.parquet").to_pylist()
    rows = read_table(tmp_path / "p" / "results.csv")
    assert len(table) == len(rows) == 16
    assert [r["residual_ref"] for r in table] == [r["residual_ref"] for r in rows]


@pytest.mark.slow
def test_tiny_sweep_on_a_local_ray_cluster_equals_the_local_run(grid, tmp_path):
    ray = pytest.importorskip("ray")
    run_sweep(grid, tmp_path / "local", jobs=2, plots=False)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        res = run_sweep(grid, tmp_path / "ray", engine="ray", plots=False)
    finally:
        ray.shutdown()
    assert (res.computed, res.failed) == (16, [])
    _same(tmp_path / "local", tmp_path / "ray")


def test_ray_engine_without_ray_is_one_line_with_an_install_hint(grid, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    res = run_cli("sweep", grid, "--out", tmp_path / "r", "--engine", "ray")
    assert_one_line_error(res, "ray", "pip install")
    assert not (tmp_path / "r" / "results.csv").exists()


@pytest.mark.parametrize("text, needle", [
    ("steps = 10\n[grid]\nnk = [10]\n", "no [objects"),
    ("[objects.a]\nsynthetic = 'plate'\nfile = 'x.ply'\n", "exactly one of"),
    ("[objects.a]\nsynthetic = 'plate'\ncolour = 1\n", "unknown key colour"),
    ("[objects.a]\nsynthetic = 'plate'\n[grid]\nnk = [0]\n", "nk"),
    ("[objects.a]\nsynthetic = 'plate'\n[grid]\nalpha = [10, 0]\n", "alpha"),
    ("[objects.a]\nsynthetic = 'plate'\n[grid]\nspeed = [1]\n", "speed is not an explore option"),
    ("[objects.a]\nsynthetic = 'plate'\n[grid]\nsteps = [1]\n", "cannot vary"),
    ("[objects.a]\nfile = 'missing.ply'\n", "does not exist"),
    ("[objects.a]\nsynthetic = 'plate'\nstarts = 'nope.npz'\n", "does not exist"),
    ("[objects.a\n", "not valid TOML"),
    ("[objects.a]\nsynthetic = 'plate'\n[grid]\nstart = 0\n", "start"),
])
def test_bad_grids_are_one_line_and_write_nothing(tmp_path, text, needle):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    res = run_cli("sweep", path, "--out", tmp_path / "out")
    assert_one_line_error(res, needle)
    assert not (tmp_path / "out").exists()
