"""Step benchmark: the median time of one full explorer step, and how it scales with the cloud.

A step is everything the explorer does per control cycle: footprint deposit, source update,
diffusion, gradient fit, agent update, metrics (no logging). Cases (issue 7):

- the reference bunny and plate captured with a 3 mm voxel, voxel rule "all", robust
  Laplacian with 40 neighbours, nK = 200, α = 10, agent radius 7.5 / 15 mm, starts 0..S-1 of
  ../shared/data/reference/starts/, beside the published code's 0.95 / 2.07 ms on this machine;
- Fibonacci spheres of radius 0.1 m with 3k, 18k and 100k points, a uniform target, nK = 200,
  r_a = 7.5 mm, seeded random starts. Goal: a 100k step costs at most 2x a 3k step.

Each case also runs with ``resync_every=1`` (Φᵀ M s recomputed from scratch every step, the
O(n_target nK) form the incremental update replaces), for comparison. BLAS is pinned to one
thread; figures are medians over all steps of all starts. Bases come from the cache
($TERGODIC_CACHE_DIR or ~/.cache/tergodic, keyed by content): the 100k one takes minutes once.

    python benchmarks/step.py                       # everything
    python benchmarks/step.py --sizes 3000,18000    # skip the 100k sphere
    python benchmarks/step.py --steps 300 --starts 1 --json step.json
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import os
import sys

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
REFERENCE = REPO.parent / "shared" / "data" / "reference"
#: The published code's step on this machine (reference/README.md), ms.
PUBLISHED = {"bunny": {"file": "bun270_X", "radius": 0.0075, "ms": 0.95},
             "plate": {"file": "plate_shapes", "radius": 0.015, "ms": 2.07}}
#: Issue 7 goals, ms per step.
GOALS = {"bunny": 0.050, "plate": 0.100}


def fibonacci_sphere(n: int, radius: float = 0.1) -> np.ndarray:
    """(n, 3) nearly uniform points on a sphere of ``radius`` metres."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    theta = np.pi * (1 + 5**0.5) * i
    return radius * np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def time_case(basis, target, starts, steps: int, nk: int = 200, **cfg_kw) -> dict:
    """Step times (ms) over ``steps`` steps from each start, and the work counters."""
    from tergodic_cli.explore import ExploreConfig, Explorer

    ms, first, work = [], [], {"footprint_points": 0, "spectral_rows": 0}
    for x0 in starts:
        ex = Explorer(basis, target, ExploreConfig(steps=steps, nk=nk, alpha="10", **cfg_kw), x0[None])
        t = np.empty(steps)
        for k in range(steps):
            ex.step()
            t[k] = ex.last_step_ms
        first.append(t[0])  # includes the one-off O(n nK) reference heat p̂ of residual_ref
        ms.append(t[1:])
        for key in work:
            work[key] += ex.work[key]
    t = np.concatenate(ms)
    n_steps = steps * len(starts)
    return {"median_ms": float(np.median(t)), "mean_ms": float(t.mean()), "p99_ms": float(np.percentile(t, 99)),
            "max_ms": float(t.max()), "first_step_ms": float(np.median(first)),
            "footprint_per_step": work["footprint_points"] / n_steps, "rows_per_step": work["spectral_rows"] / n_steps}


def interleaved_ratio(cases: list[tuple], steps: int) -> list[float]:
    """Median step (ms) of each (basis, target, start, radius) case, the explorers stepped in
    turn, so that a busy machine slows every case alike (the ratio is what is compared)."""
    from tergodic_cli.explore import ExploreConfig, Explorer

    exs = [Explorer(b, t, ExploreConfig(nk=200, alpha="10", agent_radius=r), x0[None]) for b, t, x0, r in cases]
    times = [np.empty(steps) for _ in exs]
    for k in range(steps):
        for ex, t in zip(exs, times):
            ex.step()
            t[k] = ex.last_step_ms
    return [float(np.median(t[1:])) for t in times]


def kernel_split(basis, target, start, steps: int = 300, **cfg_kw) -> dict:
    """Median µs of the parts of a step, each timed alone on a live explorer state: the whole
    compiled step, Python around it, and the compiled pieces (each with its own call overhead)."""
    from tergodic_cli.explore import ExploreConfig, Explorer
    from tergodic_cli.explore import kernels as K

    ex = Explorer(basis, target, ExploreConfig(nk=200, alpha="10", **cfg_kw), start[None])
    for _ in range(50):
        ex.step()
    tree, pts = ex._tree, ex._P  # the explorer's internal (tree) order
    x, n = ex.positions[0].copy(), ex.normals[0].copy()
    nb, d2 = np.empty(ex._k, np.int64), np.empty(ex._k)
    xp, nn = np.empty(3), np.empty(3)
    buf = np.empty(len(pts), np.int64)
    parts = {
        "knn (n_N)": lambda: K.tree_knn(*tree, x, ex._k, nb, d2),
        "CGA fit + projection": lambda: K.fit_project(pts, ex._nbrs[0], ex._k, x, n, xp, nn),
        "footprint ball query": lambda: K.tree_ball(*tree, x, ex.r_a, buf),
        # (called alone it unboxes the named Surface and State, ~0.2 µs an array: part of this figure, not of a step)
        "gradient (u at n_N + cubic)": lambda: K.agent_gradient(ex._surface, ex._st, 0, ex._prm, ex._mode),
        "diffusion (nK)": lambda: K.diffuse(ex._sp.copy(), ex._fs, True),
    }
    out = {}
    for name, fn in parts.items():
        fn()
        t = np.empty(steps)
        for k in range(steps):
            t0 = time.perf_counter()
            fn()
            t[k] = time.perf_counter() - t0
        out[name] = 1e6 * float(np.median(t))
    total, inner = np.empty(steps), np.empty(steps)
    orig = K.step_kernel

    def timed(*a):
        t0 = time.perf_counter()
        orig(*a)
        timed.dt = time.perf_counter() - t0

    K.step_kernel = timed
    try:
        for k in range(steps):
            t0 = time.perf_counter()
            ex.step()
            total[k] = time.perf_counter() - t0
            inner[k] = timed.dt
    finally:
        K.step_kernel = orig
    out["whole step"] = 1e6 * float(np.median(total))
    out["compiled step call"] = 1e6 * float(np.median(inner))
    out["python around it"] = out["whole step"] - out["compiled step call"]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--starts", type=int, default=3, help="starts per case")
    ap.add_argument("--objects", default="bunny,plate")
    ap.add_argument("--sizes", default="3000,18000,100000", help="sphere sizes ('' for none)")
    ap.add_argument("--no-full", action="store_true", help="skip the resync_every=1 comparison")
    ap.add_argument("--cache-dir", default=None, help="basis cache [default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]")
    ap.add_argument("--json", default=None, help="write all figures to this JSON file")
    args = ap.parse_args()

    from tergodic_cli.basis import BasisConfig, get_basis

    results: dict = {"setup": {"steps": args.steps, "starts": args.starts, "nk": 200, "alpha": 10, "blas_threads": 1}}
    rows = []

    def run(name, basis, target, starts, radius, published=None):
        n_t = int(np.count_nonzero(target))
        r = time_case(basis, target, starts, args.steps, agent_radius=radius)
        full = None if args.no_full else time_case(basis, target, starts[:1], min(args.steps, 300),
                                                   agent_radius=radius, resync_every=1)
        split = kernel_split(basis, target, starts[0], agent_radius=radius)
        results[name] = {"n_points": len(basis.points), "n_target": n_t, "incremental": r, "full_recompute": full,
                         "parts_us": split, "published_ms": published}
        rows.append((name, len(basis.points), n_t, r, full, published))
        print(f"{name}: median {1e3 * r['median_ms']:.1f} µs (mean {1e3 * r['mean_ms']:.1f}, p99 "
              f"{1e3 * r['p99_ms']:.1f}, max {1e3 * r['max_ms']:.0f}); footprint {r['footprint_per_step']:.1f} pts, "
              f"{r['rows_per_step']:.1f} rows/step; parts µs " + ", ".join(f"{k} {v:.1f}" for k, v in split.items()),
              file=sys.stderr, flush=True)

    # Compile (or load the cached machine code) before anything is timed.
    warm = fibonacci_sphere(500)
    from tergodic_cli.basis import compute_basis

    time_case(compute_basis(warm, 30, 30), np.ones(500), warm[:1], 5, nk=30, agent_radius=0.03)

    cache = args.cache_dir
    if args.objects:
        if not (REFERENCE / "bun270_X.ply").exists():
            print(f"reference data absent ({REFERENCE}); skipping bunny and plate", file=sys.stderr)
        else:
            from tergodic_cli.capture import CaptureConfig, capture_cloud

            for name in args.objects.split(","):
                pub = PUBLISHED[name]
                cap = capture_cloud(CaptureConfig(source="file", path=str(REFERENCE / f"{pub['file']}.ply"),
                                                  voxel=0.003, voxel_rule="all"))
                basis, _ = get_basis(cap.points, BasisConfig(nk=200, neighbors=40), cache)
                with np.load(REFERENCE / "starts" / f"{pub['file']}.npz", allow_pickle=False) as data:
                    starts = data["x0_arr"][: args.starts]
                run(name, basis, cap.target, starts, pub["radius"], pub["ms"])
    sphere_cases: dict[str, tuple] = {}
    for n in [int(s) for s in args.sizes.split(",") if s.strip()]:
        pts = fibonacci_sphere(n)
        t0 = time.perf_counter()
        basis, hit = get_basis(pts, BasisConfig(nk=200, neighbors=30), cache)
        if not hit:
            print(f"sphere {n}: basis computed in {time.perf_counter() - t0:.0f} s (cached now)", file=sys.stderr)
        starts = pts[np.random.default_rng(n).choice(n, args.starts, replace=False)]
        run(f"sphere {n // 1000}k", basis, np.ones(n), starts, 0.0075)
        sphere_cases[f"sphere {n // 1000}k"] = (basis, np.ones(n), starts[0], 0.0075)

    print(f"\nMedian full step, nK = 200, BLAS 1 thread, {args.steps} steps x {args.starts} starts "
          "(logging off; µs = microseconds)\n")
    print("| case | nP | target | step (median) | mean | p99 | published | speed-up | full recompute every step |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, n, n_t, r, full, pub in rows:
        speed = f"{pub / r['median_ms']:.0f}x" if pub else ""
        pubs = f"{pub * 1e3:.0f} µs" if pub else ""
        fulls = f"{1e3 * full['median_ms']:.1f} µs" if full else ""
        print(f"| {name} | {n} | {n_t} | {1e3 * r['median_ms']:.1f} µs | {1e3 * r['mean_ms']:.1f} µs | "
              f"{1e3 * r['p99_ms']:.1f} µs | {pubs} | {speed} | {fulls} |")
    print("\nGoals (issue 7):")
    for name, _, _, r, _, pub in rows:
        if name in GOALS:
            ok = r["median_ms"] <= GOALS[name]
            print(f"  {name}: {1e3 * r['median_ms']:.1f} µs <= {1e3 * GOALS[name]:.0f} µs: {'met' if ok else 'MISSED'} "
                  f"({pub / r['median_ms']:.0f}x the published code)")
    if "sphere 3k" in sphere_cases and "sphere 100k" in sphere_cases:
        a, b = interleaved_ratio([sphere_cases["sphere 3k"], sphere_cases["sphere 100k"]], args.steps)
        ratio = b / a
        results["ratio_100k_3k"] = {"interleaved_3k_ms": a, "interleaved_100k_ms": b, "ratio": ratio}
        print(f"  100k / 3k step: {ratio:.2f}x <= 2x: {'met' if ratio <= 2 else 'MISSED'} (stepped in turn: "
              f"{1e3 * a:.1f} µs vs {1e3 * b:.1f} µs)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
