"""``tergodic capture``: a coloured cloud and its target weight p, from a file, a generator or a simulated camera."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from tergodic_cli.capture.config import CaptureConfig
from tergodic_cli.commands._common import given_options, parse_floats
from tergodic_cli.commands._options import with_options


@with_options(CaptureConfig)
def capture(
    ctx: typer.Context,
    from_file: Optional[Path] = typer.Option(None, "--from", help="Point-cloud file: .ply, .pcd, .xyz/.xyzrgb/.txt (x y z [r g b]) or .npz (points, colors); or a triangle mesh: .obj (its .mtl texture), .stl, .glb/.gltf, .off, or a .ply with faces, sampled by Poisson disk at the --voxel spacing (seeded by --seed), coloured from its texture or vertex colours, and kept in the capture (mesh.npz)."),
    synthetic: Optional[str] = typer.Option(None, "--synthetic", help="Generate an object instead: bowl, plate, mug, sphere, holed-plate (3 cm hole), thin-mug (walls 4 mm apart), torus, box (sharp edges) or partial (one side missing)."),
    source: Optional[str] = typer.Option(None, "--source", help="file, synthetic, sim or realsense; inferred from --from / --synthetic / --object when omitted."),
    sim_object: Optional[str] = typer.Option(None, "--object", help="Simulated camera (--source sim): bowl, plate, mug, or FILE.obj (metres; --units mm for millimetres)."),
    object_pose: Optional[str] = typer.Option(None, "--object-pose", help="Sim: object pose in the robot base frame x,y,z[,roll,pitch,yaw] (m, deg) or x,y,z,qx,qy,qz,qw. Default 0.5,0,0 (the mug turned 180 deg so its marking faces the camera)."),
    camera_pose: Optional[str] = typer.Option(None, "--camera-pose", help="Sim: eye and target ex,ey,ez,tx,ty,tz (m), or the optical frame x,y,z,qx,qy,qz,qw (z forward). Default: eye 0.30,0,0.60 looking at the object. RealSense: the optical frame x,y,z,qx,qy,qz,qw in the robot base frame (hand-eye calibration); default: the camera frame."),
    serial: Optional[str] = typer.Option(None, "--serial", help="RealSense: the camera's serial number (needed when several are connected)."),
    width: int = typer.Option(640, "--width", help="Sim/RealSense: image width, pixels."),
    height: int = typer.Option(480, "--height", help="Sim/RealSense: image height, pixels."),
    fov: float = typer.Option(42.0, "--fov", help="Sim: vertical field of view, degrees."),
    renderer: str = typer.Option("auto", "--renderer", help="Sim: auto (EGL when it loads, else TinyRenderer), egl or tiny."),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder for the capture (cloud.npz, cloud.ply, capture.json)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing capture folder at --out."),
    json_out: bool = typer.Option(False, "--json", help="Print the sidecar as JSON instead of the table."),
    config: Optional[Path] = typer.Option(None, "--config", help="Repeat a capture: its CAP/config.json; options given beside it override it."),
    **opts,
) -> None:
    """Capture a coloured point cloud and segment its target marking.

    Examples:

      tergodic capture --synthetic bowl --marking X --out cap/

      tergodic capture --synthetic bowl --noise 0.0015 --out cap/

      tergodic capture --synthetic torus --marking patches --out cap/

      tergodic capture --source sim --object bowl --marking X --out cap/

      tergodic capture --source sim --object scan.obj --marking stain.png --camera-pose 0.3,0,0.6,0.5,0,0 --out cap/

      tergodic capture --source realsense --serial 123456789012 --camera-pose 0.3,0,0.6,1,0,0,0 --out cap/

      tergodic capture --from scan.ply --voxel 0.003 --target red --out cap/

      tergodic capture --from scan.pcd --units mm --crop -0.2,-0.2,0,0.2,0.2,0.3 --outliers 20,2 --out cap/

      tergodic capture --from scan.obj --target red --seed 0 --out cap/   (a textured mesh, sampled every 3 mm, kept as mesh.npz)

      tergodic capture --from part.stl --units mm --target all --out cap/   (a mesh without colour: cover all of it)

      tergodic capture --config cap/config.json --seed 3 --out cap2/
    """
    from tergodic_cli.atomic import write_png
    from tergodic_cli.capture import capture_cloud, save_capture
    from tergodic_cli.commands._options import renamed, values
    from tergodic_cli.capture.artefact import CAPTURE_CONFIG_KIND, check_out_folder
    from tergodic_cli.capture.textured import BUILTIN_OBJECTS, SimObjectConfig
    from tergodic_cli.config import from_dict, override, read_config
    import os

    from tergodic_cli.errors import check_seed, require
    from tergodic_cli.progress import Spinner

    given = given_options(ctx)
    saved, sections = None, {}  # sections: the saved object and camera of a simulated capture
    if config is not None:
        sections = read_config(config, CAPTURE_CONFIG_KIND,
                               "give the config.json that 'tergodic capture' wrote beside a capture",
                               sections=("capture", "object", "camera"))
        saved = CaptureConfig.from_dict(sections.get("capture"), f"--config {config}: capture")
    sourced = saved is not None and not given & {"source", "from_file", "synthetic", "sim_object"}
    kind = saved.source if sourced else _resolve_source(source, from_file, synthetic, sim_object)
    fields = values(CaptureConfig, opts)  # the options that set CaptureConfig fields (parsed)
    fields["drop_isolated"] = fields["drop_isolated"] if fields["drop_isolated"] is not None else True
    marking, seed, units = fields["marking"], fields["seed"], fields["units"]  # the sim object's too
    cfg = CaptureConfig(
        **fields, source=kind,
        path=str(from_file) if from_file is not None else (sim_object if kind == "sim" and sim_object not in BUILTIN_OBJECTS else None),
        synthetic=(synthetic or "bowl") if kind != "sim" else (sim_object or "bowl"),
    )
    if kind == "sim":
        cfg.units = "m"  # a sim cloud is in metres; --units applies to the .obj
    if saved is not None:  # the saved capture, with the options given on this command line on top
        cfg = override(saved, cfg, given, {"from_file": ("path",), "sim_object": ("path", "synthetic"),
                                           **renamed(CaptureConfig)})
    check_seed(cfg.seed)  # also the simulated camera's, which runs before the pipeline's checks
    check_out_folder(out, overwrite)  # before any work: a refused --out costs nothing
    if cfg.path is not None and kind == "file":  # an input inside the folder --overwrite replaces would go with it
        require(not Path(os.path.abspath(cfg.path)).is_relative_to(os.path.abspath(out)),
                f"--from {cfg.path} is inside --out {out}, which the capture replaces", "choose another --out")
    frame, configs = None, {"capture": cfg}  # a realsense camera's settings are in capture.json only
    if kind == "sim":
        from tergodic_cli.backends.pybullet.camera import SimCameraConfig, SimCaptureConfig, capture_sim

        sim = SimCaptureConfig(
            object=SimObjectConfig(object=sim_object or "bowl", marking=marking, units=units, seed=seed,
                                   pose=parse_floats(object_pose, None, "--object-pose", "0.5,0,0")),
            camera=SimCameraConfig(pose=parse_floats(camera_pose, None, "--camera-pose", "0.3,0,0.6,0.5,0,0.03"), width=width, height=height,
                                   fov_deg=fov, renderer=renderer, seed=seed),
            pipeline=cfg,
        )
        if saved is not None:
            for part, renamed in (("object", {"sim_object": ("object",), "object_pose": ("pose",)}),
                                  ("camera", {"camera_pose": ("pose",), "fov": ("fov_deg",)})):
                now = getattr(sim, part)
                old = from_dict(type(now), sections.get(part) or {}, f"--config {config}: {part}")
                setattr(sim, part, override(old, now, given, renamed))
        configs.update(object=sim.object, camera=sim.camera)
        cap = capture_sim(sim)
        frame = getattr(cap, "frame", None)
    elif kind == "realsense":
        from tergodic_cli.backends.realsense.capture import capture_realsense

        cap = capture_realsense(cfg, serial=serial, width=width, height=height,
                                camera_pose=parse_floats(camera_pose, None, "--camera-pose", "0.3,0,0.6,1,0,0,0"))
    else:
        with Spinner("capture: reading, filtering and segmenting the cloud"):  # seconds for millions of points
            cap = capture_cloud(cfg)
    # What the camera saw goes beside the artefact (not part of it), inside the same atomic folder.
    extra = (lambda folder: write_png(folder / "camera_rgb.png", frame.rgb)) if frame is not None else None
    sidecar = save_capture(cap, out, overwrite=overwrite, extra=extra, config=configs)
    if json_out:
        typer.echo(json.dumps(cap.meta, indent=2))
        return
    typer.echo(_report(cap.meta))
    if kind == "realsense":
        r = cap.meta["realsense"]
        typer.echo(f"realsense {r['name']} ({r['serial']}): {r['intrinsics']['width']}x{r['intrinsics']['height']}, "
                   f"cloud in the {cap.meta['frame'].replace('_', ' ')} frame")
    if kind == "sim":
        s = cap.meta["sim"]
        t = s["timing_ms"]
        typer.echo(f"sim camera ({s['camera']['renderer']}): render {t['render_ms']:.0f} ms, back-projection {t['back_project_ms']:.0f} ms, "
                   f"filters+segmentation {t['pipeline_ms']:.0f} ms; marking remaining {100 * s['marking_remaining']:.0f}%")
    mesh = cap.meta.get("provenance", {}).get("mesh")
    if mesh is not None:
        typer.echo(f"mesh: {mesh['vertices']} vertices, {mesh['triangles']} triangles, {mesh['area_m2'] * 1e4:.1f} cm², "
                   f"sampled every {mesh['sample_spacing_m'] * 1e3:g} mm into {mesh['samples']} points "
                   f"(colour: {mesh['colour']}; seed {mesh['seed']}); kept as mesh.npz")
    typer.echo(f"wrote {sidecar.parent}/ (cloud.npz, cloud.ply, {'mesh.npz, ' if mesh is not None else ''}capture.json, "
               f"config.json{', camera_rgb.png' if frame is not None else ''})")


_SOURCES = ("file", "synthetic", "sim", "realsense")


def _resolve_source(source: str | None, from_file, synthetic, sim_object) -> str:
    """``--source``, or the one of --from / --synthetic / --object given; one line when it is
    missing, unknown or conflicting."""
    from tergodic_cli.errors import require

    given = [name for name, value in (("file", from_file), ("synthetic", synthetic), ("sim", sim_object)) if value is not None]
    usage = "use --from FILE, --synthetic OBJECT (see --help) or --source sim --object bowl|plate|mug|FILE.obj"
    if source is None:
        require(len(given) == 1, "give exactly one source", usage)
        return given[0]
    require(source in _SOURCES, f"unknown --source '{source}'", f"use one of {', '.join(_SOURCES)}")
    others = [g for g in given if g != source]
    require(not others, f"--source {source} does not go with "
            f"{', '.join('--' + {'file': 'from', 'sim': 'object'}.get(g, g) for g in others)}", usage)
    require(source != "file" or from_file is not None, "--source file needs --from FILE", usage)
    require(source != "synthetic" or synthetic is not None, "--source synthetic needs --synthetic OBJECT", usage)
    return source


def _report(m: dict) -> str:
    """The capture's stages with their counts, target share, spacing and extent."""
    lines = ["stage               points"]
    lines += [f"  {f['stage']:<17} {f['points']:>7}" for f in m["filters"]]
    t = m["target"]
    ext = " x ".join(f"{e * 1e3:.1f}" for e in m["extent_m"])
    lines += [
        f"target '{t['spec']}' ({t['voxel_rule']}): {m['counts']['target']} of {m['counts']['output']} points ({100 * t['share']:.1f}%)",
        f"mean spacing h: {m['spacing_h_m'] * 1e3:.3f} mm    extent: {ext} mm",
    ]
    return "\n".join(lines)
