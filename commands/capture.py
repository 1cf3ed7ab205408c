"""``tergodic capture``: a coloured cloud and its target weight p, from a file or a generator."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from tergodic_cli.commands._common import parse_floats


def register(app: typer.Typer) -> None:
    app.command("capture", no_args_is_help=True)(capture)


def capture(
    from_file: Optional[Path] = typer.Option(None, "--from", help="Point-cloud file: .ply, .pcd, .xyz/.xyzrgb/.txt (x y z [r g b]) or .npz (points, colors)."),
    synthetic: Optional[str] = typer.Option(None, "--synthetic", help="Generate an object instead: bowl, plate, mug or sphere."),
    marking: str = typer.Option("X", "--marking", help="Marking painted on a synthetic object: X, ring or dots."),
    seed: int = typer.Option(0, "--seed", help="Seed for synthetic sampling and colour noise."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for the capture (cloud.npz, cloud.ply, capture.json)."),
    voxel: float = typer.Option(0.003, "--voxel", help="Voxel edge in METRES (0 disables). The paper uses 0.003."),
    voxel_rule: str = typer.Option("fraction", "--voxel-rule", help="p per voxel: 'fraction' of target points (default), or 'all' (target only if every point is; the authors' code)."),
    crop: Optional[str] = typer.Option(None, "--crop", help="Passthrough box xmin,ymin,zmin,xmax,ymax,zmax in metres."),
    outliers: Optional[str] = typer.Option(None, "--outliers", help="Statistical outlier removal NB,STD, e.g. 20,2.0."),
    target: str = typer.Option("red", "--target", help="Target colour: red, green, blue, yellow, orange, magenta, cyan, black, white; hsv:H1-H2,SMIN,VMIN; or 'all' for uniform coverage."),
    units: str = typer.Option("m", "--units", help="Units of the input coordinates: m or mm."),
    drop_invalid: bool = typer.Option(False, "--drop-invalid", help="Drop NaN/inf points instead of refusing the cloud."),
    json_out: bool = typer.Option(False, "--json", help="Print the sidecar as JSON instead of the table."),
) -> None:
    """Capture a coloured point cloud and segment its target marking.

    Examples:

      tergodic capture --synthetic bowl --marking X --out cap/

      tergodic capture --from scan.ply --voxel 0.003 --target red --out cap/

      tergodic capture --from scan.pcd --units mm --crop -0.2,-0.2,0,0.2,0.2,0.3 --outliers 20,2 --out cap/
    """
    import json

    from tergodic_cli.capture import CaptureConfig, capture_cloud, save_capture
    from tergodic_cli.capture.pipeline import format_report
    from tergodic_cli.errors import TergodicError

    if (from_file is None) == (synthetic is None):
        raise TergodicError("give exactly one source", "use --from FILE or --synthetic bowl|plate|mug|sphere")
    cfg = CaptureConfig(
        source="file" if from_file is not None else "synthetic",
        path=str(from_file) if from_file is not None else None,
        synthetic=synthetic or "bowl",
        marking=marking,
        seed=seed,
        units=units,
        voxel=voxel,
        voxel_rule=voxel_rule,
        crop=parse_floats(crop, 6, "--crop", "-0.2,-0.2,0,0.2,0.2,0.3") if crop else None,
        outliers=_parse_outliers(outliers) if outliers else None,
        target=target,
        drop_invalid=drop_invalid,
    )
    cap = capture_cloud(cfg)
    sidecar = save_capture(cap, out)
    if json_out:
        typer.echo(json.dumps(cap.meta, indent=2))
    else:
        typer.echo(format_report(cap))
        typer.echo(f"wrote {sidecar.parent}/ (cloud.npz, cloud.ply, capture.json)")


def _parse_outliers(text: str) -> tuple[int, float]:
    nb, std = parse_floats(text, 2, "--outliers", "20,2.0")
    return int(nb), std
