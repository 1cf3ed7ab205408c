"""Universal Robots e-Series through ``ur_rtde`` (SDU Robotics; ``--robot ur``, ``pip install 'tergodic[ur]'``).

API used (ur_rtde 1.6.5, checked against the signatures its pybind11 modules report):

- ``rtde_receive.RTDEReceiveInterface(hostname, frequency=-1.0, variables=[], verbose=False,
  use_upper_range_registers=False, rt_priority=0)``: ``getActualQ()``, ``getActualQd()`` (rad, rad/s),
  ``getActualTCPPose()`` (x, y, z m and a rotation vector, base frame), ``getActualTCPForce()`` (the
  wrench at the TCP, base-frame axes, payload compensated: the environment's push on the tool),
  ``getTimestamp()`` (s), ``isProtectiveStopped()``, ``isEmergencyStopped()``, ``disconnect()``.
  Reading takes no control of the robot (the dry run uses only this).
- ``rtde_control.RTDEControlInterface(hostname, frequency=-1.0, flags=FLAG_UPLOAD_SCRIPT, ur_cap_port=50002,
  rt_priority=0)`` uploads its control script: ``forceMode(task_frame, selection_vector, wrench, type,
  limits)``, ``forceModeSetDamping(damping)`` ([0, 1]), ``forceModeStop()``; ``servoL(pose, speed,
  acceleration, time, lookahead_time, gain)`` (lookahead 0.03-0.2 s, gain 100-2000), ``servoStop(a)``;
  ``moveJ(q, speed, acceleration, asynchronous)``; ``speedStop(a)``; ``setTcp(pose)``;
  ``isProgramRunning()``; ``stopScript()``; ``disconnect()``.

How the paper's controller drives a position-controlled arm: the UR's force mode is an admittance in
the controller (500 Hz): along every compliant axis of the task frame it moves so that the wrench it
applies reaches the commanded one. Each period the run computes the paper's wrench, eq. 47 before the
Jacobian (K_L V_L + W_C: line stiffness and the wrench PID; the damping D_V V_ee is the force mode's
own, see :meth:`URArm.command_line`; the same
:class:`~tergodic_cli.robot.controller.LineForceController` and
:class:`~tergodic_cli.robot.controller.LineTargetLaw` as the simulation, its wrench output
``wrench_cmd``) and hands it to ``forceMode`` in the TCP frame with all six axes compliant. Free-space
moves stream poses with ``servoL``; set-up joint moves are ``moveJ``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tergodic_cli.backends.extras import import_sdk, one_line
from tergodic_cli.backends.impedance import ImpedanceTarget
from tergodic_cli.backends.ur.model import MODELS, ur_model
from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.robot.interfaces import ArmState, LineTarget, WrenchSensor


def ur_gains():
    """The wrench PID's gains through force mode: in contact the UR applies the commanded wrench within
    a period, so the PID's proportional gain must stay well below 1 (a gain of 2, the simulation's for
    a sponge with its own dynamics, flips the force's sign every period); the integral does the work
    (k_i dt = 0.3 per 100 Hz period: the error halves in about two periods)."""
    from tergodic_cli.robot.controller import ControllerGains

    return ControllerGains(kp=0.3, ki=30.0)


@dataclass
class URConfig(Config):
    """How to reach and drive a UR.

    ip : the robot's address. model : "ur3e", "ur5e" or "ur10e" (kinematics and limits,
    :mod:`~tergodic_cli.backends.ur.model`). frequency : Hz of the RTDE interfaces (e-Series: 500).
    stream_hz : Hz at which the run sends force-mode wrenches and servo poses. tool_length : m, the TCP
    (sponge tip) along the flange's z, sent with ``setTcp``. move_speed, move_acceleration : rad/s and
    rad/s² of the set-up ``moveJ``. servo_lookahead (s), servo_gain : ``servoL``'s smoothing and gain.
    force_damping : ``forceModeSetDamping`` in [0, 1]. speed_limit : (6,) m/s and rad/s, force mode's
    limits on the compliant axes.
    """

    ip: str
    model: str = "ur5e"
    frequency: float = 500.0
    stream_hz: float = 100.0
    tool_length: float = 0.0
    move_speed: float = 0.5
    move_acceleration: float = 0.8
    servo_lookahead: float = 0.1
    servo_gain: float = 300.0
    force_damping: float = 0.1
    speed_limit: tuple = field(default_factory=lambda: (0.05, 0.05, 0.05, 0.5, 0.5, 0.5))

    def validate(self) -> None:
        require(isinstance(self.ip, str) and self.ip.strip() != "", "--robot ur needs the robot's address",
                "pass --robot-ip, the UR controller's address")
        require(self.model in MODELS, f"unknown UR model '{self.model}'", f"use one of {', '.join(MODELS)}")
        require(10.0 <= self.stream_hz <= 500.0, f"stream rate {self.stream_hz} Hz is outside 10-500 Hz", "e.g. 125")
        require(0.03 <= self.servo_lookahead <= 0.2, f"servo lookahead {self.servo_lookahead} s is outside 0.03-0.2 s", "e.g. 0.1")
        require(100.0 <= self.servo_gain <= 2000.0, f"servo gain {self.servo_gain} is outside 100-2000", "e.g. 300")
        require(0.0 <= self.force_damping <= 1.0, f"force damping {self.force_damping} is outside [0, 1]", "e.g. 0.1")
        require(len(self.speed_limit) == 6 and all(v > 0 for v in self.speed_limit),
                "speed_limit must be 6 positive numbers", "m/s and rad/s, e.g. 0.05 x 3 and 0.5 x 3")


def pose_vector(T: np.ndarray) -> list[float]:
    """(4, 4) -> UR's pose vector (x, y, z m, rx, ry, rz rotation vector)."""
    from tergodic_cli.robot.ga import matrix_to_rotvec

    T = np.asarray(T, dtype=float)
    return [*T[:3, 3].tolist(), *np.asarray(matrix_to_rotvec(T[:3, :3]), dtype=float).tolist()]


def pose_matrix_of(v) -> np.ndarray:
    """UR's pose vector -> (4, 4)."""
    from tergodic_cli.robot.ga import pose_matrix, rotvec_to_matrix

    v = np.asarray(v, dtype=float).reshape(6)
    return pose_matrix(rotvec_to_matrix(v[3:]), v[:3])


class URArm:
    """A UR behind :class:`~tergodic_cli.backends.streamed.StreamedArm`: line targets become the paper's
    wrench in force mode (:meth:`command_line`), pose references ``servoL`` (:meth:`command_impedance`).

    Parameters
    ----------
    cfg : URConfig. gains : ControllerGains (None: :func:`ur_gains`). read_only : receive only (the dry run).
    """

    name = "ur-rtde"
    controller = "line impedance + wrench PID, as the UR's force mode"

    def __init__(self, cfg: URConfig, gains=None, read_only: bool = False):
        from tergodic_cli.robot.controller import LineForceController, LineTargetLaw

        cfg.validate()
        self.cfg, self.read_only = cfg, read_only
        self.model = ur_model(cfg.model, cfg.tool_length)
        self.joint_names = list(self.model.joint_names)
        self.q_min, self.q_max, self.dq_max = self.model.q_min, self.model.q_max, self.model.dq_max
        self.home = self.model.home.copy()
        self.stream_hz = float(cfg.stream_hz)
        self.ctrl = LineForceController(gains or ur_gains(), 1.0 / self.stream_hz, self.home,
                                        np.array([1.0, 0.0, 0.0]), self.q_min, self.q_max)
        self.law = LineTargetLaw()
        self.r = self.c = None
        self._mode: str | None = None  # None | "force" | "servo"
        self._error: str | None = None
        self.last_tau = np.zeros(6)

    # ------------------------------------------------------------------ connection
    @property
    def is_connected(self) -> bool:
        return self.r is not None

    def connect(self) -> None:
        if self.r is not None:
            return
        cfg = self.cfg
        rr = import_sdk("rtde_receive")
        try:
            self.r = rr.RTDEReceiveInterface(cfg.ip, float(cfg.frequency))
            if not self.read_only:
                rc = import_sdk("rtde_control")
                self.c = rc.RTDEControlInterface(cfg.ip, float(cfg.frequency))
                self.c.setTcp([0.0, 0.0, float(cfg.tool_length), 0.0, 0.0, 0.0])
        except TergodicError:
            raise
        except Exception as exc:  # ur_rtde raises RuntimeError for a refused connection or a busy robot
            self.r = self.c = None
            raise TergodicError(f"cannot connect to the UR at {cfg.ip}: {one_line(exc)}",
                                "check the address and the cable, put the robot in Remote Control and release the brakes") from None

    def _need(self):
        if self.r is None:
            raise TergodicError("the UR is not connected", "call connect() first")
        return self.r

    def disconnect(self) -> None:
        if self.r is None:
            return
        try:
            if self.c is not None:
                self.stop()
                self.c.stopScript()
                self.c.disconnect()
        finally:
            self.r.disconnect()
            self.r = self.c = None

    # ------------------------------------------------------------------ state
    def read_state(self) -> ArmState:
        """The robot's joints and TCP pose; the Jacobian from the model's chain at those joints."""
        from tergodic_cli.robot.kernels import fk_jacobian

        r = self._need()
        q = np.asarray(r.getActualQ(), dtype=float)
        dq = np.asarray(r.getActualQd(), dtype=float)
        T_chain, J = np.empty((4, 4)), np.empty((6, 6))
        fk_jacobian(q, *self.model.chain, T_chain, J)
        return ArmState(float(r.getTimestamp()), q, dq, pose_matrix_of(r.getActualTCPPose()), J)

    def fault(self) -> str | None:
        r = self._need()
        if self._error is not None:
            return self._error
        if r.isEmergencyStopped():
            self._error = "the UR is emergency-stopped"
        elif r.isProtectiveStopped():
            self._error = "the UR made a protective stop (a collision or a force over its limit); it stopped"
        elif self.c is not None and not self.c.isProgramRunning():
            self._error = "the UR's control script stopped (Remote Control lost, or a stop from the pendant)"
        return self._error

    # ------------------------------------------------------------------ commands
    def bind(self, contact, guard) -> None:
        """Nothing to hand over: the wrench PID runs here, on the run's contact wrench."""

    def command_line(self, target: LineTarget, x_ref=None, threshold: float = 1.0, wrench=None) -> None:
        """The paper's wrench towards ``target`` (the simulation's LineTargetLaw on this arm's state and the
        run's contact ``wrench`` (6,), ee frame) as force mode in the TCP frame, all axes compliant."""
        c = self._control()
        st = self.read_state()
        if x_ref is not None:
            self.ctrl.x_ref = x_ref
        w = np.zeros(6) if wrench is None else np.asarray(wrench, dtype=float)
        # The damping D_V V_ee is the UR's own (force mode's, forceModeSetDamping): the wrench is computed
        # at rest. Fed back on the measured speed through the UR's admittance, a second damper makes a
        # loop that oscillates (and the contact-loss guard's 1000 N s/m would brake against the UR's).
        still = ArmState(st.t, st.q, np.zeros_like(st.dq), st.ee_pose, st.jacobian)
        out = self.law.step(self.ctrl, still, w, target, float(threshold))
        if self._mode != "force":
            if self._mode == "servo":
                c.servoStop(10.0)
            c.forceModeSetDamping(float(self.cfg.force_damping))
            self._mode = "force"
        self.last_tau = out.tau
        ok = c.forceMode(pose_vector(st.ee_pose), [1, 1, 1, 1, 1, 1], np.asarray(out.wrench_cmd, dtype=float).tolist(), 2,
                         list(map(float, self.cfg.speed_limit)))
        if not ok:
            self._error = "the UR refused a force-mode command"

    def command_impedance(self, target: ImpedanceTarget) -> None:
        """Servo the TCP to ``target.pose`` over one period (``servoL``; the UR is position-controlled,
        the stiffness and damping of the reference are its own)."""
        c = self._control()
        if self._mode == "force":
            c.forceModeStop()
        self._mode = "servo"
        cfg = self.cfg
        if not c.servoL(pose_vector(target.pose), 0.0, 0.0, 1.0 / self.stream_hz, float(cfg.servo_lookahead), float(cfg.servo_gain)):
            self._error = "the UR refused a servo command"

    def move_joints(self, q: np.ndarray, speed: float | None = None) -> None:
        """Blocking ``moveJ``; ``speed`` in (0, 1] scales cfg.move_speed."""
        c = self._control()
        qd = np.asarray(q, dtype=float).reshape(6)
        require(bool(np.all(qd >= self.q_min) and np.all(qd <= self.q_max)), f"joint target {np.round(qd, 3).tolist()} rad is outside the joint limits",
                "choose a reachable pose")
        self.stop()
        f = 1.0 if speed is None else float(speed)
        require(0.0 < f <= 1.0, f"move speed {f} is not in (0, 1]", "e.g. 0.5")
        if not c.moveJ(qd.tolist(), float(self.cfg.move_speed) * f, float(self.cfg.move_acceleration), False):
            self._error = "the UR stopped during a joint move"
            raise TergodicError(self._error, "check the workspace for obstacles, clear the stop on the pendant and retry")

    def stop(self) -> None:
        """End force mode or servoing; the arm comes to rest."""
        if self.c is None:
            return
        try:
            if self._mode == "force":
                self.c.forceModeStop()
            elif self._mode == "servo":
                self.c.servoStop(10.0)
            self.c.speedStop(10.0)
        except Exception as exc:  # noqa: BLE001 - a stopped robot refuses; say so, do not fight it
            self._error = self._error or f"the UR stopped: {one_line(exc)}"
        finally:
            self._mode = None
            self.law.mode = None

    def _control(self):
        self._need()
        if self.c is None:
            raise TergodicError("a dry run sends no command", "this is a bug; please report it")
        return self.c


class URForceSensor(WrenchSensor):
    """The UR e-Series' own flange F/T sensor as a WrenchSensor: ``getActualTCPForce`` (the environment's
    wrench on the tool at the TCP, base-frame axes, payload compensated: set the payload on the pendant)
    turned into this package's convention (the arm's wrench on the tool, TCP frame: the negative,
    rotated into the TCP)."""

    def __init__(self, arm: URArm, tare_samples: int = 20):
        super().__init__(np.eye(4), tare_samples)
        self.arm = arm

    def connect(self) -> None:
        self.arm.connect()

    def _sample(self) -> tuple[float, np.ndarray]:
        r = self.arm._need()
        R = pose_matrix_of(r.getActualTCPPose())[:3, :3]
        f = np.asarray(r.getActualTCPForce(), dtype=float)
        return float(r.getTimestamp()), -np.concatenate([R.T @ f[:3], R.T @ f[3:]])

    def disconnect(self) -> None:
        """The arm owns the connection."""


def make_arm(cfg: URConfig, sensor=None, gains=None, read_only: bool = False) -> URArm:
    """The registry's factory (backends/registry.py): a UR, not yet connected (``sensor``: unused, the
    run reads it)."""
    return URArm(cfg, gains=gains, read_only=read_only)


def make_sensor(cfg, arm: URArm) -> URForceSensor:
    """The registry's factory for ``--ft ur``: the UR's own flange F/T sensor."""
    return URForceSensor(arm)
