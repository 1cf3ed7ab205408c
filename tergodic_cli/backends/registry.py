"""The one backend registry: name -> config dataclass -> factory, for robots, F/T sensors and cameras.

A *backend* is one device family behind the robot layer's interfaces, in one folder of
``tergodic_cli/backends/`` (``pybullet/``, ``franka/``, ``ur/``, ``bota/``, ``netft/``, ``realsense/``),
with its config dataclass and a factory. :data:`BACKENDS` lists them all, one line each; the CLI's
``--robot``, ``--ft`` and the camera sources are its names, and
:func:`~tergodic_cli.backends.factory.make_hardware` / :func:`~tergodic_cli.backends.factory.make_camera`
build them from it. Modules are named as strings and imported only when a backend is built, so the
CLI starts without any SDK.

Adding a backend (docs/hardware.md, "Adding a robot or a sensor"): a folder with its config dataclass
and its factory, and one :class:`Backend` line here.

Factories
---------
robot (hardware) : ``make_arm(cfg, sensor, gains, read_only) -> arm`` (an ImpedanceArm, or an arm that
    takes line targets); an arm with a ``wrench_sensor`` reads the F/T through its own loop.
ft : ``make_sensor(cfg, arm) -> WrenchSensor`` (``cfg`` None for an arm's own estimate).
camera : ``make_camera(cfg) -> Camera``.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, fields

from tergodic_cli.errors import require


@dataclass(frozen=True)
class Backend:
    """One registry line.

    kind : "robot", "ft" or "camera". name : the CLI's name (``--robot``, ``--ft``, camera source).
    config : "module:Class" of its config dataclass, or None (no settings). factory : "module:function"
    (see the module docstring), or None for the robots a run drives itself (kinematic, pybullet).
    sdks : the SDK modules it imports (:func:`~tergodic_cli.backends.extras.import_sdk`: a missing one is
    a one-line install hint). hardware : a real device. arms : for an arm's own force estimate, the robot
    it belongs to. default_ft : a robot's force source when --ft is not given. wrist_ft : the robot's
    own loop reads a wrist F/T sensor (an arm's own estimate will not do). summary : one line.
    """

    kind: str
    name: str
    config: str | None
    factory: str | None
    summary: str
    sdks: tuple[str, ...] = ()
    hardware: bool = True
    arms: tuple[str, ...] | None = None
    default_ft: str | None = None
    wrist_ft: bool = False

    def config_class(self):
        """The config dataclass (imported now), or None."""
        return _load(self.config) if self.config else None

    def make_config(self, **options):
        """The config from ``options``: the dataclass's own fields among them (None keeps a default), validated."""
        cls = self.config_class()
        if cls is None:
            return None
        names = {f.name for f in fields(cls)}
        cfg = cls(**{k: v for k, v in options.items() if k in names and v is not None})
        if hasattr(cfg, "validate"):
            cfg.validate()
        return cfg

    def factory_fn(self):
        return _load(self.factory)

    def import_sdks(self) -> None:
        """Import each SDK now: a missing one raises its one-line install hint (exit code 2)."""
        from tergodic_cli.backends.extras import import_sdk

        for m in self.sdks:
            import_sdk(m)


def _load(path: str):
    module, attr = path.split(":")
    return getattr(importlib.import_module(module), attr)


_B = "tergodic_cli.backends."
#: Every backend, one line each.
BACKENDS: tuple[Backend, ...] = (
    Backend("robot", "kinematic", None, None, "the virtual agent alone", hardware=False),
    Backend("robot", "pybullet", "tergodic_cli.robot.config:RobotConfig", None,
            "a simulated arm (--arm) in PyBullet, 1 kHz torque control", sdks=(), hardware=False),
    Backend("robot", "franka", _B + "franka.franky:FrankaConfig", _B + "franka.franky:make_arm",
            "Franka through franky: streamed Cartesian impedance", sdks=("franky",), default_ft="franka"),
    Backend("robot", "franka-torque", _B + "franka.libfranka:LibfrankaConfig", _B + "franka.libfranka:make_arm",
            "Franka through pylibfranka: the line impedance and wrench PID in a 1 kHz torque loop",
            sdks=("pylibfranka",), wrist_ft=True),
    Backend("robot", "ur", _B + "ur.rtde:URConfig", _B + "ur.rtde:make_arm",
            "Universal Robots e-Series through ur_rtde: the wrench in force mode",
            sdks=("rtde_receive", "rtde_control"), default_ft="ur"),
    Backend("ft", "franka", None, _B + "franka.franky:make_sensor", "the Franka's own external-wrench estimate",
            arms=("franka",)),
    Backend("ft", "ur", None, _B + "ur.rtde:make_sensor", "the UR e-Series' flange F/T sensor", arms=("ur",)),
    Backend("ft", "bota", _B + "bota:BotaConfig", _B + "bota:make_sensor", "Bota Systems F/T sensor",
            sdks=("bota_driver",)),
    Backend("ft", "netft", _B + "netft:NetFTConfig", _B + "netft:make_sensor", "ATI Net F/T over UDP"),
    Backend("camera", "realsense", _B + "realsense:RealSenseConfig", _B + "realsense:make_camera",
            "Intel RealSense depth camera", sdks=("pyrealsense2",)),
)


def names(kind: str, hardware: bool | None = None) -> tuple[str, ...]:
    """The registered names of ``kind`` (only the real devices with ``hardware`` True, the others with False)."""
    return tuple(b.name for b in BACKENDS if b.kind == kind and (hardware is None or b.hardware == hardware))


def get(kind: str, name: str, option: str) -> Backend:
    """The backend ``name`` of ``kind``; an unknown one is a one-line error naming ``option`` and the choices."""
    for b in BACKENDS:
        if b.kind == kind and b.name == name:
            return b
    require(False, f"unknown {option} '{name}'", f"use one of {', '.join(names(kind))}")
