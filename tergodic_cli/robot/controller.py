"""The line-tracking impedance controller with a wrench PID (paper eqs. 34-47), and a joint impedance.

One control step, all in the end-effector (TCP) frame, matrix form of the CGA products:

1. L_ee is the ee z-axis (eq. 35); the target L_a⊥ (point a, unit direction d pointing into
   the surface) is moved into the ee frame by M̃ (the reverse motor);
2. M_{L_ee L_a⊥} (eq. 36) and its logarithm, the twist V_L = (t, φ) (eq. 37), by
   :func:`~tergodic_cli.robot.ga.line_motor_z`;
3. V_L becomes the wrench W_L = K_L V_L (eq. 38, see "the twist-to-wrench map" below);
4. the wrench PID W_C on W_d - W'_m (eqs. 40-41), W'_m the measured wrench in the ee frame
   (eq. 39), acting on the force along the line only (see below);
5. damping W_V = D_V V_ee on the ee twist V_ee = J^ee q̇ (eq. 46);
6. τ = J^eeᵀ (K_L V_L - D_V V_ee + W_C) (eq. 47; the CGA inner product's minus sign, B·W = -τ,
   is already folded into the matrix form). J^ee = M̃ J M (eq. 45) is never formed: we use
   J^eeᵀ W^ee = Jᵀ (R W^ee), one 6×7 product fewer.

Two choices the paper leaves open, made here:

- *The twist-to-wrench map.* Eq. 38 multiplies by the conjugate pseudoscalar I_c "as a scalar
  inertia". In gafro's blade conventions V·I_c puts the rotational part of a twist on force
  blades (e12 -> e03) and the translational part on moment blades, which would turn a tilt
  error into a push. We implement the stated intent, an identity inertia: the translational
  error becomes a force, the rotational error a moment, K_L and D_V diagonal in (t, φ) and
  (v, ω). The paper's K_L = diag(30, 30, 30, 750, 750, 300) is in gafro's twist order
  (e12, e13, e23, e1∞, e2∞, e3∞), i.e. 30 N m/rad on rotations and 750, 750, 300 N/m on x, y, z.
- *Which wrench components the PID acts on.* A PID on all six components would fight the
  line stiffness through the friction force (its integrator winds up against the motion).
  The line leaves the translation along itself free, so the PID acts on the force along the
  ee z-axis only; W_d = (0, 0, F_d, 0, 0, 0).

Additions needed in simulation (not in the paper), each small and documented in docs/robot.md:
the rotation about the tool axis is left free by a line, so a weak spring holds the ee x-axis
near a reference; a weak posture spring in the Jacobian's null space keeps the redundant
elbow away from its limits; the measured force is low-pass filtered before the PID.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np

from tergodic_cli.robot.ga import line_motor_z_scalar


#: Radians before a joint limit where the null-space repulsion starts.
LIMIT_ZONE = 0.3


@dataclass
class ControllerGains:
    """Gains of eq. 47 and the wrench PID (eq. 40), SI units; see :data:`PAPER_GAINS`.

    k_trans, k_rot : K_L on the translational (N/m) and rotational (N m/rad) error, ee axes x, y, z.
    d_trans, d_rot : D_V on the ee velocity (N s/m) and angular velocity (N m s/rad).
    kp, ki, kd : wrench PID on the force along the tool axis (N/N, 1/s, s).
    force_filter_hz : cut-off of the first-order filter on the measured force.
    integral_max : the PID integral term is kept in [0, integral_max × F_d].
    spin_stiffness : N m/rad holding the rotation about the tool axis (free for a line).
    nullspace_stiffness, nullspace_damping : posture spring (N m/rad, N m s/rad) in the null space.
    limit_stiffness : N m/rad pushing joints out of the last LIMIT_ZONE rad before a limit (null space).
    """

    k_trans: tuple[float, float, float] = (3000.0, 3000.0, 300.0)
    k_rot: tuple[float, float, float] = (30.0, 30.0, 30.0)
    d_trans: tuple[float, float, float] = (80.0, 80.0, 50.0)
    d_rot: tuple[float, float, float] = (2.0, 2.0, 2.0)
    kp: float = 2.0
    ki: float = 60.0
    kd: float = 0.0
    force_filter_hz: float = 30.0
    integral_max: float = 3.0
    spin_stiffness: float = 5.0
    nullspace_stiffness: float = 10.0
    nullspace_damping: float = 3.0
    limit_stiffness: float = 30.0

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


#: The paper's gains (V-A3), for comparison runs.
PAPER_GAINS = ControllerGains(k_trans=(750.0, 750.0, 300.0), k_rot=(30.0, 30.0, 30.0), d_trans=(150.0, 150.0, 50.0),
                              d_rot=(10.0, 10.0, 10.0), kp=0.5, ki=5.0, kd=0.5)


class ControlOutput(NamedTuple):
    """One control step's torques and diagnostics (ee frame); a NamedTuple, cheap to make at 1 kHz."""

    tau: np.ndarray  # (7,) task torques, N m
    twist_error: tuple  # V_L = (t, φ), φz being the spin error about the tool axis
    wrench_cmd: tuple  # total commanded wrench (f, m), ee frame
    force_filtered: float  # N along the tool axis
    v_ee: tuple  # ee twist (v, ω), ee frame


class LineForceController:
    """Eq. 47 with the modes the state machine needs.

    Modes
    -----
    "track"   : line stiffness + force PID towards F_d (exploration);
    "approach": line stiffness + a constant push D_z·v that moves the tool along the line at v;
    "retreat" : the same with -v.

    Parameters
    ----------
    gains : :class:`ControllerGains`.
    dt : control period, s.
    q_rest : (7,) posture the null-space spring pulls towards.
    x_ref : (3,) base-frame direction the ee x-axis is held near (the spin about the tool axis).
    q_limits : (q_min, q_max) joint limits for the null-space limit repulsion (default: the Panda's).
    """

    def __init__(self, gains: ControllerGains, dt: float, q_rest: np.ndarray, x_ref: np.ndarray, q_limits=None):
        self.g = gains
        self.dt = float(dt)
        self.q_rest = np.asarray(q_rest, dtype=float)
        self.x_ref = np.asarray(x_ref, dtype=float)
        self.K = tuple(float(k) for k in gains.k_trans + gains.k_rot)
        self.D = tuple(float(k) for k in gains.d_trans + gains.d_rot)
        self.alpha = 1.0 - math.exp(-2.0 * math.pi * gains.force_filter_hz * self.dt) if gains.force_filter_hz > 0 else 1.0
        self._tau_spring = np.zeros(7)  # null-space spring torques, refreshed every 10 steps
        self._N_damp = np.zeros((7, 7))
        self._n_age = 0
        from tergodic_cli.robot.pybullet_backend.scene import Q_MAX, Q_MIN

        self.q_min, self.q_max = (Q_MIN, Q_MAX) if q_limits is None else (np.asarray(q_limits[0]), np.asarray(q_limits[1]))
        self.reset()

    def reset(self, force_now: float = 0.0) -> None:
        """Clear the PID state."""
        self.f_filt = float(force_now)
        self.e_prev = None
        self.integral = 0.0

    def start_tracking(self, force_desired: float, force_cmd: float) -> None:
        """Bumpless switch to "track": the PID output continues from ``force_cmd``."""
        e = force_desired - self.f_filt
        self.integral = (force_cmd - self.g.kp * e) / self.g.ki if self.g.ki > 0 else 0.0
        self.e_prev = e

    def step(self, st, a, d, wrench_ee, mode: str, force_desired: float, speed: float = 0.0,
             v_ref=None) -> ControlOutput:
        """One control step.

        Parameters
        ----------
        st : :class:`~tergodic_cli.robot.interfaces.ArmState` (TCP pose, base-frame Jacobian, q, q̇).
        a, d : target line point and unit direction (into the surface), base frame, 3 floats each.
        wrench_ee : (6,) measured wrench the tool applies, ee frame (W'_m, eq. 39).
        mode : "track", "approach" or "retreat". force_desired : F_d, N. speed : approach/retreat speed, m/s.
        v_ref : velocity of the target line, base frame, 3 floats (or None): the translational damping
            acts on the velocity relative to it, so a moving target is followed without a damping lag.
        """
        g = self.g
        r0, r1, r2, r3, r4, r5, r6, r7, r8 = st.rot
        px, py, pz = st.pos
        # The target line in the ee frame: M̃ L_a⊥ M (Rᵀ applied to a - p and to d).
        vx, vy, vz = a[0] - px, a[1] - py, a[2] - pz
        dx, dy, dz = d[0], d[1], d[2]
        tx, ty, tz, fx_, fy_, _ = line_motor_z_scalar(
            r0 * vx + r3 * vy + r6 * vz, r1 * vx + r4 * vy + r7 * vz, r2 * vx + r5 * vy + r8 * vz,
            r0 * dx + r3 * dy + r6 * dz, r1 * dx + r4 * dy + r7 * dz, r2 * dx + r5 * dy + r8 * dz)
        xr = self.x_ref
        spin = math.atan2(r1 * xr[0] + r4 * xr[1] + r7 * xr[2], r0 * xr[0] + r3 * xr[1] + r6 * xr[2])
        J = st.jacobian
        V = (J @ st.dq).tolist()  # base-frame twist (v, ω) of the TCP
        if v_ref is not None:
            V[0] -= v_ref[0]
            V[1] -= v_ref[1]
            V[2] -= v_ref[2]
        ve = (r0 * V[0] + r3 * V[1] + r6 * V[2], r1 * V[0] + r4 * V[1] + r7 * V[2], r2 * V[0] + r5 * V[1] + r8 * V[2],
              r0 * V[3] + r3 * V[4] + r6 * V[5], r1 * V[3] + r4 * V[4] + r7 * V[5], r2 * V[3] + r5 * V[4] + r8 * V[5])
        # Wrench PID on the force along the tool axis (eqs. 40-41), on the filtered measurement.
        self.f_filt += self.alpha * (float(wrench_ee[2]) - self.f_filt)
        if mode == "track":
            e = force_desired - self.f_filt
            de = 0.0 if self.e_prev is None else (e - self.e_prev) / self.dt
            self.e_prev = e
            if g.ki > 0:
                self.integral = min(max(self.integral + e * self.dt, 0.0), g.integral_max * max(force_desired, 0.0) / g.ki)
            fz = g.kp * e + g.ki * self.integral + g.kd * de
        elif mode == "approach":
            fz = self.D[2] * speed
        elif mode == "retreat":
            fz = -self.D[2] * speed
        else:
            raise ValueError(f"unknown control mode {mode!r}")
        K, D = self.K, self.D
        # K_L V_L - D_V V_ee + W_C (eq. 47); no stiffness along the line (the force loop owns it),
        # and along it the damping acts on the tool's own velocity (the target's slides along the line).
        wx = K[0] * tx - D[0] * ve[0]
        wy = K[1] * ty - D[1] * ve[1]
        wz = fz - D[2] * (ve[2] if v_ref is None else ve[2] + (r2 * v_ref[0] + r5 * v_ref[1] + r8 * v_ref[2]))
        mx = K[3] * fx_ - D[3] * ve[3]
        my = K[4] * fy_ - D[4] * ve[4]
        mz = g.spin_stiffness * spin - D[5] * ve[5]
        W = np.array((r0 * wx + r1 * wy + r2 * wz, r3 * wx + r4 * wy + r5 * wz, r6 * wx + r7 * wy + r8 * wz,
                      r0 * mx + r1 * my + r2 * mz, r3 * mx + r4 * my + r5 * mz, r6 * mx + r7 * my + r8 * mz))
        tau = J.T @ W + self._posture(J, st.q, st.dq)
        return ControlOutput(tau, (tx, ty, tz, fx_, fy_, spin), (wx, wy, wz, mx, my, mz), self.f_filt, ve)

    def _posture(self, J: np.ndarray, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        # Posture spring, joint-limit repulsion and damper, projected into the Jacobian's null space
        # (I - Jᵀ (Jᵀ)⁺, damped). The task damping cannot see self-motion, so the null-space damper
        # runs every step; the projector and the slowly varying spring terms are refreshed at 100 Hz.
        g = self.g
        if self._n_age % 10 == 0:
            N = np.eye(7) - J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(6), J)
            lo = np.minimum(q - (self.q_min + LIMIT_ZONE), 0.0)
            hi = np.maximum(q - (self.q_max - LIMIT_ZONE), 0.0)
            self._tau_spring = N @ (g.nullspace_stiffness * (self.q_rest - q) - g.limit_stiffness * (lo + hi))
            self._N_damp = g.nullspace_damping * N
        self._n_age += 1
        return self._tau_spring - self._N_damp @ dq


@dataclass
class JointGains:
    """Joint impedance gains (N m/rad, N m s/rad) for moves between poses and for holding."""

    stiffness: tuple = (600.0, 600.0, 600.0, 600.0, 250.0, 150.0, 50.0)
    damping: tuple = (50.0, 50.0, 50.0, 50.0, 20.0, 15.0, 6.0)


class JointImpedance:
    """τ = K (q_d - q) + D (q̇_d - q̇): the paper's "simple joint impedance controller" (V-A3)."""

    def __init__(self, gains: JointGains | None = None):
        g = gains or JointGains()
        self.K = np.array(g.stiffness, dtype=float)
        self.D = np.array(g.damping, dtype=float)

    def __call__(self, q: np.ndarray, dq: np.ndarray, q_d: np.ndarray, dq_d: np.ndarray | None = None) -> np.ndarray:
        dq_d = np.zeros_like(q) if dq_d is None else dq_d
        return self.K * (q_d - q) + self.D * (dq_d - dq)


def min_jerk(q0: np.ndarray, q1: np.ndarray, duration: float, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-jerk interpolation from q0 to q1 over ``duration`` s: position and velocity at ``t``."""
    if duration <= 0 or t >= duration:
        return q1.copy(), np.zeros_like(q1)
    s = max(t, 0.0) / duration
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    dblend = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
    return q0 + (q1 - q0) * blend, (q1 - q0) * dblend
