"""The closed outer loop in simulation (paper Fig. 3, issue 6): clean, look again, re-target, continue.

``tergodic explore CAPTURE --robot pybullet --recapture-every K --until-clean S [--max-steps N]``
on a ``--source sim`` capture (docs/closed_loop.md). One cycle: engage and press at F_d; K explorer
steps in contact, the sponge's contacts (merged into their force-weighted mean point and summed
force) fading the *same* textured object the camera renders every ``clean_every`` simulated seconds;
retreat to the picture pose, re-capture (render, back-project, the capture pipeline), move the new
p onto the basis points and hand it to the explorer. The geometry has not changed, so the basis is
reused, never recomputed (each re-capture checks its cache key). The loop stops when the camera
sees at most ``until_clean`` of the first capture's marking (Σp, the ink weighed by its colour
intensity), or when ``max_steps`` are spent. The robot, the cleaning model and the camera run in one
process; the camera has its own PyBullet client, so the arm never occludes it.

Entry point: :func:`clean_with_robot`.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, fields, replace
from typing import Callable

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.errors import require
from tergodic_cli.robot.config import RobotConfig


@dataclass
class CleaningLoopConfig(Config):
    """The outer loop's settings (saved in summary.json as ``closed_loop``).

    recapture_every : K, explorer steps between two re-captures.
    until_clean : stop once the camera sees at most this share of the initial marking (0.05: 95 % removed).
    max_steps : the step budget: explorer steps in contact over all cycles.
    clean_every : simulated seconds between two updates of the cleaning model (the sponge moves
        0.75 mm in 50 ms at 15 mm/s, a tenth of the 7.5 mm footprint radius).
    reset_coverage : each cycle starts its coverage afresh on the new target (the new p already
        says what is left; old coverage would hide the spots that were wiped but not yet clean).
    """

    recapture_every: int = 200
    until_clean: float = 0.05
    max_steps: int = 2000
    clean_every: float = 0.05
    reset_coverage: bool = True


def validate_loop_config(cfg: CleaningLoopConfig) -> None:
    """Refuse impossible loop settings with a one-line problem; fix."""
    require(int(cfg.recapture_every) >= 1, f"--recapture-every must be >= 1 explorer steps, got {cfg.recapture_every}",
            "e.g. --recapture-every 200")
    require(math.isfinite(cfg.until_clean) and 0.0 <= cfg.until_clean < 1.0,
            f"--until-clean must be a share in [0, 1), got {cfg.until_clean}", "e.g. --until-clean 0.05 (95 % removed)")
    require(int(cfg.max_steps) >= 1, f"--max-steps must be >= 1, got {cfg.max_steps}", "e.g. --max-steps 2000")
    require(math.isfinite(cfg.clean_every) and 0.0 < cfg.clean_every <= 1.0,
            f"the cleaning update period {cfg.clean_every} s is outside (0, 1] s", "e.g. 0.05")


# ----------------------------------------------------------------------------- the scene of a sim capture
def sim_scene_configs(meta: dict):
    """(SimObjectConfig, SimCameraConfig, CaptureConfig) that reproduce a ``--source sim`` capture.

    ``meta`` is the capture's sidecar (``capture.json``): its ``sim`` record (object, camera with
    the renderer actually used) and the pipeline's ``config``.
    """
    from tergodic_cli.capture import CaptureConfig
    from tergodic_cli.backends.pybullet.camera import SimCameraConfig
    from tergodic_cli.capture.textured import CleaningModel, SimObjectConfig

    sim = meta.get("sim")
    require(isinstance(sim, dict) and isinstance(sim.get("object"), dict) and isinstance(sim.get("camera"), dict),
            "the closed loop needs a simulated capture (this one has no 'sim' record)",
            "capture with 'tergodic capture --source sim --object bowl --marking X --out CAPTURE'")
    o = dict(sim["object"])
    o["cleaning"] = CleaningModel(**(o.get("cleaning") or {}))
    c, p = dict(sim["camera"]), dict(meta.get("config") or {})
    for d, keys in ((o, ("pose",)), (c, ("pose",)), (p, ("crop", "outliers"))):  # lists: tuples
        d.update({k: tuple(d[k]) for k in keys if d.get(k) is not None})
    p.update(source="sim", allow_empty_target=True)
    return _known(SimObjectConfig, o), _known(SimCameraConfig, c), _known(CaptureConfig, p)


def _known(cls, d: dict):
    """``cls`` from the keys of ``d`` that are its fields (a sidecar record holds more)."""
    return cls(**{f.name: d[f.name] for f in fields(cls) if f.name in d})


def _basis_key(points: np.ndarray, basis_meta: dict) -> str:
    from tergodic_cli.basis import BasisConfig
    from tergodic_cli.basis.cache import geometry_key

    conf = basis_meta.get("config") if isinstance(basis_meta.get("config"), dict) else {}
    return geometry_key(np.asarray(points, dtype=np.float64), _known(BasisConfig, conf))[0]


class _Cleaner:
    """The robot's contact hook: the sponge's contacts fade the textured object's marking."""

    def __init__(self, obj):
        self.obj = obj
        self.impulse = 0.0  # N s pressed above the cleaning threshold
        self.calls = 0
        self.seconds = 0.0

    def __call__(self, contacts: list, dt: float) -> None:
        f = float(sum(c[2] for c in contacts))  # the force-weighted mean point, as SimArm.contact's
        if not contacts or f <= self.obj.cfg.cleaning.force_min:
            return
        t = time.perf_counter()
        self.obj.clean((sum(c[2] * c[0] for c in contacts) / f)[None, :], np.array([f]), dt)
        self.seconds += time.perf_counter() - t
        self.impulse += f * dt
        self.calls += 1


# ----------------------------------------------------------------------------- the loop
def clean_with_robot(capture, explorer, robot_cfg: RobotConfig, camera=None,
                     on_step: Callable[[int, dict], None] | None = None,
                     on_event: Callable[[int, str], None] | None = None,
                     on_recapture: Callable[[int, dict], None] | None = None,
                     loop_cfg: CleaningLoopConfig | None = None,
                     on_log: Callable[[str, int, dict], None] | None = None) -> dict:
    """Clean the simulated object with the robot until the camera sees at most ``until_clean`` of the marking.

    Parameters
    ----------
    capture : the initial ``--source sim`` :class:`~tergodic_cli.capture.Capture` (robot base frame);
        its ``meta["sim"]`` rebuilds the textured object and the camera, its ``meta["config"]``
        the capture pipeline of every re-capture.
    explorer : :class:`~tergodic_cli.explore.Explorer` on the capture's basis and target, built with
        :func:`~tergodic_cli.robot.robot_explore_config` (its basis is reused for every re-capture).
    robot_cfg : :class:`RobotConfig` (``object_pose`` None or the identity: the sim capture says where the object is).
    camera : an open :class:`~tergodic_cli.backends.pybullet.camera.SimCamera` whose ``obj`` is the scene
        (tests: a small image); None = built from the capture's record and closed at the end.
    on_step : on_step(step, robot_sample_dict) after each explorer step. The last step of a cycle is
        handed over after its re-capture, with ``marking_remaining`` (camera), ``marking_remaining_true``
        and ``recapture_ms`` added to its sample.
    on_event : on_event(step, text): state transitions, re-captures, warnings.
    on_recapture : on_recapture(step, record) after each re-capture, ``record`` as in ``recapture_log``
        plus ``target`` (n,) the new p on the basis points and ``applied`` (False for the last one,
        which ended the loop). See :func:`log_recapture`.
    loop_cfg : :class:`CleaningLoopConfig` (K, the remaining-marking threshold, the step budget);
        None = its defaults.
    on_log : the run's state transitions and 1 kHz force windows (:class:`~tergodic_cli.robot.run.ContactRun`).

    Returns
    -------
    The robot summary extras (:func:`~tergodic_cli.robot.summarize_robot` and the run's figures, as
    :func:`~tergodic_cli.robot.explore_with_robot`), plus ``marking_remaining`` (camera-seen share of
    the initial marking at the end), ``marking_remaining_true``, ``recaptures``, ``recapture_ms_median``,
    ``recapture_ms_max``, ``recapture_log`` (one record per re-capture: step, t_sim, mass Σp, shares, timings,
    ``basis_cache_hit``), ``basis_recomputed`` (always False), ``clean_reached``, ``loop_stop`` and
    ``closed_loop`` (the settings).
    """
    from tergodic_cli.backends.pybullet.camera import SimCamera, SimCaptureConfig, capture_sim, target_on_points
    from tergodic_cli.capture.textured import TexturedObject
    from tergodic_cli.backends.pybullet.arm import RobotRun
    from tergodic_cli.robot.surface import parse_object_pose, sim_object_mesh

    lc = loop_cfg or CleaningLoopConfig()
    validate_loop_config(lc)
    say = on_event or (lambda step, msg: None)
    meta = getattr(capture, "meta", {}) or {}
    obj_cfg, cam_cfg, pipe = sim_scene_configs(meta)
    require(meta.get("frame") == "robot_base", "the capture is not in the robot base frame",
            "use a 'tergodic capture --source sim' capture unchanged")
    if robot_cfg.object_pose is not None:  # the identity is harmless (the cloud is in the base frame already)
        require(bool(np.allclose(parse_object_pose(robot_cfg.object_pose), np.eye(4))),
                "--object-pose cannot move a simulated capture's object",
                "drop --object-pose; place the object when capturing: tergodic capture --source sim --object-pose ...")
    points = np.asarray(explorer.points, dtype=np.float64)
    require(bool(np.array_equal(points, capture.points)),
            "the explorer's basis is not built on this capture's points", "build the explorer on the capture's basis")
    require(float(np.sum(capture.target)) > 0, "the initial capture sees no marking",
            "capture an object with a marking (e.g. --marking X)")
    pipe = replace(pipe, voxel_rule="intensity")  # faint ink counts: the loop's captures weigh ink by intensity
    mass0 = None  # Σp of capture 0, taken below

    own_camera = camera is None
    if own_camera:
        camera = SimCamera(cam_cfg, TexturedObject(obj_cfg))
    obj = camera.obj
    require(obj is not None, "the camera has no textured object", "build it as SimCamera(cfg, TexturedObject(...))")
    basis_meta = dict(getattr(getattr(explorer, "_basis", None), "meta", {}) or {})
    key0 = _basis_key(points, basis_meta)
    run = None
    try:
        sim_cfg = SimCaptureConfig(object=obj.cfg, camera=camera.cfg, pipeline=pipe)
        scene_mesh = sim_object_mesh({"object": obj.cfg.to_dict(), "object_pose": obj.pose.tolist()}, robot_cfg.mesh_edge)
        run = RobotRun(capture, explorer, robot_cfg, on_event=say, scene_mesh=scene_mesh, on_log=on_log)
        cleaner = _Cleaner(obj)
        run.arm.contact_hook = cleaner
        run.arm.hook_every = max(1, int(round(lc.clean_every / robot_cfg.physics_dt)))
        log: list[dict] = []

        def recapture(step: int, check_key: bool = False) -> tuple[dict, np.ndarray]:
            cpu = time.process_time()
            t0 = time.perf_counter()
            cap = capture_sim(sim_cfg, camera=camera, allow_empty_target=True)
            t1 = time.perf_counter()
            # The renderer is deterministic and the geometry unchanged: the re-captured cloud is the
            # basis' own points, in the same order, and p maps one to one. Otherwise (depth noise, a
            # moved object) it goes to the nearest basis point, on the same basis all the same.
            same = bool(np.array_equal(cap.points, points))
            p = cap.target.copy() if same else target_on_points(points, cap)
            t2 = time.perf_counter()
            # Identical points have the basis' cache key by construction; compute it when they are not
            # (and once at the start, as the proof).
            if same and not check_key:
                hit = True
            else:
                hit = cap.points.shape == points.shape and _basis_key(cap.points, basis_meta) == key0
            t3 = time.perf_counter()
            timing = cap.meta["sim"]["timing_ms"]
            rec = {"step": int(step), "t_sim": float(run.scene.t),
                   "mass": float(np.sum(cap.target)),
                   "marking_remaining": float(np.sum(cap.target)) / mass0 if mass0 else 1.0,
                   "marking_remaining_true": float(obj.marking_remaining()),
                   "target_points": int(np.count_nonzero(cap.target > 0)),
                   "target_points_on_basis": int(np.count_nonzero(p > 0)),
                   "ms": 1e3 * (t3 - t0), "capture_ms": 1e3 * (t1 - t0), "transfer_ms": 1e3 * (t2 - t1),
                   "key_ms": 1e3 * (t3 - t2), "texture_ms": timing["texture_ms"],
                   "render_ms": timing["render_ms"], "pipeline_ms": timing["pipeline_ms"],
                   "basis_cache_hit": bool(hit), "same_points": same, "cpu_ms": 1e3 * (time.process_time() - cpu)}
            return rec, p

        # Capture 0, at the picture pose before anything moves: the rebuilt scene must show what the
        # capture showed (it also warms the renderer up).
        rec0, p0 = recapture(0, check_key=True)
        mass0 = rec0["mass"]
        require(mass0 > 0, "the loop's first picture sees no marking", "check the capture's camera and --target colour")
        # the full marking weighs 1 under both rules: capture 0 sees at least the capture's marking
        if mass0 < 0.98 * float(np.sum(capture.target)) or not rec0["basis_cache_hit"]:
            say(0, f"closed loop: warning: the rebuilt scene differs from the capture (marking seen "
                   f"{mass0 / float(np.sum(capture.target)):.3f} of the capture's, same geometry: {rec0['basis_cache_hit']}); "
                   "the target is transferred by nearest point")
        explorer.set_target(p0)  # the ink by intensity from the start
        say(0, f"closed loop: re-capture every {lc.recapture_every} steps until at most {lc.until_clean:.0%} of the "
               f"marking is left, within {lc.max_steps} steps ({camera.renderer}, {camera.cfg.width}x{camera.cfg.height})")

        run.begin()
        pause0 = time.perf_counter()
        done = 0
        clean = False
        stop = "step budget spent"
        with run.guarded():
            while True:
                n = min(int(lc.recapture_every), int(lc.max_steps) - done)
                run.engage()
                run.explore(n, on_step, defer_last=True)
                done += n
                step = run._step()
                run.to_picture(f"{n} explorer steps in this cycle ({done} of {lc.max_steps}); re-capturing")
                t_pause = time.perf_counter()
                rec, p = recapture(step)
                p = p * run.reachable  # reach: the part the tool cannot follow stays dropped (robot/reach.py)
                run.paused_s += time.perf_counter() - t_pause
                log.append(rec)
                clean = rec["marking_remaining"] <= lc.until_clean or not np.any(p > 0)
                last = clean or done >= lc.max_steps
                run.emit_deferred({"marking_remaining": rec["marking_remaining"],
                                   "marking_remaining_true": rec["marking_remaining_true"],
                                   "recapture_ms": rec["ms"]})
                say(step, f"closed loop: re-capture {len(log)} at step {step}: the camera sees "
                          f"{rec['marking_remaining']:.1%} of the marking (ink left {rec['marking_remaining_true']:.1%}; "
                          f"{rec['target_points']} target points); {rec['ms']:.0f} ms, basis reused "
                          f"({'cache hit' if rec['basis_cache_hit'] else 'geometry changed: nearest-point transfer'})")
                if not last:
                    t_pause = time.perf_counter()
                    explorer.set_target(p, reset_coverage=lc.reset_coverage)
                    run.paused_s += time.perf_counter() - t_pause
                if on_recapture is not None:
                    t_cb = time.perf_counter()
                    on_recapture(step, {**rec, "target": p, "applied": not last})
                    run.paused_s += time.perf_counter() - t_cb
                if clean:
                    stop = (f"clean: the camera sees {rec['marking_remaining']:.1%} of the marking (<= {lc.until_clean:.1%}); "
                            f"true ink left {rec['marking_remaining_true']:.1%}")
                    break
                if last:
                    stop = (f"step budget of {lc.max_steps} steps spent with {rec['marking_remaining']:.1%} of the "
                            f"marking left (> {lc.until_clean:.1%}); true ink left {rec['marking_remaining_true']:.1%}")
                    break
            run.finish(stop)
        total_wall = time.perf_counter() - pause0
        ms = [r["ms"] for r in log]
        return {
            **run.result(),
            "marking_remaining": log[-1]["marking_remaining"] if log else None,
            "marking_remaining_true": float(obj.marking_remaining()),
            "recaptures": len(log),
            "recapture_ms_median": float(np.median(ms)) if ms else None,
            "recapture_ms_max": float(np.max(ms)) if ms else None,
            "recapture_cpu_ms_median": float(np.median([r["cpu_ms"] for r in log])) if log else None,
            "recapture_log": log,
            "recapture_initial": rec0,
            "basis_recomputed": False,
            "basis_cache_hits": int(sum(r["basis_cache_hit"] for r in log)),
            "clean_reached": bool(clean),
            "loop_stop": run.stop_reason or stop,
            "steps_done": int(run._step()),
            "cleaning_impulse_Ns": cleaner.impulse,
            "cleaning_updates": cleaner.calls,
            "cleaning_ms_total": 1e3 * cleaner.seconds,
            "realtime_factor_overall": run.scene.t / total_wall if total_wall > 0 else None,
            "closed_loop": {**lc.to_dict(), "camera": {**camera.cfg.to_dict(), "renderer": camera.renderer},
                            "cleaning_model": asdict(obj.cfg.cleaning)},
        }
    finally:
        if run is not None:
            run.close()
        if own_camera:
            camera.close()


def log_recapture(runlog, explorer, step: int, t: float, record: dict) -> None:
    """Log one re-capture into a :class:`~tergodic_cli.runlog.RunLog`: the cloud with the new target, and an event.

    Use as ``on_recapture=lambda step, rec: log_recapture(runlog, explorer, step, step * cfg.dt, rec)``.
    """
    runlog.log_cloud(step, coverage=explorer.coverage, heat=explorer.heat, source=explorer.source,
                     target=record["target"], t=t)
    runlog.log_event(step, t, f"recapture: marking_remaining={record['marking_remaining']:.6f} "
                              f"marking_remaining_true={record['marking_remaining_true']:.6f} "
                              f"recapture_ms={record['ms']:.1f} basis_cache_hit={str(record['basis_cache_hit']).lower()} "
                              f"applied={str(record['applied']).lower()}")
