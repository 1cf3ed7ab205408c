"""The line-tracking impedance controller with a wrench PID (paper eqs. 34-47), and a joint impedance.

One control step, all in the end-effector (TCP) frame, matrix form of the CGA products
(docs/robot.md, "The controller"): the target line L_a⊥ moved into the ee frame by M̃; the motor
M_{L_ee L_a⊥} (eq. 36) and its logarithm V_L = (t, φ) (eq. 37,
:func:`~tergodic_cli.robot.ga.line_motor_z`); τ = J^eeᵀ (K_L V_L - D_V V_ee + W_C) (eq. 47) with
the wrench PID W_C on W_d - W'_m (eqs. 40-41), using J^eeᵀ W^ee = Jᵀ (R W^ee) instead of forming
J^ee (eq. 45).

Two choices the paper leaves open (docs/robot.md): eq. 38's I_c is read as its stated intent, an
identity inertia (translation error -> force, rotation error -> moment; used literally in gafro's
blades a tilt would push along the axis); the PID's integral acts on the axial force only (across
the line it winds up against the friction until the tool sticks), and its derivative sees the
wrench filtered once more (``derivative_filter_hz``: the paper's K_d on the 1 kHz contact jitter
pushed 25 N at the first touch). Simulation adds a weak spin spring (a line leaves the rotation
about the tool axis free), a null-space posture spring and a low-pass filter on the measured force.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# the gains' config lives with the robot's (numpy-free: the CLI builds its options at start-up)
from tergodic_cli.robot.config import PAPER_GAINS, ControllerGains, gains_preset  # noqa: F401

#: Radians before a joint limit where the null-space repulsion starts.
LIMIT_ZONE = 0.3


class ControlOutput(NamedTuple):
    """One control step's torques and diagnostics (ee frame); views into the step's diagnostics array."""

    tau: np.ndarray  # (n,) task torques, N m
    twist_error: np.ndarray  # (6,) V_L = (t, φ), φz being the spin error about the tool axis
    wrench_cmd: np.ndarray  # (6,) total commanded wrench (f, m), ee frame
    force_filtered: float  # N along the tool axis
    v_ee: np.ndarray  # (6,) ee twist (v, ω), ee frame


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
    q_rest : (n,) posture the null-space spring pulls towards (n: the arm's joints, its model's DoF).
    x_ref : (3,) base-frame direction the ee x-axis is held near (the spin about the tool axis).
    q_min, q_max : (n,) the arm's joint limits, rad (its model's): the null-space repulsion near them;
        None: no repulsion.

    The arithmetic is :func:`tergodic_cli.robot.kernels.line_force_step` (compiled); this class
    holds its packed parameters ``kpk`` and state ``mut`` (PID, null-space terms).
    """

    def __init__(self, gains: ControllerGains, dt: float, q_rest: np.ndarray, x_ref: np.ndarray,
                 q_min: np.ndarray | None = None, q_max: np.ndarray | None = None):
        from tergodic_cli.robot import kernels as Kn

        self._Kn = Kn
        self.g = gains
        self.dt = float(dt)
        self.K = tuple(float(k) for k in gains.k_trans + gains.k_rot)
        self.D = tuple(float(k) for k in gains.d_trans + gains.d_rot)

        def lowpass(hz: float) -> float:  # the first-order filter's gain per step
            return Kn.lowpass_gain(hz, self.dt)

        g = gains
        prm = np.array([g.kp, g.ki, g.kd, lowpass(g.force_filter_hz), g.integral_max,  # CP_* order
                        g.spin_stiffness, g.nullspace_stiffness, g.nullspace_damping,
                        g.limit_stiffness, self.dt, LIMIT_ZONE, g.guard_speed, g.guard_damping,
                        1.0 if g.pid_wrench else 0.0, lowpass(g.derivative_filter_hz)])
        #: Packed constants (kernels.KPK_*) and mutable state (kernels.MUT_*) of the compiled step.
        q_rest = np.asarray(q_rest, dtype=float)
        self.dof = n = len(q_rest)
        if not 1 <= n <= Kn.MAX_DOF:
            raise ValueError(f"the controller takes 1..{Kn.MAX_DOF} joints, got {n}")

        def slots(x, fill: float) -> np.ndarray:  # n joints in MAX_DOF slots
            out = np.full(Kn.MAX_DOF, fill)
            out[:n] = np.full(n, fill) if x is None else np.asarray(x, dtype=float)
            return out

        self.kpk = np.concatenate([self.K, self.D, prm, np.asarray(x_ref, dtype=float), slots(q_rest, 0.0),
                                   slots(q_min, -np.inf), slots(q_max, np.inf)])  # the limits: null-space repulsion
        assert self.kpk.shape == (Kn.N_KPK,)
        self.mut = np.zeros(Kn.N_MUT)
        self._vref = np.zeros(3)
        self._modes = Kn.MODES
        self._step = Kn.line_force_step
        self.reset()

    @property
    def x_ref(self) -> np.ndarray:
        return self.kpk[self._Kn.KPK_XREF:self._Kn.KPK_XREF + 3]

    @x_ref.setter
    def x_ref(self, v) -> None:
        self.kpk[self._Kn.KPK_XREF:self._Kn.KPK_XREF + 3] = np.asarray(v, dtype=float)

    @property
    def f_filt(self) -> float:
        """N, the filtered force along the tool axis."""
        return float(self.mut[self._Kn.CS_FFILT + 2])

    @property
    def integral(self) -> float:
        """N s, the PID integral of the axial force error."""
        return float(self.mut[self._Kn.CS_INTEGRAL + 2])

    def reset(self, force_now: float = 0.0) -> None:
        """Clear the PID state."""
        Kn = self._Kn
        self.mut[:Kn.CS_AGE] = 0.0
        self.mut[Kn.CS_DFILT:Kn.CS_DFILT + 6] = 0.0
        self.mut[Kn.CS_FFILT + 2] = self.mut[Kn.CS_DFILT + 2] = float(force_now)

    def start_tracking(self, force_desired: float, force_cmd: float) -> None:
        """Bumpless switch to "track": the PID output continues from ``force_cmd``."""
        Kn = self._Kn
        e = force_desired - self.f_filt
        self.mut[Kn.CS_INTEGRAL + 2] = (force_cmd - self.g.kp * e) / self.g.ki if self.g.ki > 0 else 0.0
        self.mut[Kn.CS_EPREV:Kn.CS_EPREV + 6] = -self.mut[Kn.CS_DFILT:Kn.CS_DFILT + 6]
        self.mut[Kn.CS_EPREV + 2] = force_desired - self.mut[Kn.CS_DFILT + 2]
        self.mut[Kn.CS_HAS_EPREV] = 1.0

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
        m = self._modes.get(mode)
        if m is None:
            raise ValueError(f"unknown control mode {mode!r}")
        tau = np.empty(self.dof)
        diag = np.empty(19)
        use_vref = v_ref is not None
        if use_vref:
            self._vref[:] = v_ref
        J = st.jacobian
        self._step(st.ee_pose, J if J.flags.c_contiguous else np.ascontiguousarray(J), _f64(st.q), _f64(st.dq),
                   _f64(a), _f64(d), _f64(wrench_ee), m, float(force_desired), float(speed), self._vref, use_vref,
                   self.kpk, self.mut, tau, diag)
        return ControlOutput(tau, diag[0:6], diag[6:12], float(diag[12]), diag[13:19])


def _f64(x) -> np.ndarray:
    return x if isinstance(x, np.ndarray) and x.dtype == np.float64 and x.flags.c_contiguous else np.ascontiguousarray(x, dtype=float)


class JointImpedance:
    """τ = K (q_d - q) + D (q̇_d - q̇): the paper's "simple joint impedance controller" (V-A3), for
    moves between poses and for holding. K (n,) N m/rad and D (n,) N m s/rad: the arm's (its module's
    ``joint_gains``)."""

    def __init__(self, K, D):
        self.K = np.asarray(K, dtype=float)
        self.D = np.asarray(D, dtype=float)

    def __call__(self, q: np.ndarray, dq: np.ndarray, q_d: np.ndarray, dq_d: np.ndarray | None = None) -> np.ndarray:
        dq_d = np.zeros_like(q) if dq_d is None else dq_d
        return self.K * (q_d - q) + self.D * (dq_d - dq)


#: N/m of the approach's axial position servo: its set-point advances at the guarded speed, so a
#: steady push on the tool (gravity-model error, posture torques) cannot make it touch faster (a
#: pure velocity servo, D_z = 50 N s/m, let 0.17 N push it in at 5.5 mm/s against 2 commanded).
APPROACH_K = 2000.0
#: N s/m added to the approach's axial damping (the controller's D_z, 50) on the speed error.
APPROACH_D = 100.0
#: N the retreat's servo may pull the tool back with while it lags its set-point (the same servo as
#: the approach, backwards): a pure velocity servo pulls only D_z x 0.05 m/s = 2.5 N, which a steady
#: posture or gravity-model torque held at 0 of 45 mm for 3 s (corpus soccer ball, stand, 2 N,
#: seed 2, step 762), and the tool stayed touching after its fault.
RETREAT_PULL = 20.0


class LineTargetLaw:
    """The torque of one control tick towards a :class:`~tergodic_cli.robot.interfaces.LineTarget`, on a
    :class:`LineForceController`: the one home of how "press" and "move" become the controller's modes
    (the simulated arm and the hardware torque loop both tick it).

    "press" tracks the target's force (bumpless from the approach's push at first contact); "move" is a
    position servo along the axis whose set-point moves at the commanded speed. Approach (speed > 0):
    while the tool is blocked the set-point runs ahead and the push grows (APPROACH_K × overshoot) until
    the force registers, capped at twice the contact threshold. Retreat (speed < 0): the same servo
    backwards, its pull capped at RETREAT_PULL.

    Attributes: ``mode`` ("press", "approach", "retreat" or None: the next tick starts afresh),
    ``s_set`` (m, the approach's set-point along d), ``speed`` (m/s, the approach's last push speed).
    """

    def __init__(self):
        self.mode: str | None = None
        self.s_set = 0.0
        self.speed = 0.0

    def step(self, ctrl: LineForceController, st, w, target, threshold: float) -> ControlOutput:
        """One tick: ``st`` the ArmState, ``w`` (6,) the contact wrench (ee frame), ``target`` the
        LineTarget, ``threshold`` N the contact threshold. Returns the controller's output."""
        approach = target.mode == "move" and target.speed > 0
        mode = "approach" if approach else "retreat" if target.mode == "move" else target.mode
        if target.mode == "press":
            if self.mode == "approach":  # first contact: the PID continues from the push it replaces
                ctrl.start_tracking(target.force, ctrl.D[2] * self.speed)
            out = ctrl.step(st, target.a, target.d, w, "track", target.force, 0.0, target.v_line)
        else:
            d = target.d
            p_along = float(st.ee_pose[:3, 3] @ d)
            if self.mode != mode:
                ctrl.reset()
                self.s_set = p_along
            if approach:
                self.s_set = min(self.s_set + target.speed * ctrl.dt, p_along + 2.0 * threshold / APPROACH_K)
            else:
                self.s_set = max(self.s_set + target.speed * ctrl.dt, p_along - RETREAT_PULL / APPROACH_K)
            push = APPROACH_K * (self.s_set - p_along) + APPROACH_D * (target.speed - float(d @ (st.jacobian[:3] @ st.dq)))
            self.speed = target.speed + push / ctrl.D[2]
            out = ctrl.step(st, target.a, d, w, "approach", target.force, self.speed)
        self.mode = mode
        return out


#: The approach slows down to reach the expected surface in about this many seconds from where it is.
APPROACH_TAU_S = 0.25
#: Desired force (N) at and above which the tool touches at the full ``contact_speed``; below it the
#: touch is slower in proportion, so the impact (the contact's damping × speed: 1 N at 2 mm/s on the
#: simulated sponge) stays a fifth of F_d.
TOUCH_REF_FORCE = 5.0


#: The approach is at its touch speed this far (m) before the expected surface: the cloud is not
#: the surface to the tenth of a millimetre.
TOUCH_MARGIN = 0.001


def guarded_approach_speed(gap: float, approach_speed: float, contact_speed: float, force: float) -> float:
    """Speed (m/s) of a guarded approach ``gap`` metres before the expected surface (the cloud's point):
    ``approach_speed`` far away, slowing down over the last few mm ((gap - TOUCH_MARGIN) / APPROACH_TAU_S)
    to the touch speed, ``contact_speed`` scaled down below TOUCH_REF_FORCE, from TOUCH_MARGIN on."""
    touch = contact_speed * min(1.0, max(force, 0.0) / TOUCH_REF_FORCE)
    return min(approach_speed, max(touch, (gap - TOUCH_MARGIN) / APPROACH_TAU_S))


def min_jerk(q0: np.ndarray, q1: np.ndarray, duration: float, t: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum-jerk interpolation from q0 to q1 over ``duration`` s: position and velocity at ``t``."""
    if duration <= 0 or t >= duration:
        return q1.copy(), np.zeros_like(q1)
    s = max(t, 0.0) / duration
    blend = 10 * s**3 - 15 * s**4 + 6 * s**5
    dblend = (30 * s**2 - 60 * s**3 + 30 * s**4) / duration
    return q0 + (q1 - q0) * blend, (q1 - q0) * dblend
