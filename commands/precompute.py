"""``tergodic precompute``: Laplacian, mass and eigenpairs of a capture, cached by geometry."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from tergodic_cli.basis.config import BasisConfig
from tergodic_cli.commands._options import with_options


@with_options(BasisConfig)
def precompute(
    ctx: typer.Context,
    capture: Path = typer.Argument(..., help="Capture folder written by 'tergodic capture'."),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Cache root [default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]."),
    force: bool = typer.Option(False, "--force", help="Recompute even when the cache holds this basis."),
    max_points: int = typer.Option(500_000, "--max-points", help="Refuse captures whose basis needs more points than this (GBs and minutes of work); a cloud much denser than 3 mm needs only its 3 mm stand-ins."),
    json_out: bool = typer.Option(False, "--json", help="Print the basis metadata as JSON."),
    config: Optional[Path] = typer.Option(None, "--config", help="Repeat a basis: the config.json of its cache entry (nK, neighbours, solver); --nk/--neighbors given beside it override it."),
    **opts,
) -> None:
    """Compute (or load from cache) the spectral basis of a capture.

    The basis depends only on geometry: a new target, or a rigid motion of the
    same points, reuses it. A second identical call is a cache hit.

    Example:

      tergodic precompute cap/ --nk 200 --neighbors 30

      tergodic precompute cap2/ --config ~/.cache/tergodic/basis/KEY/config.json
    """
    from tergodic_cli.basis import get_basis
    from tergodic_cli.basis.cache import BASIS_CONFIG_KIND, validate_basis_config
    from tergodic_cli.capture import load_capture
    from tergodic_cli.capture.filters import basis_size
    from tergodic_cli.capture.pipeline import check_size
    from tergodic_cli.commands._common import given_options
    from tergodic_cli.commands._options import renamed, values
    from tergodic_cli.config import override, read_config
    from tergodic_cli.progress import echo as echo_err

    bcfg = BasisConfig(**values(BasisConfig, opts))
    if config is not None:  # the saved config, with --nk / --neighbors given on this command line on top
        d = read_config(config, BASIS_CONFIG_KIND,
                        "give the config.json of a basis cache entry (see 'tergodic precompute --json')", sections=("basis",))
        saved = BasisConfig.from_dict(d.get("basis"), f"--config {config}: basis")
        bcfg = override(saved, bcfg, given_options(ctx), renamed(BasisConfig))
    validate_basis_config(bcfg)  # before the capture is read
    cap = load_capture(capture)
    h = cap.meta.get("spacing_h_m")
    check_size(capture, cap.n_points, max_points,
               basis_size(cap.points, float(h), bcfg.nk, bcfg.neighbors) if isinstance(h, (int, float)) else None)
    basis, hit = get_basis(cap.points, bcfg, cache_dir, force=force, on_event=echo_err)
    if json_out:
        typer.echo(json.dumps({**basis.meta, "cache_hit": hit}, indent=2))
        return
    if hit:
        t = basis.meta["timings_load"]
        typer.echo(f"cache hit: basis {basis.meta['key']} loaded in {t['key_ms'] + t['load_ms']:.1f} ms, nothing recomputed")
    else:
        t = basis.meta["timings"]
        typer.echo("computed basis: " + ", ".join(f"{k.removesuffix('_ms')} {v:.0f} ms" for k, v in t.items()))
    on = f" (the basis on {len(basis.sel)} 3 mm stand-ins)" if basis.thinned else ""
    typer.echo(f"  {cap.n_points} points{on}, nK = {basis.nk}, neighbours = {bcfg.neighbors}, h = {basis.h * 1e3:.3f} mm, "
               f"λ = {basis.evals[0]:.3g} .. {basis.evals[-1]:.4g} 1/m²")
    typer.echo(f"  {basis.meta['path']}")

