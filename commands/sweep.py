"""``tergodic sweep``: the explorer over a grid of objects x starts x nK x α x options."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer


# The docstring's "\b" lines keep click from reflowing the GRID.toml example (it prints verbatim).
def sweep(
    grid: Path = typer.Argument(..., help="GRID.toml: [objects.NAME] tables and a [grid] of option lists."),
    out: Path = typer.Option(..., "--out", "-o", help="Sweep folder: results.csv, series.npz, plots, runs/ (resumable)."),
    jobs: Optional[int] = typer.Option(None, "--jobs", "-j", help="Parallel workers [default: all local CPUs; with Ray: all cluster CPUs]."),
    engine: str = typer.Option("joblib", "--engine", help="'joblib' (local processes) or 'ray' (an existing Ray cluster, or a local one)."),
    address: Optional[str] = typer.Option(None, "--address", help="Ray cluster address (HOST:PORT or 'auto'); without it Ray starts locally."),
    cache_dir: Optional[Path] = typer.Option(None, "--cache-dir", help="Basis cache root [default: $TERGODIC_CACHE_DIR or ~/.cache/tergodic]."),
    no_plots: bool = typer.Option(False, "--no-plots", help="Skip the figures."),
    parquet: bool = typer.Option(False, "--parquet", help="Also write results.parquet (needs pyarrow)."),
    json_out: bool = typer.Option(False, "--json", help="Print the sweep summary (counts, files) as JSON."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a folder holding another grid's sweep or files this sweep did not write (whole, once the new sweep is complete)."),
) -> None:
    """Run every combination of a grid, like the paper's parameter studies (Figs. 6-11).

    Each (object, nK) basis is computed once (the largest nK, then truncated). Finished runs
    are kept in OUT/runs/ and skipped when the command is run again, so an interrupted sweep
    resumes where it stopped; a finished run whose record does not verify (damaged, edited)
    is run again, and said so. A folder holding another grid's sweep, or files the sweep did not
    write, is refused unless --overwrite; a second sweep into one folder is refused while the
    first runs. --jobs is capped at the CPUs. Results do not depend on the engine or the number of jobs.

    GRID.toml:

    \b
      steps = 1000

    \b
      [objects.bowl]
      capture = "data/bowl"      # or file = "cloud.ply", or synthetic = "mug"
      neighbors = 30
      agent_radius = 0.0075

    \b
      [objects.bunny]            # the paper's bunny and starts (its reference data)
      file = "bun270_X.ply"
      voxel = 0.003
      voxel_rule = "all"
      starts = "starts/bun270_X.npz"

    \b
      [grid]
      start = 10
      nk = [25, 50, 100, 200]
      alpha = [1, 5, 10, 50, 100]

    Examples:

      tergodic sweep grid.toml --out sweep/ --jobs 2

      tergodic sweep grid.toml --out sweep/ --engine ray --address 10.0.0.5:6379
    """
    from tergodic_cli.sweep import run_sweep
    from tergodic_cli.progress import echo as echo_err

    try:
        res = run_sweep(grid, out, jobs=jobs, engine=engine, address=address, cache_dir=cache_dir, plots=not no_plots,
                        parquet=parquet, on_event=echo_err, overwrite=overwrite)
    except KeyboardInterrupt as exc:
        from tergodic_cli.errors import Interrupted

        raise Interrupted("interrupted; rerun the same command to resume", exc) from None
    if json_out:
        typer.echo(json.dumps(res.summary(), indent=2))
    else:
        typer.echo(f"sweep: {res.n_runs} runs ({res.computed} computed, {res.skipped} already done, "
                   f"{len(res.failed)} failed) in {res.wall_s:.1f} s")
        typer.echo(f"wrote {out}/ ({', '.join(res.files)})")
        if res.table:
            typer.echo(res.ergodicity_tables())
    if res.failed:
        from tergodic_cli.errors import TergodicError

        first = res.failed[0]
        raise TergodicError(f"{len(res.failed)} run(s) failed, e.g. {first['run_id']}: {first['error']}",
                            "fix the cause and run the same command again: finished runs are kept")
