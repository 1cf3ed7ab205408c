"""Franka Panda / FR3 through the official ``pylibfranka`` bindings: the paper's 1 kHz torque control
(``--robot franka-torque``, ``pip install 'tergodic[libfranka]'``).

API used (pylibfranka 0.21.3, checked against its type stubs ``pylibfranka/_pylibfranka.pyi``):

- ``Robot(robot_ip_address, realtime_config=RealtimeConfig.kEnforce)`` connects (``kIgnore``: no
  real-time kernel needed; the dry run uses it, as it sends no command); ``read_once()`` -> ``RobotState``
  (``q``, ``dq``, ``tau_J``, ``O_T_EE`` 16 numbers column-major, ``time`` a ``Duration`` with
  ``to_sec()``, ``current_errors`` an ``Errors`` that is truthy when set); ``load_model()`` -> ``Model``
  with ``zero_jacobian(state)`` (42 numbers, column-major (6, 7)) and ``coriolis(state)`` (7,);
  ``set_collision_behavior(lower_torque, upper_torque, lower_force, upper_force)`` (7, 7, 6, 6),
  ``set_EE(NE_T_EE)`` (16, column-major), ``automatic_error_recovery()``, ``stop()``.
- ``start_torque_control()`` -> ``ActiveControlBase``: ``readOnce()`` -> (``RobotState``, ``Duration``)
  blocks until the next 1 ms state; ``writeOnce(Torques(tau))`` sends the torque (libfranka adds
  gravity; the Coriolis torque is the caller's); ``Torques.motion_finished = True`` ends the control.
- Exceptions: ``NetworkException``, ``RealtimeException``, ``ControlException``, ``CommandException``
  (subclasses of ``RuntimeError``).

The loop runs in a process of its own (:mod:`tergodic_cli.backends.torque` says why).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tergodic_cli.backends.extras import import_sdk, one_line
from tergodic_cli.backends.franka.franky import LIMITS, _connect_fix
from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, require


@dataclass
class LibfrankaConfig(Config):
    """How to reach the arm and run its 1 kHz loop.

    ip : the FCI address. model : "panda" or "fr3" (joint limits). realtime : "enforce" (a PREEMPT_RT
    kernel, as libfranka requires for control) or "ignore" (bench tests only; the dry run always
    ignores it: it sends nothing). ne_t_ee : (4, 4) the TCP (sponge tip) in Desk's nominal
    end-effector frame, or None. torque_thresholds, force_thresholds : libfranka's collision reflex
    (N m, N). stream_hz : Hz at which the run sends line targets to the loop. lift_speed : m/s, the
    loop's own lift after a force fault. isolate : "process" (the loop in its own process) or
    "inline" (tests with a fake SDK).
    """

    ip: str
    model: str = "panda"
    realtime: str = "enforce"
    ne_t_ee: np.ndarray | None = None
    torque_thresholds: float = 30.0
    force_thresholds: float = 40.0
    stream_hz: float = 100.0
    lift_speed: float = 0.02
    isolate: str = "process"

    def validate(self) -> None:
        require(isinstance(self.ip, str) and self.ip.strip() != "", "--robot franka-torque needs the robot's address",
                "pass --robot-ip, the FCI address set in Desk (e.g. 172.16.0.2)")
        require(self.model in LIMITS, f"unknown Franka model '{self.model}'", "use panda or fr3")
        require(self.realtime in ("enforce", "ignore"), f"unknown realtime setting '{self.realtime}'", "use enforce or ignore")
        require(10.0 <= self.stream_hz <= 500.0, f"stream rate {self.stream_hz} Hz is outside 10-500 Hz", "e.g. 100")
        require(self.isolate in ("process", "inline"), f"unknown isolate '{self.isolate}'", "use process")


def _mat(values, rows: int, cols: int) -> np.ndarray:
    """libfranka's column-major arrays as a C-contiguous (rows, cols) matrix."""
    return np.ascontiguousarray(np.asarray(values, dtype=float).reshape(cols, rows).T)


class LibfrankaDevice:
    """The pylibfranka side of the loop (a :class:`~tergodic_cli.backends.torque.TorqueDevice`), made and
    used in the loop process. ``read_only``: never starts control (the dry run)."""

    def __init__(self, cfg: LibfrankaConfig, read_only: bool = False):
        self.cfg, self.read_only = cfg, read_only
        self.fr = self.robot = self.model = self.ctrl = None

    def connect(self) -> None:
        fr = import_sdk("pylibfranka")
        self.fr, cfg = fr, self.cfg
        rt = fr.RealtimeConfig.kEnforce if cfg.realtime == "enforce" and not self.read_only else fr.RealtimeConfig.kIgnore
        try:
            self.robot = fr.Robot(cfg.ip, rt)
        except Exception as exc:  # NetworkException, RealtimeException, IncompatibleVersion...
            raise TergodicError(f"cannot connect to the Franka at {cfg.ip}: {one_line(exc)}", _connect_fix(exc)) from None
        self.model = self.robot.load_model()
        if self.read_only:
            return
        try:
            if self.robot.read_once().current_errors:
                self.robot.automatic_error_recovery()
            tt, ft = float(cfg.torque_thresholds), float(cfg.force_thresholds)
            self.robot.set_collision_behavior([tt] * 7, [tt] * 7, [ft] * 6, [ft] * 6)
            if cfg.ne_t_ee is not None:
                self.robot.set_EE(np.asarray(cfg.ne_t_ee, dtype=float).flatten(order="F").tolist())
        except Exception as exc:
            raise TergodicError(f"the Franka at {cfg.ip} refused its set-up: {one_line(exc)}",
                                "recover the robot in Desk (unlock the joints, activate FCI) and retry") from None

    def read(self) -> tuple:
        s = self.ctrl.readOnce()[0] if self.ctrl is not None else self.robot.read_once()
        return (float(s.time.to_sec()), np.asarray(s.q, dtype=float), np.asarray(s.dq, dtype=float), _mat(s.O_T_EE, 4, 4),
                _mat(self.model.zero_jacobian(s), 6, 7), np.asarray(self.model.coriolis(s), dtype=float),
                np.asarray(s.tau_J, dtype=float))

    def errors(self) -> str | None:
        """The robot's current errors as one line, or None."""
        e = self.robot.read_once().current_errors
        return str(e) if e else None

    def start(self) -> None:
        if self.read_only:
            raise TergodicError("a dry run sends no command", "this is a bug; please report it")
        self.ctrl = self.robot.start_torque_control()

    def write(self, tau: np.ndarray) -> None:
        self.ctrl.writeOnce(self.fr.Torques(np.asarray(tau, dtype=float).tolist()))

    def finish(self) -> None:
        if self.ctrl is None:
            return
        try:
            t = self.fr.Torques([0.0] * 7)
            t.motion_finished = True
            self.ctrl.writeOnce(t)
        finally:
            self.ctrl = None

    def close(self) -> None:
        if self.robot is not None:
            try:
                self.finish()
            finally:
                self.robot = None


def make_libfranka_arm(cfg: LibfrankaConfig, sensor, gains=None, sensor_frame=None, read_only: bool = False):
    """A Franka torque arm (:class:`~tergodic_cli.backends.torque.TorqueArm`), not yet connected.

    Parameters
    ----------
    cfg : LibfrankaConfig. sensor : the F/T sensor (Bota, Net F/T), unconnected: it connects in the
        loop process. gains : ControllerGains (None: the simulation's). sensor_frame : (4, 4) the sensor
        in the TCP frame (None: the sensor's own ``frame_in_ee``). read_only : a dry run's arm.
    """
    from tergodic_cli.backends.pybullet.arms.panda import HOME, JOINT_D, JOINT_K, JOINTS, TAU_MAX
    from tergodic_cli.backends.torque import LoopSpec, TorqueArm
    from tergodic_cli.robot.controller import ControllerGains

    cfg.validate()
    import_sdk("pylibfranka")  # the install hint now, before anything connects
    q_min, q_max, dq_max = (x.copy() for x in LIMITS[cfg.model])
    spec = LoopSpec(device=lambda: LibfrankaDevice(cfg), sensor=lambda: sensor, gains=gains or ControllerGains(),
                    q_rest=np.array(HOME), q_min=q_min, q_max=q_max, tau_max=np.array(TAU_MAX),
                    joint_k=np.array(JOINT_K), joint_d=np.array(JOINT_D), lift_speed=cfg.lift_speed)
    frame = sensor_frame if sensor_frame is not None else getattr(sensor, "frame_in_ee", None)
    arm = TorqueArm(spec, "franka-libfranka", JOINTS, HOME, dq_max, frame, cfg.stream_hz, cfg.isolate,
                    reason=lambda msg: f"the Franka stopped: {msg}")
    if read_only:
        arm.reader = lambda: LibfrankaDevice(cfg, read_only=True)
    return arm


def make_arm(cfg: LibfrankaConfig, sensor, gains=None, read_only: bool = False):
    """The registry's factory (backends/registry.py): see :func:`make_libfranka_arm`."""
    return make_libfranka_arm(cfg, sensor, gains=gains, read_only=read_only)
