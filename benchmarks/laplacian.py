"""Laplacian benchmark: our compiled re-implementation against robust_laplacian, on the reference bunny.

Run ``python benchmarks/laplacian.py [--repeats N] [--compile-time]``.

First, the cost of a fresh process (what one ``tergodic precompute`` pays): import and first call on
the 2996-point bunny, in new interpreters, for the library, our ahead-of-time build (the default
when ``make`` has built it) and our numba just-in-time kernels (numba cache warm). Then:

For the bunny at 2996 and 18001 points (the paper's 3 mm and 0.976 mm voxels, voxel rule "all") and
n_neighbors 30 and 40 it measures, BLAS pinned to one thread, medians over ``--repeats`` interleaved runs of

- ``robust_laplacian.point_cloud_laplacian`` (the authors' call, C++),
- ``tergodic_cli.basis.fast_laplacian.point_cloud_laplacian`` (ours, single-threaded; the
  ahead-of-time build when there is one, else numba),

and prints the in-run ratio and the largest differences (L relative to max|L|, mass relative to its
maximum, entries present in only one sparsity pattern). When our guard refuses a cloud
(LaplacianMismatchRisk: a near-tie where round-off could make the two differ) it prints the reason and
the time it took to refuse. ``--compile-time`` also measures the first call with an empty numba cache
(a fresh subprocess; about half a minute).
"""

from __future__ import annotations

import _env  # noqa: F401,I001  (first: path fix, one BLAS thread; see benchmarks/_env.py)

import argparse  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BUNNY = REPO.parent / "shared" / "data" / "reference" / "bun270_X.ply"
#: voxel edge (mm) -> expected point count (paper, Table I)
SIZES = {3.0: 2996, 0.9763594: 18001}
NEIGHBORS = (30, 40)
GOAL_RATIO = 3.0


def load_cloud(voxel_mm: float, expected: int) -> np.ndarray:
    from tergodic_cli.capture import CaptureConfig, capture_cloud

    cap = capture_cloud(CaptureConfig(source="file", path=str(BUNNY), voxel=voxel_mm / 1000.0, voxel_rule="all"))
    assert len(cap.points) == expected, f"voxel {voxel_mm} mm gave {len(cap.points)} points, expected {expected}"
    return cap.points


def differences(ref, ours) -> tuple[int, float, float]:
    (L0, M0), (L1, m1) = ref, ours
    L0 = sp.csr_matrix(L0)
    L0.eliminate_zeros()
    L1 = L1.copy()
    L1.eliminate_zeros()
    m0 = np.asarray(M0.diagonal())
    only_one = int(abs((L0 != 0).astype(np.int8) - (L1 != 0).astype(np.int8)).sum())
    return only_one, float(abs(L0 - L1).max() / abs(L0).max()), float(np.max(np.abs(m0 - m1)) / np.max(m0))


def compile_seconds() -> float:
    """First call with an empty numba cache, in a fresh interpreter."""
    code = ("import time, numpy as np\n"
            "from tergodic_cli.basis.fast_laplacian import point_cloud_laplacian\n"
            "pts = np.random.default_rng(0).normal(size=(400, 3))\n"
            "t = time.perf_counter()\n"
            "try:\n    point_cloud_laplacian(pts, 30)\nexcept Exception:\n    pass\n"
            "print(time.perf_counter() - t)\n")
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    return float(out.stdout.strip().splitlines()[-1])


FRESH_CODE = {
    "robust_laplacian": ("import robust_laplacian\n"
                         "f = lambda p: robust_laplacian.point_cloud_laplacian(p, n_neighbors=30)\n"),
    "ours, ahead-of-time build": ("from tergodic_cli.basis.fast_laplacian import point_cloud_laplacian\n"
                                  "f = lambda p: point_cloud_laplacian(p, 30, backend='aot')\n"),
    "ours, numba just in time": ("from tergodic_cli.basis.fast_laplacian import point_cloud_laplacian\n"
                                 "f = lambda p: point_cloud_laplacian(p, 30, backend='jit')\n"),
}


def fresh_process_ms(points: np.ndarray, repeats: int) -> dict[str, float | str]:
    """Median ms from before the import to L in memory, each in a new interpreter (numpy preloaded)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "points.npy")
        np.save(path, points)
        out: dict[str, list[float] | str] = {name: [] for name in FRESH_CODE}
        for _ in range(repeats):
            for name, body in FRESH_CODE.items():
                code = ("import sys, time, numpy as np\n"
                        f"p = np.load({path!r})\n"
                        "t = time.perf_counter()\n" + body + "f(p)\n"
                        "print(1e3 * (time.perf_counter() - t), 'numba' in sys.modules)\n")
                res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
                if res.returncode:
                    out[name] = res.stderr.strip().splitlines()[-1][:100]
                elif isinstance(out[name], list):
                    out[name].append(float(res.stdout.split()[0]))
    return {k: (float(np.median(v)) if isinstance(v, list) else v) for k, v in out.items()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9, help="interleaved runs per measurement; medians reported")
    ap.add_argument("--compile-time", action="store_true", help="also time the first call with an empty numba cache")
    args = ap.parse_args(argv)
    if not BUNNY.exists():
        print(f"laplacian benchmark skipped: reference cloud {BUNNY} is absent")
        return 0

    import robust_laplacian

    from tergodic_cli.basis.fast_laplacian import LaplacianMismatchRisk, point_cloud_laplacian

    print(f"Laplacian benchmark: bunny {', '.join(map(str, SIZES.values()))} points, neighbours {NEIGHBORS}, "
          f"median of {args.repeats} interleaved runs, BLAS 1 thread; load average {os.getloadavg()[0]:.2f} "
          f"on {os.cpu_count()} CPUs")
    warm = load_cloud(3.0, 2996)
    print("fresh process, import + first call at 2996 points (median of 3):")
    for name, ms in fresh_process_ms(warm, 3).items():
        print(f"  {name:28s} {ms:7.0f} ms" if isinstance(ms, float) else f"  {name:28s} failed: {ms}")
    from tergodic_cli.basis.fast_laplacian import compiled_pipeline

    print(f"ours below = the {compiled_pipeline('auto')[1]} build")
    t = time.perf_counter()
    try:
        point_cloud_laplacian(warm, 30)
    except LaplacianMismatchRisk:
        pass
    print(f"first call in this process (numba cache load, or compile if the cache is cold): "
          f"{time.perf_counter() - t:.2f} s")
    if args.compile_time:
        print(f"first call with an empty numba cache (compile): {compile_seconds():.1f} s")

    print(f"\n  {'nP':>6} {'k':>3} {'robust_laplacian':>16} {'ours':>8} {'ratio':>6}  max ΔL/|L|  max Δm/m  pattern")
    for voxel, n in SIZES.items():
        pts = load_cloud(voxel, n)
        for k in NEIGHBORS:
            def ours(pts=pts, k=k):
                try:
                    return point_cloud_laplacian(pts, k)
                except LaplacianMismatchRisk as exc:
                    return exc

            times = [[], []]
            outs = [None, None]
            for _ in range(args.repeats):
                for i, fn in enumerate((lambda: robust_laplacian.point_cloud_laplacian(pts, 1e-5, k), ours)):
                    t = time.perf_counter()
                    outs[i] = fn()
                    times[i].append(1e3 * (time.perf_counter() - t))
            ref_ms, our_ms = (float(np.median(x)) for x in times)
            if isinstance(outs[1], LaplacianMismatchRisk):
                print(f"  {n:6d} {k:3d} {ref_ms:13.1f} ms {our_ms:5.1f} ms      refused: {outs[1]} "
                      "(the caller falls back to robust_laplacian)")
                continue
            only_one, dL, dm = differences(outs[0], outs[1])
            print(f"  {n:6d} {k:3d} {ref_ms:13.1f} ms {our_ms:5.1f} ms {ref_ms / our_ms:5.2f}x  {dL:9.1e}  "
                  f"{dm:8.1e}  {only_one} differ")
    print(f"\nGoal (issue 7): >= {GOAL_RATIO:.0f}x faster than robust_laplacian at 2996 points with equal L and mass. "
          f"Load average at the end {os.getloadavg()[0]:.2f}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
