"""Franka Emika Panda / FR3 through franky (``pip install 'tergodic[franka]'``, module ``franky``).

API used (franky-control 2.0, checked against its type stubs ``franky/_franky.pyi``):

- ``Robot(fci_hostname, relative_dynamics_factor=..., realtime_config=RealtimeConfig.Enforce)``
  connects; ``robot.state`` is a ``RobotState`` (``q``, ``dq``, ``O_T_EE`` as ``Affine``, ``time``
  as ``Duration``); ``robot.model.zero_jacobian(Frame.EndEffector, state)`` the (6, 7) base-frame
  Jacobian; ``set_ee``, ``set_collision_behavior``, ``recover_from_errors``, ``has_errors``,
  ``is_in_control``, ``poll_motion``, ``join_motion``, ``stop``.
- ``JointMotion(np.ndarray(7), relative_dynamics_factor=f)`` for set-up moves (a plain Python
  list is refused by franky 2.0's binding; it needs an array or a ``JointState``).
- ``CartesianImpedanceTrackingMotion`` + ``set_gains(CartesianImpedanceGains)`` +
  ``set_reference(CartesianReference(target=Affine, target_twist=Twist))``: franky's client-side
  Cartesian impedance controller, computed in its 1 kHz real-time thread; Python streams
  references (:mod:`tergodic_cli.backends.impedance` explains the mapping).
- ``TorqueStopMotion`` to end the impedance controller (a torque-mode controller) gracefully.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from tergodic_cli.config import Config
from tergodic_cli.errors import TergodicError, require
from tergodic_cli.backends.extras import import_sdk, one_line
from tergodic_cli.backends.impedance import ImpedanceTarget
from tergodic_cli.robot.interfaces import ArmState, WrenchSensor
from tergodic_cli.backends.pybullet.arms.panda import DQ_MAX, HOME, JOINTS, Q_MAX, Q_MIN

#: Joint limits (rad, rad/s) from Franka's datasheets.
LIMITS = {
    "panda": (Q_MIN, Q_MAX, DQ_MAX),
    "fr3": (np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
            np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
            np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])),
}


@dataclass
class FrankaConfig(Config):
    """How to reach and drive the arm.

    ip : the FCI address (Desk: Settings -> Network). model : "panda" or "fr3" (joint limits).
    stream_hz : rate at which references are streamed from Python (the SDK's controller runs at 1 kHz).
    move_speed : relative dynamics factor (0, 1] of the planned joint moves (set-up, picture pose).
    ne_t_ee : (4, 4) TCP (sponge tip) in Desk's nominal end-effector frame, or None when Desk's
        end-effector already is the sponge tip. Sent with ``set_ee`` at connect.
    torque_thresholds, force_thresholds : libfranka's collision reflex thresholds (N m, N).
    realtime : "enforce" (refuse to run without a PREEMPT_RT kernel) or "ignore" (bench tests only).
    max_delta_tau : N m per 1 ms torque-rate limit of franky's torque motions.
    error_clip : m, franky clamps the impedance controller's translational error to this on each base
        axis, which bounds the commanded force at stiffness × error_clip whatever the reference does.
    """

    ip: str
    model: str = "panda"
    stream_hz: float = 100.0
    move_speed: float = 0.1
    ne_t_ee: np.ndarray | None = None
    torque_thresholds: float = 30.0
    force_thresholds: float = 40.0
    realtime: str = "enforce"
    max_delta_tau: float = 1.0
    error_clip: float = 0.05

    def validate(self) -> None:
        require(isinstance(self.ip, str) and self.ip.strip() != "", "--robot franka needs the robot's address",
                "pass --robot-ip, the FCI address set in Desk (e.g. 172.16.0.2)")
        require(self.model in LIMITS, f"unknown Franka model '{self.model}'", "use panda or fr3")
        require(10.0 <= self.stream_hz <= 500.0, f"stream rate {self.stream_hz} Hz is outside 10-500 Hz",
                "stream references at 50-200 Hz (100 by default)")
        require(0.0 < self.move_speed <= 1.0, f"move speed {self.move_speed} is not in (0, 1]", "e.g. 0.1")
        require(0.001 <= self.error_clip <= 0.2, f"error clip {self.error_clip} m is outside 1-200 mm", "e.g. 0.05")
        require(self.realtime in ("enforce", "ignore"), f"unknown realtime setting '{self.realtime}'", "use enforce or ignore")
        if self.ne_t_ee is not None:
            T = np.asarray(self.ne_t_ee, dtype=float)
            require(T.shape == (4, 4) and np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6),
                    "ne_t_ee is not a (4, 4) rigid transform", "give the TCP pose in the nominal end-effector frame")


class FrankyArm:
    """A Franka arm behind :class:`~tergodic_cli.robot.interfaces.Arm` and
    :class:`~tergodic_cli.backends.impedance.ImpedanceArm`.

    The exploration loop streams :meth:`command_impedance` references, whose stiffness and damping
    run at 1 kHz inside franky (raw torques from Python: a 10 ms zero-order hold, docs/hardware.md).
    """

    name = "franka-franky"

    def __init__(self, cfg: FrankaConfig):
        cfg.validate()
        self.cfg = cfg
        self.joint_names = list(JOINTS)
        self.q_min, self.q_max, self.dq_max = (x.copy() for x in LIMITS[cfg.model])
        #: The picture posture (the Panda's "ready" pose) when the run gives none.
        self.home = np.array(HOME)
        self.stream_hz = float(cfg.stream_hz)
        self.robot = self._fr = self._motion = self._gains_key = self._error = None
        self._mode: str | None = None  # None | "impedance"
        self.measured_tau = np.zeros(7)

    # ------------------------------------------------------------------ connection
    @property
    def is_connected(self) -> bool:
        return self.robot is not None

    def connect(self) -> None:
        if self.robot is not None:
            return
        fr = import_sdk("franky")
        self._fr = fr
        cfg = self.cfg
        rt = fr.RealtimeConfig.Enforce if cfg.realtime == "enforce" else fr.RealtimeConfig.Ignore
        try:
            robot = fr.Robot(cfg.ip, relative_dynamics_factor=float(cfg.move_speed), realtime_config=rt)
        except Exception as exc:  # franky raises its own NetworkException, RealtimeException, IncompatibleVersionException
            raise TergodicError(f"cannot connect to the Franka at {cfg.ip}: {one_line(exc)}",
                                _connect_fix(exc)) from None
        try:
            if robot.has_errors:
                robot.recover_from_errors()
            robot.set_collision_behavior(float(cfg.torque_thresholds), float(cfg.force_thresholds))
            if cfg.ne_t_ee is not None:
                robot.set_ee(np.asarray(cfg.ne_t_ee, dtype=float).flatten(order="F").tolist())  # column-major
        except Exception as exc:
            raise TergodicError(f"the Franka at {cfg.ip} refused its set-up: {one_line(exc)}",
                                "recover the robot in Desk (unlock the joints, activate FCI) and retry") from None
        self.robot = robot

    def _require(self):
        if self.robot is None:
            raise TergodicError("the Franka is not connected", "call connect() first")
        return self.robot

    def disconnect(self) -> None:
        """Stop any controller (the arm comes to rest and holds) and drop the connection."""
        if self.robot is None:
            return
        try:
            self.stop()
        finally:
            self.robot = None
            self._mode = None

    # ------------------------------------------------------------------ state
    def read_state(self) -> ArmState:
        robot = self._require()
        s = robot.state
        q = np.asarray(s.q, dtype=float).reshape(7)
        dq = np.asarray(s.dq, dtype=float).reshape(7)
        T = np.asarray(s.O_T_EE.matrix, dtype=float).reshape(4, 4)
        J = np.asarray(robot.model.zero_jacobian(self._fr.Frame.EndEffector, s), dtype=float).reshape(6, 7)
        self.measured_tau = np.asarray(s.tau_J, dtype=float).reshape(7)  # link-side torque sensors, N m
        return ArmState(float(s.time.to_sec()), q, dq, T, J)

    def fault(self) -> str | None:
        """A one-line reason when franky reports an error (a reflex, a stopped motion), else None."""
        robot = self._require()
        if self._error is not None:
            return self._error
        try:
            if self._mode is not None:
                robot.poll_motion()  # re-raises an exception the control thread stored
        except Exception as exc:
            self._error, self._mode = f"the Franka stopped: {one_line(exc)}", None
            return self._error
        if robot.has_errors:
            self._error = "the Franka reports an error (see Desk); it stopped"
        return self._error

    # ------------------------------------------------------------------ commands
    def command_impedance(self, target: ImpedanceTarget) -> None:
        """Start, or update, franky's Cartesian impedance tracking with ``target`` (base frame)."""
        robot = self._require()
        fr = self._fr
        T = np.asarray(target.pose, dtype=float)
        require(T.shape == (4, 4) and bool(np.all(np.isfinite(T))), "the impedance target pose is not a finite (4, 4) matrix",
                "this is a bug in the caller; please report it")
        ref = fr.CartesianReference(target=fr.Affine(T),
                                    target_twist=fr.Twist(np.asarray(target.twist[:3], float), np.asarray(target.twist[3:], float)))
        K, D = np.asarray(target.stiffness, dtype=float), np.asarray(target.damping, dtype=float)
        key = np.round(np.concatenate([K.ravel(), D.ravel()]), 6).tobytes()
        start = self._mode != "impedance"
        if start:
            clip = float(self.cfg.error_clip)
            self._motion = fr.CartesianImpedanceTrackingMotion(
                max_delta_tau=float(self.cfg.max_delta_tau), lower_joint_limits=self.q_min, upper_joint_limits=self.q_max,
                translational_error_clip=np.full(3, clip), gains_time_constant=0.02)
            self._gains_key = None
        if key != self._gains_key:
            gains = fr.CartesianImpedanceGains()
            gains.stiffness = K
            gains.damping = D
            self._motion.set_gains(gains)
            self._gains_key = key
        self._motion.set_reference(ref)
        if start:
            robot.move(self._motion, asynchronous=True)
            self._mode = "impedance"

    def move_joints(self, q: np.ndarray, speed: float | None = None) -> None:
        """Blocking joint-space move (franky plans it with Ruckig); ends a torque-mode controller first."""
        robot = self._require()
        qd = np.asarray(q, dtype=float).reshape(7)
        require(bool(np.all(qd >= self.q_min) and np.all(qd <= self.q_max)), f"joint target {np.round(qd, 3).tolist()} rad is outside the joint limits",
                "choose a reachable pose")
        f = float(self.cfg.move_speed if speed is None else speed)
        require(0.0 < f <= 1.0, f"move speed {f} is not in (0, 1]", "e.g. 0.1")
        self.stop()
        try:
            robot.move(self._fr.JointMotion(qd, relative_dynamics_factor=f))
        except Exception as exc:
            self._error = f"the Franka stopped during a joint move: {one_line(exc)}"
            raise TergodicError(self._error, "check the workspace for obstacles, recover the robot in Desk and retry") from None

    def stop(self) -> None:
        """End a torque-mode controller gracefully (ramp to pure damping, come to rest), then wait for it."""
        robot = self._require()
        if self._mode is None:
            return
        try:
            robot.move(self._fr.TorqueStopMotion(), asynchronous=True)
            robot.join_motion(3.0)
        except Exception as exc:
            self._error = f"the Franka stopped: {one_line(exc)}"
        finally:
            self._mode, self._motion = None, None


class FrankaWrenchEstimate(WrenchSensor):
    """The Franka's own estimate of the external wrench as a sensor (no extra hardware):
    ``-K_F_ext_hat_K`` of a connected :class:`FrankyArm`, minus the tare.

    libfranka estimates the wrench the environment applies to the robot from its joint torque
    sensors, ``K_F_ext_hat_K`` (stiffness frame K, which is the end-effector frame unless ``set_k``
    moved it). The sensor convention of :mod:`tergodic_cli.robot.interfaces` is the wrench the arm
    applies to the tool, so the reading is its negative. Far noisier than a wrist sensor (about
    ±1-2 N at the TCP from joint friction and model error): fine for a first test, not for
    measured force tracking.
    """

    def __init__(self, arm, tare_samples: int = 20):
        super().__init__(None, tare_samples)
        self.arm = arm

    def connect(self) -> None:
        self.arm.connect()

    def _sample(self) -> tuple[float, np.ndarray]:
        s = self.arm._require().state
        return float(s.time.to_sec()), -np.asarray(s.K_F_ext_hat_K, dtype=float).reshape(6)

    def disconnect(self) -> None:
        """The arm owns the connection."""


def _connect_fix(exc: BaseException) -> str:
    name = type(exc).__name__
    if "Realtime" in name:
        return "run on a PREEMPT_RT kernel with real-time permissions (franky's setup guide), or pass realtime='ignore' on a bench"
    if "IncompatibleVersion" in name:
        return "install the franky wheels built for your robot's libfranka version (franky's README lists them)"
    return "check the cable and the address, unlock the joints and activate FCI in Desk"



def make_arm(cfg: FrankaConfig, sensor=None, gains=None, read_only: bool = False) -> FrankyArm:
    """The registry's factory (backends/registry.py): franky's arm, not yet connected; ``read_only`` (the
    dry run) needs no real-time kernel. ``sensor`` and ``gains`` are not used (franky runs its own loop)."""
    return FrankyArm(replace(cfg, realtime="ignore") if read_only else cfg)


def make_sensor(cfg, arm: FrankyArm) -> FrankaWrenchEstimate:
    """The registry's factory for ``--ft franka``: the arm's own external-wrench estimate."""
    return FrankaWrenchEstimate(arm)
