"""A fake ``pylibfranka`` (0.21.3): the classes, signatures and refusals tergodic relies on.

Names, argument names and defaults follow ``pylibfranka/_pylibfranka.pyi`` of pylibfranka 0.21.3:
``Robot(robot_ip_address, realtime_config=RealtimeConfig.kEnforce)``, ``read_once``, ``load_model``,
``start_torque_control`` -> ``ActiveControlBase`` (``readOnce`` -> (RobotState, Duration),
``writeOnce(Torques)``), ``Model.zero_jacobian``/``coriolis`` (flat, column-major), ``RobotState``'s
``q``, ``dq``, ``tau_J``, ``O_T_EE`` (16, column-major), ``K_F_ext_hat_K``, ``time``,
``current_errors``; ``set_collision_behavior(lower_torque, upper_torque, lower_force, upper_force)``,
``set_EE``, ``automatic_error_recovery``, ``stop``. Behaviours copied from the real library:

- ``Robot(ip)`` with no robot there raises ``NetworkException``; with ``kEnforce`` on a kernel
  without real-time capabilities, ``RealtimeException``;
- ``read_once()`` while a control is active raises ``InvalidOperationException``;
- ``Torques`` takes exactly 7 numbers; ``motion_finished = True`` ends the control;
- a contact force over the upper collision force threshold is a reflex: the next ``readOnce`` raises
  ``ControlException`` and ``current_errors`` is set until ``automatic_error_recovery``.

The physics is :class:`fakes.world.FakeWorld` at 1 ms per read. The arm is a Cartesian mass
``MASS`` (kg; ``INERTIA`` kg m² in rotation) with a light friction ``FRICTION`` (N s/m, N m s/rad):
the commanded torque less the Coriolis torque is a wrench W = (J Jᵀ)⁻¹ J τ at the TCP (gravity is
the SDK's), the tool's free twist after one step u = v + dt (W - friction v) / mass; the world turns
u into motion and the contact force that stops it (f_n = -(u·n) mass / dt: the push into the surface).
The Coriolis torque the model reports is the fixed ``CORIOLIS`` · q̇ (a known value to check).
"""

from __future__ import annotations

import enum

import numpy as np

_NETWORK: dict = {}
_REALTIME_KERNEL = True
#: The fake arm's apparent Cartesian mass (kg) and rotational inertia (kg m²), and its friction
#: (N s/m, N m s/rad).
MASS, INERTIA, FRICTION, FRICTION_ROT = 3.0, 0.05, 5.0, 0.1
#: The fake model's Coriolis torque per joint speed, N m s/rad.
CORIOLIS = 0.01


class FrankaException(Exception):
    pass


class NetworkException(RuntimeError):
    pass


class RealtimeException(RuntimeError):
    pass


class ControlException(RuntimeError):
    pass


class CommandException(RuntimeError):
    pass


class InvalidOperationException(RuntimeError):
    pass


class RealtimeConfig(enum.Enum):
    kEnforce = 0
    kIgnore = 1


class ControllerMode(enum.Enum):
    JointImpedance = 0
    CartesianImpedance = 1


class Duration:
    def __init__(self, ms: int = 0):
        self._ms = int(ms)

    def to_sec(self) -> float:
        return self._ms * 1e-3


class Errors:
    def __init__(self, names=()):
        self.names = list(names)

    def __bool__(self) -> bool:
        return bool(self.names)

    def __str__(self) -> str:
        return "[" + ", ".join(f'"{n}"' for n in self.names) + "]"

    @property
    def cartesian_reflex(self) -> bool:
        return "cartesian_reflex" in self.names


class RobotState:
    """What the world looks like at one millisecond (numbers as lists, matrices column-major)."""

    def __init__(self, world, tau, errors):
        self.q = world.q.copy()
        self.dq = world.dq.copy()
        self.O_T_EE = world.T.flatten(order="F").copy()
        self.tau_J = np.asarray(tau, dtype=float).copy()
        self.K_F_ext_hat_K = world.external_wrench_K()
        self.time = Duration(int(round(world.t * 1000)))
        self.current_errors = Errors(errors)
        self._J = world.J.copy()


class Torques:
    def __init__(self, arg0):
        tau = [float(x) for x in arg0]
        if len(tau) != 7:
            raise TypeError("__init__(): incompatible constructor arguments (FixedSize(7))")
        self.tau_J = tau
        self.motion_finished = False


class Model:
    def zero_jacobian(self, arg0: RobotState):
        return arg0._J.flatten(order="F").copy()

    def coriolis(self, arg0: RobotState):
        return CORIOLIS * np.asarray(arg0.dq, dtype=float)

    def gravity(self, arg0: RobotState):
        return np.zeros(7)


class ActiveControlBase:
    def __init__(self, robot: "Robot"):
        self._robot = robot
        self.finished = False

    def readOnce(self):
        r = self._robot
        if self.finished:
            raise ControlException("libfranka: the control has finished")
        if r._errors:
            self.finished, r._active = True, None
            raise ControlException(f"libfranka: Move command aborted: motion aborted by reflex! {Errors(r._errors)}")
        return r._advance(), Duration(1)

    def writeOnce(self, arg0) -> None:
        r = self._robot
        if self.finished:
            raise ControlException("libfranka: the control has finished")
        if not isinstance(arg0, Torques):
            raise TypeError("writeOnce(): incompatible function arguments")
        r.tau = np.asarray(arg0.tau_J, dtype=float)
        r.n_writes += 1
        if arg0.motion_finished:
            self.finished, r._active, r.tau = True, None, None


class Robot:
    def __init__(self, robot_ip_address: str, realtime_config: RealtimeConfig = RealtimeConfig.kEnforce):
        world = _NETWORK.get(robot_ip_address)
        if world is None:
            raise NetworkException("libfranka: Connection to FCI refused. Please install FCI feature or enable FCI mode in Desk.")
        if realtime_config == RealtimeConfig.kEnforce and not _REALTIME_KERNEL:
            raise RealtimeException("libfranka: Running kernel does not have realtime capabilities.")
        self.world = world
        world.dt = 0.001
        world.robot = self
        self.tau = None
        self._active = None
        self._errors: list[str] = []
        self.upper_force = 1e9
        self.ne_t_ee = np.eye(4)
        self.n_writes = self.n_reads = 0

    # ------------------------------------------------------------------ SDK calls
    def read_once(self) -> RobotState:
        if self._active is not None:
            raise InvalidOperationException("libfranka: cannot read while a control is running")
        return self._advance()

    def load_model(self) -> Model:
        return Model()

    def start_torque_control(self) -> ActiveControlBase:
        if self._active is not None:
            raise InvalidOperationException("libfranka: a control is already running")
        if self._errors:
            raise ControlException(f"libfranka: the robot is in an error state {Errors(self._errors)}")
        self._active = ActiveControlBase(self)
        return self._active

    def set_collision_behavior(self, lower_torque_thresholds, upper_torque_thresholds, lower_force_thresholds,
                               upper_force_thresholds) -> None:
        for x, n in ((lower_torque_thresholds, 7), (upper_torque_thresholds, 7), (lower_force_thresholds, 6),
                     (upper_force_thresholds, 6)):
            if len(x) != n:
                raise TypeError("set_collision_behavior(): incompatible function arguments")
        self.upper_force = float(max(upper_force_thresholds[:3]))

    def set_EE(self, arg0) -> None:
        if self._active is not None:
            raise CommandException("libfranka: cannot set the end effector while a control runs")
        self.ne_t_ee = np.asarray(arg0, dtype=float).reshape(4, 4, order="F")

    def automatic_error_recovery(self) -> None:
        self._errors = []

    def stop(self) -> None:
        if self._active is not None:
            self._active.finished = True
            self._active = None
        self.tau = None

    # ------------------------------------------------------------------ the plant
    def _advance(self) -> RobotState:
        self.world.step()
        self.n_reads += 1
        if self.world.f_n > self.upper_force:
            self._errors = ["cartesian_reflex"]
        return RobotState(self.world, self.tau if self.tau is not None else np.zeros(7), self._errors)

    def _control(self, world, dt):
        """The world's hook: the torque as a twist of the massless arm (see the module docstring)."""
        if self.tau is None or self._active is None:
            return None
        J = world.J
        tau = self.tau - CORIOLIS * world.dq
        W = np.linalg.solve(J @ J.T + 1e-9 * np.eye(6), J @ tau)
        v = J @ world.dq
        m = np.array([MASS] * 3 + [INERTIA] * 3)
        c = np.array([FRICTION] * 3 + [FRICTION_ROT] * 3)
        u = v + dt * (W - c * v) / m
        return "twist", u, np.diag(m / dt)
