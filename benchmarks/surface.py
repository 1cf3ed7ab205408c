"""The contact surface's figures, before and after issue 24: per object, how smooth and how close.

"before": ball pivoting decimated once to the curved edge (the former rule); "after": the surface
``tergodic explore --robot pybullet`` builds now (:func:`~tergodic_cli.robot.surface.reconstruct_mesh`:
screened Poisson cropped to the cloud, ball pivoting for open sheets, the decimation ladder), and,
for the corpus, the source mesh as a capture that holds it would use, and the distance of every
surface's vertices to that source mesh (the sponge must touch the object where it is). Figures from
:func:`~tergodic_cli.robot.surface.surface_figures`; "refused" is the check the run applies.

    python benchmarks/surface.py                         # corpus smooth objects at 3 mm + built-ins
    python benchmarks/surface.py --objects all           # every corpus mesh (tune and check)
    python benchmarks/surface.py --objects duck,bunny --densities 3mm,6mm --no-builtins
    python benchmarks/surface.py --objects duck,bunny --no-builtins --contact-cost   # + PyBullet cost

``--contact-cost``: a 12 mm ball (the sponge's contact parameters) pushed at 5 N onto 300 seeded
cloud points of each surface, 200 steps of 1 ms each; microseconds per step, medians of 3
alternating repeats, and the after/before ratio of the same run.
"""

from __future__ import annotations

if __name__ == "__main__":
    import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse
import math
import sys

import numpy as np

SMOOTH = ("duck", "bunny", "teddy", "sphere", "torus")
BUILTINS = ("bowl", "plate", "mug", "partial", "thin-mug", "box", "sphere", "torus", "holed-plate")


def figures(points, h, normals, mesh, rebuilt: bool) -> dict:
    from tergodic_cli.errors import TergodicError
    from tergodic_cli.robot.surface import check_surface, surface_figures

    f = surface_figures(mesh, points, h, normals)
    try:
        check_surface(f, rebuilt=rebuilt)
        f["refused"] = ""
    except TergodicError as e:
        f["refused"] = str(e).split(":")[0].split("(")[0].strip()
    return f


def row(name: str, what: str, f: dict, mesh=None, source=None) -> str:
    """One table row; with ``source`` (vertices, triangles), the distance of ``mesh``'s vertices to it."""
    sm = f["dihedral_smooth_p95_deg"]
    ex = f["fold_excess_p95_deg"]
    to_source = "-"
    if source is not None and mesh is not None:
        from tergodic_cli.capture.mesh import mesh_distance

        d = 1e3 * mesh_distance(source[0], source[1], mesh.vertices)
        to_source = f"{np.percentile(d, 95):.2f} / {d.max():.2f}"
    return (f"| {name} | {what} | {f['method']} | {f['triangles']} | {f['dihedral_p95_deg']:.1f} | "
            f"{'-' if sm is None else f'{sm:.1f}'} | {'-' if ex is None else f'{ex:.1f}'} | {f['border_edges']} | "
            f"{100 * f['coverage']:.1f} | {f['surface_to_cloud_p95_mm']:.2f} / {f['spacing_mm']:.2f} | {to_source} | "
            f"{f['build_seconds']:.2f} | {f['refused'] or 'no'} |")


def step_cost(mesh, points: np.ndarray, normals: np.ndarray, n: int = 300, ticks: int = 200) -> float:
    """Microseconds per 1 ms PyBullet step of a 12 mm ball pushed at 5 N onto ``mesh`` at n cloud points."""
    import time

    import pybullet as pb

    cid = pb.connect(pb.DIRECT)
    try:
        pb.setTimeStep(0.001, physicsClientId=cid)
        col = pb.createCollisionShape(pb.GEOM_MESH, vertices=mesh.vertices.tolist(), indices=mesh.triangles.ravel().tolist(),
                                      flags=pb.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=cid)
        pb.createMultiBody(0, col, physicsClientId=cid)
        ball = pb.createMultiBody(0.5, pb.createCollisionShape(pb.GEOM_SPHERE, radius=0.012, physicsClientId=cid),
                                  physicsClientId=cid)
        pb.changeDynamics(ball, -1, contactStiffness=5000, contactDamping=500, physicsClientId=cid)
        total = 0.0
        for i in np.random.default_rng(0).choice(len(points), min(n, len(points)), replace=False):
            c = points[i] + 0.0115 * normals[i]
            pb.resetBasePositionAndOrientation(ball, c.tolist(), [0, 0, 0, 1], physicsClientId=cid)
            pb.resetBaseVelocity(ball, [0, 0, 0], [0, 0, 0], physicsClientId=cid)
            t0 = time.perf_counter()
            for _ in range(ticks):
                pb.applyExternalForce(ball, -1, (-5.0 * normals[i]).tolist(), c.tolist(), pb.WORLD_FRAME, physicsClientId=cid)
                pb.stepSimulation(physicsClientId=cid)
            total += time.perf_counter() - t0
        return 1e6 * total / (min(n, len(points)) * ticks)
    finally:
        pb.disconnect(cid)


def compare(name: str, points: np.ndarray, source=None, cost: bool = False) -> list[str]:
    from tergodic_cli.capture.filters import mean_spacing
    from tergodic_cli.robot.surface import curved_edge, oriented_normals, reconstruct_mesh, source_mesh

    h = mean_spacing(points)
    n = oriented_normals(points, "outward")
    e = curved_edge(points, n, 0.01)  # RobotConfig.mesh_edge's default, finer on tight curves
    before = reconstruct_mesh(points, n, h, e, "ball_pivoting", math.inf)
    after = reconstruct_mesh(points, n, h, e)
    out = [row(name, "before", figures(points, h, n, before, True), before, source),
           row(name, "after", figures(points, h, n, after, True), after, source)]
    if cost:
        us = {"before": [], "after": []}
        for _ in range(3):
            for k, m in (("before", before), ("after", after)):
                us[k].append(step_cost(m, points, n))
        b, a = float(np.median(us["before"])), float(np.median(us["after"]))
        out.append(f"| {name} | contact cost | | | before {b:.0f} us/step, after {a:.0f} us/step: x{a / b:.2f} | | | | | | | | |")
    if source is not None:
        sm = source_mesh(source, 0.01)
        out.append(row(name, "source mesh", figures(points, h, n, sm, False), sm, source))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--objects", default=",".join(SMOOTH), help="corpus meshes (benchmarks/corpus.py)")
    ap.add_argument("--densities", default="3mm")
    ap.add_argument("--no-builtins", action="store_true")
    ap.add_argument("--contact-cost", action="store_true", help="also time PyBullet contact on both surfaces")
    args = ap.parse_args()
    print("| object | surface | method | triangles | dihedral p95 (deg) | smooth part p95 | fold excess p95 | "
          "border edges | coverage % | surface-cloud p95 / h (mm) | vertices-source mesh p95 / max (mm) | build (s) | refused |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    if args.objects:
        import _env  # noqa: F811

        corpus = _env.load("corpus")
        names = corpus.mesh_names("all") if args.objects == "all" else args.objects.split(",")
        for c in corpus.cases("all", args.densities.split(","), ("band",), names):
            for line in compare(f"{c.mesh_name} {c.density} ({c.capture.n_points} pts)", c.capture.points,
                                (c.vertices, c.triangles), args.contact_cost):
                print(line, flush=True)
    if not args.no_builtins:
        from tergodic_cli.capture import CaptureConfig, capture_cloud

        for name in BUILTINS:
            cap = capture_cloud(CaptureConfig(source="synthetic", synthetic=name))
            for line in compare(f"{name} (built-in, {cap.n_points} pts)", cap.points, cost=args.contact_cost):
                print(line, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
