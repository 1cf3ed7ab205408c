"""Ahead-of-time build of the fast Laplacian's kernels, and the loader that finds it.

Why: the kernels (:mod:`tergodic_cli.basis.fast_laplacian_kernels`) are numba code. Just in time,
a fresh process pays 0.6-0.8 s to import numba and set up its compiler before the first call
(and ~30 s to compile once), more than the 2-3x faster Laplacian saves on one cloud. Built
ahead of time with ``numba.pycc`` they become a standalone extension module that loads in under
a millisecond without numba, so the fast Laplacian can be the default.

- ``make`` builds it (``python -m tergodic_cli.basis.fast_laplacian_aot``, ~15-40 s, once).
- The module's name carries a hash of the kernels' source (``fast_laplacian_<hash>``): after an
  edit of the kernels the old build no longer matches, is ignored, and the next build replaces it.
- It is written to ``tergodic_cli/basis/_aot/`` (ignored by git), or, where the package folder
  is read-only, to ``<cache dir>/aot/``. Both are searched.
- The build compiles for a generic x86-64 CPU (no AVX), so a copied virtual environment cannot
  crash on an older CPU with an illegal instruction. It is a build artefact: never committed.
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import os
import shutil
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

KERNELS = Path(__file__).with_name("fast_laplacian_kernels.py")
PACKAGE_DIR = Path(__file__).with_name("_aot")
BUILD_HINT = "python -m tergodic_cli.basis.fast_laplacian_aot (or make)"
#: The compiled functions: name -> name of its numba signature in the kernels module.
EXPORTS = {"laplacian_pipeline": "PIPELINE_SIGNATURE", "mean_neighbour_distance": "MEAN_DISTANCE_SIGNATURE"}

_LOADED: dict[str, object] = {}


def kernels_digest() -> str:
    """16 hex digits of BLAKE2b over the kernels' source: the build's identity."""
    return hashlib.blake2b(KERNELS.read_bytes(), digest_size=8).hexdigest()


def module_name(digest: str | None = None) -> str:
    return f"fast_laplacian_{digest or kernels_digest()}"


def search_dirs() -> list[Path]:
    """Where a build is looked for, in order: the package's ``_aot/``, then ``<cache dir>/aot``."""
    from tergodic_cli.basis.cache import default_cache_dir

    return [PACKAGE_DIR, default_cache_dir() / "aot"]


def _suffix() -> str:
    return sysconfig.get_config_var("EXT_SUFFIX") or importlib.machinery.EXTENSION_SUFFIXES[0]


def find_build() -> tuple[Path | None, str]:
    """The current build's file, or None and why there is none (one line)."""
    try:
        name = module_name()
    except OSError as exc:  # an install without the kernels' source (bytecode only) cannot tell a build's age
        return None, f"the kernels' source {KERNELS.name} is unreadable ({exc.strerror}); reinstall tergodic"
    for folder in search_dirs():
        path = folder / (name + _suffix())
        if path.is_file():
            return path, "built"
    stale = [p.name for d in search_dirs() if d.is_dir() for p in d.glob("fast_laplacian_*" + _suffix())]
    if stale:
        return None, f"the ahead-of-time build is stale (the kernels changed since); rebuild: {BUILD_HINT}"
    return None, f"the fast Laplacian is not built; build it once: {BUILD_HINT}"


def load_module():
    """The current build as a module (functions ``laplacian_pipeline``, ``mean_neighbour_distance``),
    or (None, why).

    Returns
    -------
    (module, "built") or (None, reason). A failed import (another NumPy ABI, a broken file) counts
    as not built, with its reason.
    """
    path, why = find_build()
    if path is None:
        return None, why
    name = path.name.split(".")[0]
    if name in _LOADED:
        return _LOADED[name], "built"
    try:
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        missing = [f for f in EXPORTS if not hasattr(module, f)]
        if missing:
            raise ImportError(f"it lacks {', '.join(missing)}")
    except Exception as exc:  # an unloadable build is no build: say why and let the caller fall back
        return None, f"the ahead-of-time build at {path} does not load ({type(exc).__name__}: {exc}); rebuild: {BUILD_HINT}"
    _LOADED[name] = module
    return module, "built"


def load_pipeline():
    """The compiled ``laplacian_pipeline`` of the current build, or (None, why); see :func:`load_module`."""
    module, why = load_module()
    return (module.laplacian_pipeline if module is not None else None), why


def _smoke_test(module) -> None:
    """The fresh build on a small noisy sphere: no guard, symmetric L, zero row sums, a plausible spacing."""
    import numpy as np

    rng = np.random.default_rng(0)
    v = rng.normal(size=(400, 3))
    pts = np.ascontiguousarray(v / np.linalg.norm(v, axis=1, keepdims=True) * 0.05)
    indptr, indices, data, mass, code, where = module.laplacian_pipeline(pts, 12, 1e-5, np.ones(len(pts)), False)
    if code:
        raise RuntimeError(f"the built module refused its smoke-test cloud (guard {code} at {where})")
    import scipy.sparse as sp

    L = sp.csr_matrix((data, indices, indptr), shape=(len(pts), len(pts)))
    scale = abs(L).max()
    if not (abs(L - L.T).max() <= 1e-12 * scale and np.abs(L @ np.ones(len(pts))).max() <= 1e-10 * scale
            and np.all(mass > 0)):
        raise RuntimeError("the built module's Laplacian is not symmetric with zero row sums")
    h = module.mean_neighbour_distance(pts, 3)
    if not 0.002 < h < 0.01:  # 400 points on a 5 cm sphere are ~4.4 mm apart
        raise RuntimeError(f"the built module's mean neighbour distance {h:.3g} m is implausible")


def build(out_dir: Path | None = None, force: bool = False, log=print) -> Path:
    """Compile the kernels into ``out_dir`` (default: the first writable of :func:`search_dirs`).

    Writes into a temporary folder, smoke-tests the module there, then renames it into place and
    removes older builds, so an interrupted build leaves nothing half-written.

    Returns
    -------
    Path of the built extension module.
    """
    import warnings

    digest = kernels_digest()
    name = module_name(digest)
    if out_dir is None:
        for folder in search_dirs():
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError:
                continue
            if os.access(folder, os.W_OK):
                out_dir = folder
                break
        else:
            raise RuntimeError(f"no writable folder for the build among {[str(d) for d in search_dirs()]}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / (name + _suffix())
    if target.is_file() and not force:
        log(f"fast Laplacian: {target} is up to date")
        return target
    log(f"fast Laplacian: compiling its kernels ahead of time into {out_dir} (about 30-50 s, once) ...")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numba.pycc is "pending deprecation"; see docs/precompute.md
        from numba.pycc import CC

        from tergodic_cli.basis import fast_laplacian_kernels as kernels

        tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=out_dir))
        try:
            cc = CC(name)
            cc.output_dir = str(tmp)
            cc.verbose = False
            cc.target_cpu = "generic"  # a copied venv must not SIGILL on an older CPU
            for fn, signature in EXPORTS.items():
                cc.export(fn, getattr(kernels, signature))(getattr(kernels, fn))
            cc.compile()
            built = tmp / (name + _suffix())
            spec = importlib.util.spec_from_file_location(name, built)
            module = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(module)
            _smoke_test(module)
            os.replace(built, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    for old in out_dir.glob("fast_laplacian_*" + _suffix()):
        if old != target:
            old.unlink(missing_ok=True)
    log(f"fast Laplacian: built {target.name} in {time.perf_counter() - t0:.0f} s")
    return target


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m tergodic_cli.basis.fast_laplacian_aot",
                                 description="Build the fast Laplacian ahead of time (once per install).")
    ap.add_argument("--out", type=Path, help="output folder [default: tergodic_cli/basis/_aot, else <cache>/aot]")
    ap.add_argument("--force", action="store_true", help="rebuild even when the current build exists")
    ap.add_argument("--check", action="store_true", help="only say whether a current build is found (exit 1 if not)")
    args = ap.parse_args(argv)
    if args.check:
        path, why = find_build()
        print(path if path else why)
        return 0 if path else 1
    try:
        build(args.out, force=args.force)
    except Exception as exc:
        print(f"error: the fast Laplacian did not build ({type(exc).__name__}: {str(exc).splitlines()[0]}); "
              "tergodic still works and uses robust_laplacian", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
