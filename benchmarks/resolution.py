"""Resolution independence (issue 13, item 5): one object sampled at about 3k, 30k and 100k points.

The synthetic bowl with its X (the project's own object; ``--object torus``: two patches), sampled densely and voxel-filtered to
three sizes (``--sampling direct``: the object sampled at each size and captured whole); the default explorer (nK 200, α 10, δt = α h₀² with a fixed h₀, r_a 7.5 mm), the same
three starts (the points nearest three fixed positions), 1000 steps. Prints ε, touched,
off-surface share, step max and the median step time per size, and the ratios to the 3k row.
Goals: ε within 10 % across the sizes, touched ≥ 98 % at each, step at 100k ≤ 2x the step at 3k.
The target is binary by default (voxel rule "all"): with the "fraction" rule a coarse grid's p has
soft edges (half the marked points of the 3k cloud), which a Gaussian footprint matches more easily,
so ε then measures the capture's sampling of the marking as much as the explorer.

    python benchmarks/resolution.py             # 3k, 30k, 100k (the 100k basis takes a few minutes)
    python benchmarks/resolution.py --sizes 3000,30000
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def capture_at(n_target_points: int, raw, rule: str = "all"):
    """The capture of ``raw`` (points, colours) with the voxel that leaves about ``n_target_points``."""
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    lo, hi = 1e-4, 0.01
    cap = None
    for _ in range(18):  # bisect the voxel size on the point count
        voxel = (lo * hi) ** 0.5
        cap = capture_cloud(CaptureConfig(source="synthetic", voxel=voxel, voxel_rule=rule), raw=raw)
        if abs(cap.n_points - n_target_points) < 0.03 * n_target_points:
            break
        lo, hi = (voxel, hi) if cap.n_points > n_target_points else (lo, voxel)
    return cap


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="3000,30000,100000")
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--starts", type=int, default=3, help="starts per size: the three fixed ones, then seeded "
                    "points of the first size's cloud (the same positions at every size) [default: 3]")
    ap.add_argument("--object", default="bowl", help="synthetic object: bowl (X marking) or torus (two patches)")
    ap.add_argument("--cache", default=None, help="basis cache folder to reuse between runs [default: a new temp one]")
    ap.add_argument("--voxel-rule", default="all", help="all (binary p: the same target at every size; default) or "
                    "fraction (p = the share of marked points in a voxel: softer edges on coarse grids)")
    ap.add_argument("--sampling", default="voxel", choices=("voxel", "direct"),
                    help="voxel: a dense cloud voxel-filtered to each size (--voxel-rule); direct: the object "
                    "sampled at each size's spacing and captured whole (voxel 0, p per point) [default: voxel]")
    args = ap.parse_args()
    from tergodic_cli.basis import BasisConfig, get_basis
    from tergodic_cli.capture.synthetic import generate_synthetic
    from tergodic_cli.capture import CaptureConfig, capture_cloud
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.explore.metrics import coverage_score

    sizes = [int(s) for s in args.sizes.split(",")]
    # Raw samples dense enough for the largest size (about 3 raw points per kept point).
    marking = {"bowl": "X", "torus": "patches"}[args.object]
    area = 0.0012**2 * len(generate_synthetic(args.object, marking, seed=0).points)  # default spacing 1.2 mm
    area_per_point = area / max(sizes)
    syn = generate_synthetic(args.object, marking, seed=0, spacing=float(np.sqrt(area_per_point / 3.0)))
    raw = (syn.points, syn.colors)
    cache = args.cache or tempfile.mkdtemp(prefix="tergodic-resolution-")
    fixed = np.array([[0.0, 0.0, 0.0], [0.03, 0.02, 0.01], [-0.04, 0.0, 0.02]])
    caps = []
    for n in sizes:
        if args.sampling == "direct":
            one = generate_synthetic(args.object, marking, seed=0, spacing=float(np.sqrt(area / n)))
            caps.append(capture_cloud(CaptureConfig(source="synthetic", voxel=0.0), raw=(one.points, one.colors)))
        else:
            caps.append(capture_at(n, raw, args.voxel_rule))
    dense = caps[-1]
    rows = []
    for cap in caps:
        if len(fixed) < args.starts:  # seeded extra starts, fixed positions from the first size's cloud
            pick = np.random.default_rng(0).choice(cap.n_points, args.starts - len(fixed), replace=False)
            fixed = np.vstack([fixed[:3], cap.points[pick]])
        t0 = time.perf_counter()
        basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=30), cache)
        t_basis = time.perf_counter() - t0
        eps, touched, off, smax, ms, common = [], [], [], [], [], []
        for x in fixed:
            x0 = cap.points[np.argmin(np.linalg.norm(cap.points - x, axis=1))]
            ex = Explorer(basis, cap.target, ExploreConfig(steps=args.steps), x0[None], on_event=lambda m: None)
            t = np.empty(args.steps)
            X = np.empty((args.steps, 3))
            for k in range(args.steps):
                ex.step()
                t[k] = ex.last_step_ms
                X[k] = ex.positions[0]
            # the same trajectory scored on the densest cloud: the explorer alone, the target's sampling fixed
            common.append(coverage_score(dense.points, dense.target, X, ex.cfg.agent_radius, 1.0)["ergodicity"])
            sc = ex.score()
            eps.append(sc["ergodicity"])
            touched.append(sc["touched_fraction"])
            off.append(sc["off_surface_fraction"])
            smax.append(sc["step_max_m"])
            ms.append(np.median(t))
        rows.append((cap.n_points, float(basis.h), t_basis, float(np.median(eps)), min(touched), max(off), max(smax),
                     float(np.median(ms)), float(np.median(common))))
        print(f"{cap.n_points} points (h {basis.h * 1e3:.2f} mm, basis {t_basis:.1f} s): ε {np.round(eps, 3)}",
              file=sys.stderr, flush=True)
    print("\n| points | h | ε median | ε / 3k | ε on the densest cloud | touched min | off-surface | step max | step "
          "| step / 3k |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    e0, s0 = rows[0][3], rows[0][7]
    for n, h, _tb, e, tmin, off, smax, ms, ec in rows:
        print(f"| {n} | {h * 1e3:.2f} mm | {e:.3f} | {e / e0:.2f} | {ec:.3f} | {100 * tmin:.1f}% | {100 * off:.1f}% | "
              f"{smax * 1e3:.2f} mm | {ms * 1e3:.0f} µs | {ms / s0:.2f} |")
    es = [r[3] for r in rows]
    ecs = [r[8] for r in rows]
    print(f"\nspread of ε (max / min - 1): {max(es) / min(es) - 1:.0%} (goal 10 %); of ε on the densest cloud: "
          f"{max(ecs) / min(ecs) - 1:.0%}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
