"""The capture stage's configuration (standard library only: the verbs build their options from it at start-up)."""

from __future__ import annotations

from dataclasses import dataclass, field

from tergodic_cli.config import Config, option, parse_floats

#: Above this many points after filtering, precompute needs GBs and minutes (issue 16, item 6); on a
#: dense cloud the limit is on its 3 mm stand-ins, which carry the basis (issue 27, item 5).
MAX_POINTS = 500_000


def _outliers(text: str) -> tuple[int, float]:
    nb, std = parse_floats(text, 2, "--outliers", "20,2.0")
    return int(nb), std


@dataclass
class CaptureConfig(Config):
    """Everything that determines a capture; saved in ``capture.json`` and ``config.json``."""

    source: str = "synthetic"  # "file" | "synthetic" | "sim" | "realsense" (the last two pass raw arrays)
    path: str | None = None  # a cloud, or a triangle mesh (.obj, .stl, .glb, .off, a .ply with faces) to sample
    synthetic: str = "bowl"
    marking: str = field(default="X", metadata=option(
        "--marking", "Marking: X, ring, dots or patches (two discs on opposite sides); with --source sim also "
        "IMAGE.png (alpha = intensity, else non-white = marking)."))
    seed: int = field(default=0, metadata=option(  # synthetic clouds, and the Poisson-disk sampling of a mesh
        "--seed", "Seed for synthetic sampling, colour noise, surface noise, the dots marking and the sampling of a "
        "mesh."))
    noise: float = field(default=0.0, metadata=option(
        "--noise", "Synthetic: Gaussian noise along the surface normal, σ in METRES (e.g. 0.0015 = 1.5 mm; 0 = none)."))
    units: str = field(default="m", metadata=option(
        "--units", "Units of the input coordinates (the cloud or mesh file, or the sim .obj): m or mm."))
    voxel: float = field(default=0.003, metadata=option(
        "--voxel", "Voxel edge in METRES (0 disables). The paper uses 0.003."))
    voxel_rule: str = field(default="fraction", metadata=option(  # the closed loop's: "intensity"
        "--voxel-rule", "p per voxel: 'fraction' of target points (default), 'all' (target only if every point is; "
        "the authors' code), or 'intensity' (mean ink intensity: faint ink counts; needs a noise-free colour, e.g. "
        "--source sim)."))
    crop: tuple[float, float, float, float, float, float] | None = field(default=None, metadata=option(
        "--crop", "Passthrough box xmin,ymin,zmin,xmax,ymax,zmax in metres.", type=str,
        parse=lambda text: parse_floats(text, 6, "--crop", "-0.2,-0.2,0,0.2,0.2,0.3")))
    outliers: tuple[int, float] | None = field(default=None, metadata=option(
        "--outliers", "Statistical outlier removal NB,STD, e.g. 20,2.0.", type=str, parse=_outliers))
    drop_isolated: bool = field(default=True, metadata=option(  # stray points (filters.isolated_points)
        "--keep-isolated", "Keep stray points (by default a point with fewer than 2 others within 8 median spacings, "
        "a flying pixel, is dropped after the voxel grid).", type=bool, parse=lambda keep: not keep))
    target: str = field(default="red", metadata=option(
        "--target", "Target colour: red, green, blue, yellow, orange, magenta, cyan, black, white; "
        "hsv:H1-H2,SMIN,VMIN; or 'all' for uniform coverage."))
    drop_invalid: bool = field(default=False, metadata=option(
        "--drop-invalid", "Drop NaN/inf points instead of refusing the cloud."))
    colour_depth: int | None = field(default=None, metadata=option(
        "--colour-depth", "Bits per colour channel, 8 or 16, when the file does not say (XYZRGB text, NPZ); default: "
        "0..1 floats or 0..255, and more is refused."))
    max_points: int = field(default=MAX_POINTS, metadata=option(
        "--max-points", "Warn when the basis would need more points than this after filtering (precompute refuses "
        "them); a cloud much denser than 3 mm needs only its 3 mm stand-ins."))
    allow_empty_target: bool = False  # re-captures of a cleaned object may have no marking left
