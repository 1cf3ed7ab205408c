"""Sheet separation (issue 25, item 2): how far the agent runs from the mesh a cloud was sampled from.

A hollow object's wall is two sheets (outside and inside) a wall's thickness apart; when that is
close to the sampling the agent's fit neighbourhood can hold both, and the agent then runs between
them, inside the material. Here: pybullet_data's shape sorter (toys/shape_sorter.obj, scaled by 0.5:
a 0.2 m box with 10 mm walls), Poisson-disk sampled with open3d at about ``--spacing`` (6.7 mm),
two red discs (25 mm radius) on the outside of its holed face (turned up, +z), written as a coloured
PLY and captured with the project's pipeline (voxel = spacing). For every step: the agent's unsigned
distance to the mesh (open3d RaycastingScene), the run's off-surface figure and ε.

    python benchmarks/sheets.py                        # 5 starts, 1000 steps
    python benchmarks/sheets.py --starts 3 --steps 500 --json out.json
    python benchmarks/sheets.py --no-sheets            # as before sheet separation
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

#: The distance to the mesh a tool can follow (issue 25's goal: 99 % of steps within it), metres.
LIMIT = 0.0015


def shape_sorter(spacing: float, seed: int = 0):
    """(open3d TriangleMesh in metres, points (n, 3), colours (n, 3)): the sampled shape sorter."""
    import open3d as o3d
    import pybullet_data

    mesh = o3d.io.read_triangle_mesh(os.path.join(pybullet_data.getDataPath(), "toys", "shape_sorter.obj"))
    mesh.scale(0.5, center=np.zeros(3))
    # its holed face is the -x face: turn it up (+z)
    mesh.rotate(np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), center=np.zeros(3))
    o3d.utility.random.seed(seed)
    area = mesh.get_surface_area()
    n = int(area / (0.866 * spacing * spacing))  # hexagonal packing at the spacing
    pcd = mesh.sample_points_poisson_disk(n, init_factor=5)
    pts = np.asarray(pcd.points)
    top = pts[:, 2].max()
    centres = np.array([[0.04, 0.03, top], [-0.05, -0.045, top]])
    mark = np.zeros(len(pts), bool)
    for c in centres:
        mark |= (np.abs(pts[:, 2] - top) < 1e-6) & (np.linalg.norm(pts[:, :2] - c[:2], axis=1) < 0.025)
    colours = np.where(mark[:, None], [0.85, 0.1, 0.1], [0.7, 0.7, 0.7])
    return mesh, pts, colours


def mesh_distance(mesh, x: np.ndarray) -> np.ndarray:
    """Unsigned distance (metres) from each of ``x`` (m, 3) to the mesh."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(x, dtype=np.float32))).numpy().astype(float)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spacing", type=float, default=0.0067, help="sampling and voxel, metres [default: 0.0067]")
    ap.add_argument("--starts", type=int, default=5)
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--no-sheets", action="store_true",
                    help="every neighbour in the fits, as before sheet separation (the sheet gap set to inf)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.capture.readers import write_ply
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.explore import kernels as K

    tmp = Path(tempfile.mkdtemp(prefix="tergodic-sheets-"))
    mesh, pts, colours = shape_sorter(args.spacing)
    write_ply(tmp / "sorter.ply", pts, colours)
    cap = capture_cloud(CaptureConfig(source="file", path=str(tmp / "sorter.ply"), voxel=args.spacing),
                        on_event=lambda msg: None)
    basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=30), str(tmp / "cache"))
    starts = cap.points[np.random.default_rng(0).choice(np.flatnonzero(cap.target > 0), args.starts, replace=False)]
    print(f"shape sorter: {cap.n_points} points, h {basis.h * 1e3:.2f} mm, target {int((cap.target > 0).sum())}")
    print("| start | ε | touched | steps > 1.5 mm from the mesh | 99th pct | max | off-surface figure | step |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for s, x0 in enumerate(starts):
        ex = Explorer(basis, cap.target, ExploreConfig(steps=args.steps, agent_radius=0.0075), x0[None],
                      on_event=lambda msg: None)
        if args.no_sheets:
            ex._prm[K.PR_SHEET_GAP] = np.inf
        xs, ms = np.empty((args.steps, 3)), np.empty(args.steps)
        for k in range(args.steps):
            ex.step()
            xs[k], ms[k] = ex.positions[0], ex.last_step_ms
        d = mesh_distance(mesh, xs)
        sc = ex.score()
        r = {"start": s, "ergodicity": sc["ergodicity"], "touched": sc["touched_fraction"],
             "far_share": float(np.mean(d > LIMIT)), "d99_mm": 1e3 * float(np.percentile(d, 99)),
             "dmax_mm": 1e3 * float(d.max()), "off_surface_fraction": sc["off_surface_fraction"],
             "step_us": 1e3 * float(np.median(ms))}
        rows.append(r)
        print(f"| {s} | {r['ergodicity']:.3f} | {100 * r['touched']:.1f}% | {100 * r['far_share']:.1f}% | "
              f"{r['d99_mm']:.2f} mm | {r['dmax_mm']:.2f} mm | {100 * r['off_surface_fraction']:.1f}% | "
              f"{r['step_us']:.0f} µs |", flush=True)
    med = {k: float(np.median([r[k] for r in rows])) for k in ("ergodicity", "far_share", "off_surface_fraction")}
    print(f"\nmedian: ε {med['ergodicity']:.3f}, steps > 1.5 mm {100 * med['far_share']:.1f}%, "
          f"off-surface figure {100 * med['off_surface_fraction']:.1f}%; all steps > 1.5 mm: "
          f"{100 * np.mean([r['far_share'] for r in rows]):.1f}%")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
