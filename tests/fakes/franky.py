"""A fake ``franky`` module (franky-control 2.0.0): the classes, signatures and refusals tergodic relies on.

Names, argument names and defaults follow ``franky/_franky.pyi`` of franky-control 2.0.0. The robot's
physics is :class:`fakes.world.FakeWorld`; ``_NETWORK[ip] = world`` puts a robot "on the network".
Behaviours copied from the real library:

- ``Robot(ip)`` for an address with no robot raises ``NetworkException("libfranka: Connection to FCI
  refused. ...")`` (the message the real library gives for a closed port);
- ``JointMotion`` refuses a plain list (the real pybind11 binding accepts an ndarray or JointState);
- a motion object can run once (``MotionReuseException``); the control-signal type cannot change while
  a motion runs (``InvalidMotionTypeException``); an asynchronous motion's exception is stored and
  raised by the next ``move``/``join_motion``/``poll_motion``;
- ``SimpleTorqueMotion`` ends with ``TorqueSignalTimeoutException`` when ``set_torque`` is not called
  within ``signal_timeout``; its torque steps are limited to ``max_delta_tau`` per 1 ms;
- the Cartesian impedance gains are smoothed with ``gains_time_constant``; damping None = critical
  (2 √K); the translational error is clipped elementwise at ``translational_error_clip``;
- ``set_ee`` while a motion runs raises ``CommandException``; a contact force above the collision
  force threshold triggers a reflex (``ControlException``, ``has_errors`` until ``recover_from_errors``).
"""

from __future__ import annotations

import builtins
import enum

import numpy as np

_NETWORK: dict = {}
_REALTIME_KERNEL = True


# ---------------------------------------------------------------------------- exceptions
class Exception(builtins.Exception):  # noqa: A001 - franky.Exception, the base of franky's control errors
    pass


class ControlException(Exception):
    pass


class CommandException(builtins.Exception):
    pass


class NetworkException(builtins.Exception):
    pass


class RealtimeException(builtins.Exception):
    pass


class IncompatibleVersionException(builtins.Exception):
    pass


class InvalidMotionTypeException(builtins.Exception):
    pass


class MotionReuseException(builtins.Exception):
    pass


class TorqueSignalTimeoutException(builtins.Exception):
    pass


# ---------------------------------------------------------------------------- enums and small types
class RealtimeConfig(enum.Enum):
    Enforce = 0
    Ignore = 1


class ControllerMode(enum.Enum):
    JointImpedance = 0
    CartesianImpedance = 1


class ReferenceType(enum.Enum):
    Absolute = 0
    Relative = 1


class Frame(enum.Enum):
    Joint1 = 0
    Joint2 = 1
    Joint3 = 2
    Joint4 = 3
    Joint5 = 4
    Joint6 = 5
    Joint7 = 6
    Flange = 7
    EndEffector = 8
    Stiffness = 9


class Duration:
    def __init__(self, arg0: int = 0):
        self._ms = int(arg0)

    def to_sec(self) -> float:
        return self._ms / 1000.0

    def to_msec(self) -> int:
        return self._ms


class RelativeDynamicsFactor:
    def __init__(self, *args, **kwargs):
        vals = list(args) + [kwargs[k] for k in ("velocity", "acceleration", "jerk", "value") if k in kwargs]
        if len(vals) == 0:
            vals = [1.0]
        if len(vals) == 1:
            vals = vals * 3
        self.velocity, self.acceleration, self.jerk = (float(v) for v in vals[:3])
        for v in (self.velocity, self.acceleration, self.jerk):
            if not 0.0 < v <= 1.0:
                raise ValueError("relative dynamics factors must be in (0, 1]")


def _rdf(x) -> RelativeDynamicsFactor:
    return x if isinstance(x, RelativeDynamicsFactor) else RelativeDynamicsFactor(float(x))


def _vec(x, n: int, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.shape not in ((n,), (n, 1)):
        raise TypeError(f"{name}: expected {n} values, got shape {a.shape}")
    return a.reshape(n).copy()


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


class Affine:
    def __init__(self, *args, **kwargs):
        T = np.eye(4)
        if "transformation_matrix" in kwargs or (len(args) == 1 and np.asarray(args[0]).shape == (4, 4)):
            T = np.asarray(kwargs.get("transformation_matrix", args[0] if args else None), dtype=float).copy()
        elif len(args) == 1 and isinstance(args[0], Affine):
            T = args[0].matrix
        else:
            t = kwargs.get("translation", args[0] if len(args) > 0 else np.zeros(3))
            q = kwargs.get("quaternion", args[1] if len(args) > 1 else np.array([0.0, 0.0, 0.0, 1.0]))
            T[:3, 3] = _vec(t, 3, "translation")
            T[:3, :3] = _quat_matrix(_vec(q, 4, "quaternion"))
        if T.shape != (4, 4) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise TypeError("Affine: not a rigid transformation")
        self._T = T

    @property
    def matrix(self) -> np.ndarray:
        return self._T.copy()

    @property
    def translation(self) -> np.ndarray:
        return self._T[:3, 3].copy()

    @property
    def inverse(self) -> "Affine":
        Ti = np.eye(4)
        Ti[:3, :3] = self._T[:3, :3].T
        Ti[:3, 3] = -self._T[:3, :3].T @ self._T[:3, 3]
        return Affine(Ti)

    def __mul__(self, other: "Affine") -> "Affine":
        return Affine(self._T @ other._T)


class Twist:
    def __init__(self, linear_velocity=None, angular_velocity=None):
        self.linear = np.zeros(3) if linear_velocity is None else _vec(linear_velocity, 3, "linear_velocity")
        self.angular = np.zeros(3) if angular_velocity is None else _vec(angular_velocity, 3, "angular_velocity")


class TwistAcceleration(Twist):
    pass


class JointState:
    def __init__(self, position, velocity=None):
        self.position = _vec(position.position if isinstance(position, JointState) else position, 7, "position")
        self.velocity = np.zeros(7) if velocity is None else _vec(velocity, 7, "velocity")


class RobotPose:
    def __init__(self, end_effector_pose: Affine, elbow_state=None):
        self.end_effector_pose = end_effector_pose
        self.elbow_state = elbow_state


class RobotState:
    """The fields of franky.RobotState that tergodic reads."""

    def __init__(self, world):
        self.q = world.q.copy()
        self.dq = world.dq.copy()
        self.q_d = world.q.copy()
        self.dq_d = np.zeros(7)
        self.O_T_EE = Affine(world.T)
        self.time = Duration(int(round(world.t * 1000)))
        self.K_F_ext_hat_K = world.external_wrench_K()
        R = world.T[:3, :3]
        self.O_F_ext_hat_K = np.concatenate([R @ self.K_F_ext_hat_K[:3], np.zeros(3)])
        self.tau_J = np.zeros(7)


class Model:
    def __init__(self, world):
        self._world = world

    def zero_jacobian(self, frame: Frame, state: RobotState) -> np.ndarray:
        if frame != Frame.EndEffector:
            raise NotImplementedError("the fake model knows the end-effector frame only")
        if not np.allclose(state.q, self._world.q):
            raise NotImplementedError("the fake model evaluates the present state only")
        return self._world.J.copy()


# ---------------------------------------------------------------------------- gains and references
class CartesianImpedanceGains:
    def __init__(self, translational_stiffness: float = 500.0, rotational_stiffness: float = 50.0):
        self._K = np.diag([float(translational_stiffness)] * 3 + [float(rotational_stiffness)] * 3)
        self._D = None

    @staticmethod
    def isotropic(translational_stiffness, rotational_stiffness, translational_damping=None, rotational_damping=None):
        g = CartesianImpedanceGains(translational_stiffness, rotational_stiffness)
        if translational_damping is not None and rotational_damping is not None:
            g.damping = np.diag([translational_damping] * 3 + [rotational_damping] * 3)
        return g

    @staticmethod
    def diagonal(stiffness, damping=None):
        g = CartesianImpedanceGains()
        g.stiffness = np.diag(_vec(stiffness, 6, "stiffness"))
        if damping is not None:
            g.damping = np.diag(_vec(damping, 6, "damping"))
        return g

    @property
    def stiffness(self) -> np.ndarray:
        return self._K.copy()

    @stiffness.setter
    def stiffness(self, K) -> None:
        K = np.asarray(K, dtype=float)
        if K.shape != (6, 6) or not np.allclose(K, K.T, atol=1e-9) or np.linalg.eigvalsh(K).min() < -1e-9:
            raise ValueError("stiffness must be a symmetric positive semi-definite 6x6 matrix")
        self._K = K.copy()

    @property
    def damping(self):
        return None if self._D is None else self._D.copy()

    @damping.setter
    def damping(self, D) -> None:
        if D is None:
            self._D = None
            return
        D = np.asarray(D, dtype=float)
        if D.shape != (6, 6) or not np.allclose(D, D.T, atol=1e-9) or np.linalg.eigvalsh(D).min() < -1e-9:
            raise ValueError("damping must be a symmetric positive semi-definite 6x6 matrix")
        self._D = D.copy()


def _critical(K: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(K)
    return 2.0 * (V * np.sqrt(np.maximum(w, 0.0))) @ V.T


class CartesianReference:
    def __init__(self, target: Affine = None, target_twist: Twist | None = None, target_acceleration=None):
        if target is not None and not isinstance(target, Affine):
            raise TypeError("CartesianReference: target must be an Affine")
        if target_twist is not None and not isinstance(target_twist, Twist):
            raise TypeError("CartesianReference: target_twist must be a Twist")
        self.target = target if target is not None else Affine()
        self.target_twist = target_twist
        self.target_acceleration = target_acceleration


class PostureTask:
    def __init__(self, target, stiffness, damping=None, max_torque=None):
        self.target = _vec(target, 7, "target")
        self.stiffness = stiffness


# ---------------------------------------------------------------------------- motions
class _Motion:
    signal = "none"

    def __init__(self):
        self._started = False
        self.finished = False

    def _begin(self, world) -> None:
        pass


class JointMotion(_Motion):
    signal = "joint_position"

    def __init__(self, target, reference_type: ReferenceType = ReferenceType.Absolute, relative_dynamics_factor=1.0,
                 return_when_finished: bool = True):
        super().__init__()
        if not isinstance(target, (JointState, np.ndarray)):
            raise TypeError("__init__(): incompatible constructor arguments. The following argument types are supported:\n"
                            "    1. franky._franky.JointMotion(target: franky._franky.JointState, ...)")
        self.target = JointState(target.position if isinstance(target, JointState) else target)
        self.reference_type = reference_type
        self.relative_dynamics_factor = _rdf(relative_dynamics_factor)

    def _control(self, robot, world, dt):
        f = self.relative_dynamics_factor.velocity * robot.relative_dynamics_factor.velocity
        err = self.target.position - world.q
        if np.max(np.abs(err)) < 1e-5:
            self.finished = True
            return ("dq", np.zeros(7))
        vmax = f * np.array([2.175, 2.175, 2.175, 2.175, 2.61, 2.61, 2.61])
        return ("dq", np.clip(err / 0.05, -vmax, vmax))


class _TorqueMotion(_Motion):
    signal = "torque"


class SimpleTorqueMotion(_TorqueMotion):
    #: viscous joint model of the fake (N m s/rad): dq = tau / b
    JOINT_DAMPING = 10.0

    def __init__(self, initial_torque=None, signal_timeout=0.05, compensate_coriolis: bool = False, max_delta_tau: float = 1.0,
                 lower_joint_limits=None, upper_joint_limits=None, joint_limit_activation_distance: float = 0.1,
                 joint_limit_stiffness: float = 4.0, joint_limit_damping: float = 1.0, joint_limit_max_torque: float = 5.0,
                 friction=None):
        super().__init__()
        self._torque = np.zeros(7) if initial_torque is None else _vec(initial_torque, 7, "initial_torque")
        self.signal_timeout = signal_timeout
        self.max_delta_tau = float(max_delta_tau)
        self._applied = np.zeros(7)
        self._last_signal = None

    def set_torque(self, torque) -> None:
        t = _vec(torque, 7, "torque")
        if not np.all(np.isfinite(t)):
            raise ValueError("torque must be finite")
        self._torque = t
        self._last_signal = self._world.t if getattr(self, "_world", None) is not None else None

    def get_torque(self) -> np.ndarray:
        return self._torque.copy()

    def _begin(self, world) -> None:
        self._world = world
        self._last_signal = world.t

    def _control(self, robot, world, dt):
        if self.signal_timeout is not None and world.t - self._last_signal > self.signal_timeout + 1e-9:
            raise TorqueSignalTimeoutException(f"no torque signal for {self.signal_timeout} s")
        step = np.clip(self._torque - self._applied, -self.max_delta_tau, self.max_delta_tau)
        self._applied = self._applied + step
        return ("dq", self._applied / self.JOINT_DAMPING)


class TorqueStopMotion(_TorqueMotion):
    def __init__(self, damping=None, ramp_duration: float = 0.2, velocity_epsilon: float = 0.02, max_duration: float = 2.0,
                 compensate_coriolis: bool = True, max_delta_tau: float = 1.0):
        super().__init__()
        self.ramp_duration = float(ramp_duration)
        self._t = 0.0

    def _control(self, robot, world, dt):
        self._t += dt
        if self._t >= self.ramp_duration:
            self.finished = True
        return ("dq", np.zeros(7))  # massless arm: pure damping brings it to rest at once


class CartesianImpedanceTrackingMotion(_TorqueMotion):
    def __init__(self, translational_stiffness: float = 500, rotational_stiffness: float = 50, force_constraints=None,
                 posture_task=None, manipulability_task=None, max_delta_tau: float = 1.0, lower_joint_limits=None,
                 upper_joint_limits=None, joint_limit_activation_distance: float = 0.1, joint_limit_stiffness: float = 4.0,
                 joint_limit_damping: float = 1.0, joint_limit_max_torque: float = 5.0, translational_error_clip=None,
                 rotational_error_clip=None, gains_time_constant: float = 0.1, friction=None):
        super().__init__()
        self._gains = CartesianImpedanceGains(translational_stiffness, rotational_stiffness)
        self._K = self._gains.stiffness
        self._D = _critical(self._K)
        self._ref: CartesianReference | None = None
        self.tau_g = float(gains_time_constant)
        self.clip_t = np.full(3, np.inf) if translational_error_clip is None else _vec(translational_error_clip, 3, "translational_error_clip")
        self.clip_r = np.full(3, np.inf) if rotational_error_clip is None else _vec(rotational_error_clip, 3, "rotational_error_clip")
        self.references = 0
        self.gain_updates = 0

    def set_gains(self, gains: CartesianImpedanceGains) -> None:
        if not isinstance(gains, CartesianImpedanceGains):
            raise TypeError("set_gains(): expected CartesianImpedanceGains")
        self._gains = gains
        self.gain_updates += 1

    def get_gains(self) -> CartesianImpedanceGains:
        g = CartesianImpedanceGains()
        g.stiffness = self._gains.stiffness
        g.damping = self._gains.damping
        return g

    def set_reference(self, reference: CartesianReference) -> None:
        if not isinstance(reference, CartesianReference):
            raise TypeError("set_reference(): expected CartesianReference")
        self._ref = reference
        self.references += 1

    def get_reference(self):
        return self._ref

    def _begin(self, world) -> None:
        if self._ref is None:
            self._ref = CartesianReference(target=Affine(world.T))

    def _control(self, robot, world, dt):
        a = min(1.0, dt / self.tau_g) if self.tau_g > 0 else 1.0
        K_t = self._gains.stiffness
        D_t = self._gains.damping if self._gains.damping is not None else _critical(K_t)
        self._K += a * (K_t - self._K)
        self._D += a * (D_t - self._D)
        T_t = self._ref.target.matrix
        e = np.concatenate([np.clip(T_t[:3, 3] - world.T[:3, 3], -self.clip_t, self.clip_t),
                            np.clip(world.rotvec_error(T_t[:3, :3]), -self.clip_r, self.clip_r)])
        v_t = np.zeros(6)
        if self._ref.target_twist is not None:
            v_t = np.concatenate([self._ref.target_twist.linear, self._ref.target_twist.angular])
        u = v_t + np.linalg.solve(self._D + 1e-9 * np.eye(6), self._K @ e)
        return ("twist", u, self._D.copy())


# ---------------------------------------------------------------------------- the robot
class Robot:
    control_rate = 0.001
    degrees_of_freedom = 7

    def __init__(self, fci_hostname: str, relative_dynamics_factor=1.0, default_torque_threshold: float = 20.0,
                 default_force_threshold: float = 30.0, controller_mode: ControllerMode = ControllerMode.JointImpedance,
                 realtime_config: RealtimeConfig = RealtimeConfig.Enforce, **kalman):
        if fci_hostname not in _NETWORK:
            raise NetworkException("libfranka: Connection to FCI refused. Please install FCI feature or enable FCI mode in Desk.")
        if realtime_config == RealtimeConfig.Enforce and not _REALTIME_KERNEL:
            raise RealtimeException("libfranka: Running kernel does not have realtime capabilities.")
        self._world = _NETWORK[fci_hostname]
        self._world.robot = self
        self._hostname = fci_hostname
        self._rdf = _rdf(relative_dynamics_factor)
        self.force_threshold = float(default_force_threshold)
        self.torque_threshold = float(default_torque_threshold)
        self._active: _Motion | None = None
        self._queue: list[_Motion] = []
        self._stored: BaseException | None = None
        self._has_errors = False
        self.moves: list[str] = []  # names of the motions started, for tests
        self.set_ee_calls = 0

    # ---- properties
    @property
    def fci_hostname(self) -> str:
        return self._hostname

    @property
    def relative_dynamics_factor(self) -> RelativeDynamicsFactor:
        return self._rdf

    @relative_dynamics_factor.setter
    def relative_dynamics_factor(self, value) -> None:
        self._rdf = _rdf(value)

    @property
    def state(self) -> RobotState:
        with self._world.lock:
            return RobotState(self._world)

    @property
    def current_joint_state(self) -> JointState:
        return JointState(self._world.q, self._world.dq)

    @property
    def current_pose(self) -> RobotPose:
        return RobotPose(Affine(self._world.T))

    @property
    def model(self) -> Model:
        return Model(self._world)

    @property
    def has_errors(self) -> bool:
        return self._has_errors

    @property
    def is_in_control(self) -> bool:
        return self._active is not None

    # ---- commands
    def set_collision_behavior(self, *args) -> None:
        if self._active is not None:
            raise CommandException("libfranka: command rejected: a motion is running")
        if len(args) == 2:
            self.torque_threshold = float(np.max(args[0]))
            self.force_threshold = float(np.max(args[1]))
        elif len(args) in (4, 8):
            self.torque_threshold = float(np.max(args[len(args) // 4]))
            self.force_threshold = float(np.max(args[-1]))
        else:
            raise TypeError("set_collision_behavior(): incompatible function arguments")

    def set_ee(self, NE_T_EE) -> None:
        if self._active is not None:
            raise CommandException("libfranka: command rejected: a motion is running")
        v = np.asarray(NE_T_EE, dtype=float)
        if v.shape != (16,):
            raise TypeError("set_ee(): NE_T_EE must have 16 values (column-major)")
        self._world.ne_t_ee = v.reshape(4, 4, order="F")
        self._world._refresh()
        self.set_ee_calls += 1

    def recover_from_errors(self) -> bool:
        self._has_errors = False
        return True

    def _raise_stored(self) -> None:
        if self._stored is not None:
            exc, self._stored = self._stored, None
            raise exc

    def move(self, motion, asynchronous: bool = False, limit_rate: bool = False, cutoff_frequency: float = 100.0) -> None:
        self._raise_stored()
        if not isinstance(motion, _Motion):
            raise TypeError("move(): incompatible function arguments")
        if motion._started:
            raise MotionReuseException("Motion has already been started; create a new motion instance.")
        if self._has_errors:
            raise ControlException("libfranka: Move command rejected: the robot is in an error state; call recover_from_errors()")
        if self._active is not None and self._active.signal != motion.signal:
            raise InvalidMotionTypeException("The type of control signal must not change while the robot is in motion.")
        motion._started = True
        self.moves.append(type(motion).__name__)
        motion._begin(self._world)
        self._active = motion  # a new motion takes over the running one (franky preempts seamlessly)
        if not asynchronous:
            self.join_motion()

    def join_motion(self, timeout=None) -> bool:
        waited = 0.0
        while self._active is not None:
            if timeout is not None and waited >= timeout:
                return False
            self._world.step()
            waited += self._world.dt
            if waited > 600.0:
                raise RuntimeError("fake franky: a synchronous motion never finished")
        self._raise_stored()
        return True

    def poll_motion(self) -> bool:
        self._raise_stored()
        return self._active is not None

    def stop(self) -> None:
        if self._active is not None:
            self._active = None
            self._stored = ControlException("libfranka: Move command preempted!")

    # ---- the real-time side, called by the world every 1 ms
    def _control(self, world, dt):
        m = self._active
        if m is None:
            return None
        try:
            cmd = m._control(self, world, dt)
        except builtins.Exception as exc:  # the control thread stores it
            self._active = None
            self._stored = exc
            return None
        if m.finished:
            self._active = None
        if world.f_n > self.force_threshold:
            self._active = None
            self._has_errors = True
            self._stored = ControlException("libfranka: Move command aborted: motion aborted by reflex! [cartesian_reflex]")
            return None
        return cmd
