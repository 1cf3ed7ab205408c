"""Compiled (numba) kernels of the 1 kHz robot loop: forward kinematics and Jacobian, the contact
wrench, the line-force controller and the safety limits.

Each kernel is the only implementation of its math (the controller, the contact wrench and the
safety guard call them); :func:`pybullet_tick` chains them into one call per tick of a PyBullet run
(docs/robot.md, "Timing").

Arrays are float64 and C-contiguous; small matrix products are written out (numba's ``@`` on 3×3
goes through BLAS, slower at this size).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tergodic_cli.robot import ga


def njit(fn):
    return numba.njit(cache=True, nogil=True, fastmath=False)(fn)


line_motor_z = njit(ga.line_motor_z)

# Controller modes.
MODE_TRACK, MODE_APPROACH, MODE_RETREAT = 0, 1, 2
MODES = {"track": MODE_TRACK, "approach": MODE_APPROACH, "retreat": MODE_RETREAT}

# Controller parameters, one float64 array (CP_*), and state (CS_*).
CP_KP, CP_KI, CP_KD, CP_ALPHA, CP_IMAX, CP_SPIN, CP_NS_K, CP_NS_D, CP_LIM_K, CP_DT, CP_LIMIT_ZONE = range(11)
CP_VGUARD, CP_DGUARD, CP_WRENCH, CP_DALPHA = 11, 12, 13, 14
N_CP = 15
# PID state: the filtered wrench (6), the previous error of the derivative (6), whether it is set, the
# integral (6), the step count, the wrench filtered again for the derivative (6).
CS_FFILT, CS_EPREV, CS_HAS_EPREV, CS_INTEGRAL, CS_AGE, CS_DFILT = 0, 6, 12, 13, 19, 20
N_CS = 26
# Diagnostics of one controller step (CD_*): twist error (6), commanded wrench (6), filtered force, ee twist (6).
CD_TWIST, CD_WRENCH, CD_FFILT, CD_VEE = 0, 6, 12, 13
N_CD = 19

#: Joint slots of the packed arrays below: an arm has n <= MAX_DOF joints (its model's DoF, read from
#: its URDF) and uses the first n of each slot; the kernels take n from the Jacobian's width.
MAX_DOF = 7
# The controller's packed constants ``kpk`` and mutable state ``mut`` (held by LineForceController):
# kpk: K (6), D (6), prm (N_CP), x_ref (3), q_rest (MAX_DOF), q_min (MAX_DOF), q_max (MAX_DOF)
KPK_K, KPK_D, KPK_PRM = 0, 6, 12
KPK_XREF = KPK_PRM + N_CP
KPK_QREST, KPK_QMIN, KPK_QMAX = KPK_XREF + 3, KPK_XREF + 3 + MAX_DOF, KPK_XREF + 3 + 2 * MAX_DOF
N_KPK = KPK_XREF + 3 + 3 * MAX_DOF
# mut: PID state (N_CS), null-space spring torques (MAX_DOF), null-space damping (n x n, row-major, in
# MAX_DOF² slots)
MUT_STATE, MUT_SPRING, MUT_DAMP = 0, N_CS, N_CS + MAX_DOF
N_MUT = N_CS + MAX_DOF + MAX_DOF * MAX_DOF

# Safety fault codes of :func:`state_fault`, :func:`force_fault`, :func:`pybullet_tick`.
OK, F_JOINT_POS, F_JOINT_VEL, F_TCP_SPEED, F_WORKSPACE, F_FORCE, F_SENSOR, F_IMPACT = 0, 1, 2, 3, 4, 5, 6, 7


# ----------------------------------------------------------------------------- kinematics
@njit
def _mul3(r, b):
    """r b for two 3x3 matrices as row-major 9-tuples (kept in registers), as a 9-tuple."""
    return (r[0] * b[0] + r[1] * b[3] + r[2] * b[6], r[0] * b[1] + r[1] * b[4] + r[2] * b[7],
            r[0] * b[2] + r[1] * b[5] + r[2] * b[8], r[3] * b[0] + r[4] * b[3] + r[5] * b[6],
            r[3] * b[1] + r[4] * b[4] + r[5] * b[7], r[3] * b[2] + r[4] * b[5] + r[5] * b[8],
            r[6] * b[0] + r[7] * b[3] + r[8] * b[6], r[6] * b[1] + r[7] * b[4] + r[8] * b[7],
            r[6] * b[2] + r[7] * b[5] + r[8] * b[8])


@njit
def fk_jacobian(q, F, axis, qidx, tcp_off, T, J):
    """TCP pose and geometric Jacobian of a serial chain.

    q : (n,) joint positions. F : (m, 4, 4) each link frame in its parent's at zero joint angle.
    axis : (m, 3) joint axes in the link frames. qidx : (m,) index into q of each link's joint (-1: fixed).
    tcp_off : (3,) the TCP in the last link's frame. Fills T (4, 4), the TCP in the base frame, and
    J (6, n): rows (v, ω) of the TCP, base frame (libfranka's zero Jacobian, PyBullet's calculateJacobian).
    """
    n = J.shape[1]
    zs = np.empty((n, 3))
    ps = np.empty((n, 3))
    R = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    px, py, pz = 0.0, 0.0, 0.0
    for k in range(F.shape[0]):
        f = F[k]
        # p += R f_t; R = R f_R
        px, py, pz = (px + R[0] * f[0, 3] + R[1] * f[1, 3] + R[2] * f[2, 3],
                      py + R[3] * f[0, 3] + R[4] * f[1, 3] + R[5] * f[2, 3],
                      pz + R[6] * f[0, 3] + R[7] * f[1, 3] + R[8] * f[2, 3])
        R = _mul3(R, (f[0, 0], f[0, 1], f[0, 2], f[1, 0], f[1, 1], f[1, 2], f[2, 0], f[2, 1],
                      f[2, 2]))
        i = qidx[k]
        if i >= 0:
            ux, uy, uz = axis[k, 0], axis[k, 1], axis[k, 2]
            c, s = math.cos(q[i]), math.sin(q[i])
            v = 1.0 - c
            # Rodrigues: rotation by q about u (unit), in the link frame; R = R Rot
            R = _mul3(R, (c + ux * ux * v, ux * uy * v - uz * s, ux * uz * v + uy * s,
                          uy * ux * v + uz * s, c + uy * uy * v, uy * uz * v - ux * s,
                          uz * ux * v - uy * s, uz * uy * v + ux * s, c + uz * uz * v))
            zs[i, 0] = R[0] * ux + R[1] * uy + R[2] * uz
            zs[i, 1] = R[3] * ux + R[4] * uy + R[5] * uz
            zs[i, 2] = R[6] * ux + R[7] * uy + R[8] * uz
            ps[i, 0], ps[i, 1], ps[i, 2] = px, py, pz
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = R
    ox, oy, oz = tcp_off[0], tcp_off[1], tcp_off[2]
    tx = px + r00 * ox + r01 * oy + r02 * oz
    ty = py + r10 * ox + r11 * oy + r12 * oz
    tz = pz + r20 * ox + r21 * oy + r22 * oz
    T[0, 0], T[0, 1], T[0, 2], T[0, 3] = r00, r01, r02, tx
    T[1, 0], T[1, 1], T[1, 2], T[1, 3] = r10, r11, r12, ty
    T[2, 0], T[2, 1], T[2, 2], T[2, 3] = r20, r21, r22, tz
    T[3, 0], T[3, 1], T[3, 2], T[3, 3] = 0.0, 0.0, 0.0, 1.0
    for i in range(n):
        zx, zy, zz = zs[i, 0], zs[i, 1], zs[i, 2]
        dx, dy, dz = tx - ps[i, 0], ty - ps[i, 1], tz - ps[i, 2]
        J[0, i] = zy * dz - zz * dy
        J[1, i] = zz * dx - zx * dz
        J[2, i] = zx * dy - zy * dx
        J[3, i], J[4, i], J[5, i] = zx, zy, zz


matrix_to_rotvec = njit(ga.matrix_to_rotvec)


@njit
def ik_dls(T, q, lo, hi, q_rest, F, axis, qidx, tcp_off, iters):
    """Damped least squares inverse kinematics of the TCP pose ``T`` (4, 4) on the chain (F, axis,
    qidx, tcp_off) of :func:`fk_jacobian`, from ``q`` (n,) rad, inside [``lo``, ``hi``] (n,).

    Each iteration: the pose error e (6,) = (position m, rotation vector rad) of T against the TCP;
    dq = J⁺ e + (I - J⁺ J) 0.2 (q_rest - q) with J⁺ = Jᵀ (J Jᵀ + 10⁻⁴ I)⁻¹, scaled to at most 0.2 rad a
    joint, then clipped to the bounds. Stops below 10 µm and 0.1 mrad or after ``iters`` iterations.
    Returns (q (n,), position error m, orientation error rad). (:func:`~tergodic_cli.robot.reach.ik`
    is its Python face.)
    """
    n = q.shape[0]
    Tq, J = np.empty((4, 4)), np.empty((6, n))
    e = np.empty(6)
    damp, eye_n = 1e-4 * np.eye(6), np.eye(n)
    R = np.ascontiguousarray(T[:3, :3])
    pe = oe = np.inf
    for _ in range(iters):
        fk_jacobian(q, F, axis, qidx, tcp_off, Tq, J)
        phi = matrix_to_rotvec(R @ np.ascontiguousarray(Tq[:3, :3].T))
        for k in range(3):
            e[k] = T[k, 3] - Tq[k, 3]
            e[3 + k] = phi[k]
        pe = math.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
        oe = math.sqrt(e[3] * e[3] + e[4] * e[4] + e[5] * e[5])
        if pe < 1e-5 and oe < 1e-4:
            break
        Jt = np.ascontiguousarray(J.T)
        Jp = Jt @ np.linalg.inv(J @ Jt + damp)
        dq = Jp @ e + (eye_n - Jp @ J) @ (0.2 * (q_rest - q))
        big = np.max(np.abs(dq))
        if big > 0.2:
            dq *= 0.2 / big
        q = np.minimum(np.maximum(q + dq, lo), hi)
    return q, pe, oe


# ----------------------------------------------------------------------------- the contact wrench
@njit
def rot(R, x0, x1, x2):
    """R x for the 3x3 block of ``R`` (a rotation or a 4x4 pose), as three scalars."""
    return (R[0, 0] * x0 + R[0, 1] * x1 + R[0, 2] * x2, R[1, 0] * x0 + R[1, 1] * x1 + R[1, 2] * x2,
            R[2, 0] * x0 + R[2, 1] * x1 + R[2, 2] * x2)


@njit
def rot_t(R, x0, x1, x2):
    """Rᵀ x for the 3x3 block of ``R``, as three scalars."""
    return (R[0, 0] * x0 + R[1, 0] * x1 + R[2, 0] * x2, R[0, 1] * x0 + R[1, 1] * x1 + R[2, 1] * x2,
            R[0, 2] * x0 + R[1, 2] * x1 + R[2, 2] * x2)


@njit
def tool_load(T, R_se, mg, com, out):
    """The wrench (6,) that holds the tool still against gravity, sensor frame (what a tared-at-zero
    sensor reads for a free tool). T (4, 4) or (3, 3): the TCP rotation; R_se (3, 3): the sensor in
    the ee frame; mg: weight, N; com (3,): centre of mass, sensor frame."""
    # Rᵀ_base_sensor (0, 0, m g) = R_seᵀ (row 3 of R_base_ee) m g.
    z0, z1, z2 = T[2, 0] * mg, T[2, 1] * mg, T[2, 2] * mg
    f0, f1, f2 = rot_t(R_se, z0, z1, z2)
    c0, c1, c2 = com[0], com[1], com[2]
    out[0], out[1], out[2] = f0, f1, f2
    out[3], out[4], out[5] = c1 * f2 - c2 * f1, c2 * f0 - c0 * f2, c0 * f1 - c1 * f0


@njit
def contact_wrench(r, T, R_se, p_se, mg, com, tare_load, out):
    """The wrench (6,) the tool applies to its surroundings, ee frame, moment about the TCP (eq. 39).

    r : (6,) sensor reading (tare removed), sensor frame. T : (4, 4) TCP pose (only R is used).
    R_se (3, 3), p_se (3,): the sensor frame in the ee frame. mg : tool weight, N; com (3,) its centre
    of mass in the sensor frame; tare_load (6,): the tool load at the tare orientation. Fills ``out``.
    """
    w = np.empty(6)
    tool_load(T, R_se, mg, com, w)
    for k in range(6):  # the reading, the tool load at the tare put back and the load now removed
        w[k] = r[k] + tare_load[k] - w[k]
    g0, g1, g2 = rot(R_se, w[0], w[1], w[2])
    m0, m1, m2 = rot(R_se, w[3], w[4], w[5])
    p0, p1, p2 = p_se[0], p_se[1], p_se[2]  # moment about the TCP: m_B = m_A + (A - B) × f
    out[0], out[1], out[2] = g0, g1, g2
    out[3] = m0 + p1 * g2 - p2 * g1
    out[4] = m1 + p2 * g0 - p0 * g2
    out[5] = m2 + p0 * g1 - p1 * g0


# The inertial compensation's state (ContactWrench.dyn): the last sample time, the centre of mass's
# velocity and the angular velocity then (base frame), whether they are set, and the last
# accelerations (reused when the same tick is read twice).
DY_T, DY_VC, DY_W, DY_HAS, DY_AC, DY_AL = 0, 1, 4, 7, 8, 11
N_DY = 14
#: Longest gap (s) between two samples that still gives an acceleration (longer: a restart, a = 0).
DY_MAX_GAP = 0.005


@njit
def tcp_twist(J, dq, n):
    """The TCP twist J q̇ (v, ω) over the first ``n`` joints, base frame, as six scalars."""
    v0 = v1 = v2 = w0 = w1 = w2 = 0.0
    for j in range(n):
        qd = dq[j]
        v0 += J[0, j] * qd
        v1 += J[1, j] * qd
        v2 += J[2, j] * qd
        w0 += J[3, j] * qd
        w1 += J[4, j] * qd
        w2 += J[5, j] * qd
    return v0, v1, v2, w0, w1, w2


@njit
def inertial_wrench(t, T, J, dq, R_se, p_se, com, m, inertia, dyn, out):
    """The wrench (6,) that accelerates the tool, sensor frame, moment about the sensor origin:
    (m a_c, c × m a_c + I α + ω × I ω), with a_c the centre of mass's acceleration and α the angular
    one, backward differences of the arm's state (J q̇) between samples; ``inertia`` (3,) is the
    tool's principal inertia about its centre of mass, along the sensor axes. Updates ``dyn``."""
    v0, v1, v2, w0, w1, w2 = tcp_twist(J, dq, dq.shape[0])
    # The centre of mass from the TCP, base frame: R (p_se + R_se c).
    e0, e1, e2 = rot(R_se, com[0], com[1], com[2])
    c0, c1, c2 = rot(T, p_se[0] + e0, p_se[1] + e1, p_se[2] + e2)
    # The centre of mass's velocity and the angular velocity: dyn holds them from DY_VC on (DY_W
    # follows DY_VC), their backward differences from DY_AC on (DY_AL follows DY_AC).
    vw = (v0 + w1 * c2 - w2 * c1, v1 + w2 * c0 - w0 * c2, v2 + w0 * c1 - w1 * c0, w0, w1, w2)
    dt = t - dyn[DY_T]
    if dyn[DY_HAS] != 0.0 and dt == 0.0:
        pass  # the same sample again: the accelerations stand
    elif dyn[DY_HAS] != 0.0 and 0.0 < dt <= DY_MAX_GAP:
        for k in range(6):
            dyn[DY_AC + k] = (vw[k] - dyn[DY_VC + k]) / dt
    else:
        dyn[DY_AC:DY_AC + 6] = 0.0
    dyn[DY_T], dyn[DY_HAS] = t, 1.0
    for k in range(6):
        dyn[DY_VC + k] = vw[k]
    # Into the sensor frame: x_s = R_seᵀ Rᵀ x_b.
    f0, f1, f2 = rot_t(R_se, *rot_t(T, dyn[DY_AC], dyn[DY_AC + 1], dyn[DY_AC + 2]))
    f0, f1, f2 = m * f0, m * f1, m * f2
    al0, al1, al2 = rot_t(R_se, *rot_t(T, dyn[DY_AL], dyn[DY_AL + 1], dyn[DY_AL + 2]))
    om0, om1, om2 = rot_t(R_se, *rot_t(T, w0, w1, w2))
    h0, h1, h2 = inertia[0] * om0, inertia[1] * om1, inertia[2] * om2
    out[0], out[1], out[2] = f0, f1, f2
    out[3] = com[1] * f2 - com[2] * f1 + inertia[0] * al0 + om1 * h2 - om2 * h1
    out[4] = com[2] * f0 - com[0] * f2 + inertia[1] * al1 + om2 * h0 - om0 * h2
    out[5] = com[0] * f1 - com[1] * f0 + inertia[2] * al2 + om0 * h1 - om1 * h0


@njit
def contact_wrench_dyn(r, t, T, J, dq, R_se, p_se, mg, com, tare_load, m, inertia, dyn, out):
    """:func:`contact_wrench` with the tool's inertial wrench (:func:`inertial_wrench`) removed from
    the reading first: the contact wrench alone, also while the arm accelerates."""
    rc = np.empty(6)
    inertial_wrench(t, T, J, dq, R_se, p_se, com, m, inertia, dyn, rc)
    for k in range(6):
        rc[k] = r[k] - rc[k]
    contact_wrench(rc, T, R_se, p_se, mg, com, tare_load, out)


# ----------------------------------------------------------------------------- the controller
@njit
def line_force_step(T, J, q, dq, a, d, w, mode, force_desired, speed, v_ref, use_vref, kpk, mut,
                    tau, diag):
    """One step of eq. 47 with the wrench PID (see :class:`~tergodic_cli.robot.controller.LineForceController`).

    T (4, 4) TCP pose, J (6, n) base-frame Jacobian, q, dq (n,), a, d (3,) target line (base frame, d
    into the surface), w (6,) measured ee wrench, mode MODE_*, v_ref (3,) target line velocity (used
    when ``use_vref``). kpk (N_KPK,): the controller's packed constants (gains K, D, parameters,
    x_ref, q_rest, joint limits); mut (N_MUT,): its PID state and the null-space terms, refreshed
    here every 10 steps (updated). Fills tau (n,) and diag (N_CD,). n <= MAX_DOF joints.
    """
    n = J.shape[1]
    K, D, x_ref = kpk[KPK_K:KPK_K + 6], kpk[KPK_D:KPK_D + 6], kpk[KPK_XREF:KPK_XREF + 3]
    prm = kpk[KPK_PRM:KPK_PRM + N_CP]
    state = mut[MUT_STATE:MUT_STATE + N_CS]
    # The target line in the ee frame (M̃ L_a⊥ M: Rᵀ applied to a - p and to d), its motor's log.
    e0, e1, e2 = rot_t(T, a[0] - T[0, 3], a[1] - T[1, 3], a[2] - T[2, 3])
    u0, u1, u2 = rot_t(T, d[0], d[1], d[2])
    tx, ty, tz, fx_, fy_, _unused = line_motor_z(e0, e1, e2, u0, u1, u2)
    xe0, xe1, _xe2 = rot_t(T, x_ref[0], x_ref[1], x_ref[2])
    spin = math.atan2(xe1, xe0)
    V0, V1, V2, V3, V4, V5 = tcp_twist(J, dq, n)  # base-frame TCP twist J q̇
    if use_vref:
        V0 -= v_ref[0]
        V1 -= v_ref[1]
        V2 -= v_ref[2]
    ve0, ve1, ve2 = rot_t(T, V0, V1, V2)
    ve3, ve4, ve5 = rot_t(T, V3, V4, V5)
    # Wrench PID (eqs. 40-41) on the filtered measured wrench W'_m, ee frame: W_e = W_d - W'_m with
    # W_d = (0, 0, F_d, 0, 0, 0). P and D on the full wrench (CP_WRENCH) or on the axial force alone;
    # the integral on the axial force.
    alpha, dalpha = prm[CP_ALPHA], prm[CP_DALPHA]
    for k in range(6):
        state[CS_FFILT + k] += alpha * (w[k] - state[CS_FFILT + k])
        state[CS_DFILT + k] += dalpha * (state[CS_FFILT + k] - state[CS_DFILT + k])
    c = np.zeros(6)
    if mode == MODE_TRACK:
        ki = prm[CP_KI]
        cap = prm[CP_IMAX] * max(force_desired, 0.0) / ki if ki > 0 else 0.0
        for k in range(6):
            if k != 2 and prm[CP_WRENCH] == 0.0:
                continue
            e = (force_desired if k == 2 else 0.0) - state[CS_FFILT + k]
            # The derivative on a slower filter: the contact's 1 kHz jitter, differentiated, is hundreds of N/s.
            e_d = (force_desired if k == 2 else 0.0) - state[CS_DFILT + k]
            de = 0.0 if state[CS_HAS_EPREV] == 0.0 else (e_d - state[CS_EPREV + k]) / prm[CP_DT]
            state[CS_EPREV + k] = e_d
            if ki > 0 and k == 2:  # (across the line the integral would wind up against the friction)
                state[CS_INTEGRAL + k] = min(max(state[CS_INTEGRAL + k] + e * prm[CP_DT], 0.0), cap)
            c[k] = prm[CP_KP] * e + ki * state[CS_INTEGRAL + k] + prm[CP_KD] * de
        state[CS_HAS_EPREV] = 1.0
        fz = c[2]
    elif mode == MODE_APPROACH:
        fz = D[2] * speed
    else:
        fz = -D[2] * speed
    # K_L V_L - D_V V_ee + W_C (eq. 47); along the line the damping acts on the tool's own velocity.
    wx = K[0] * tx - D[0] * ve0 + c[0]
    wy = K[1] * ty - D[1] * ve1 + c[1]
    v_ax = ve2 + rot_t(T, v_ref[0], v_ref[1], v_ref[2])[2] if use_vref else ve2
    wz = fz - D[2] * v_ax
    if mode == MODE_TRACK and v_ax > prm[CP_VGUARD]:
        # Contact lost: the PID's push (up to (K_p + integral_max) F_d) would fly the tool into the
        # surface at push / D_z (0.1 m/s at 1 N: a 38 N impact). Past this speed it is damped hard.
        wz -= prm[CP_DGUARD] * (v_ax - prm[CP_VGUARD])
    mx = K[3] * fx_ - D[3] * ve3 + c[3]
    my = K[4] * fy_ - D[4] * ve4 + c[4]
    mz = prm[CP_SPIN] * spin - D[5] * ve5 + c[5]
    W0, W1, W2 = rot(T, wx, wy, wz)
    W3, W4, W5 = rot(T, mx, my, mz)
    tau_spring, n_damp = mut[MUT_SPRING:MUT_SPRING + n], mut[MUT_DAMP:MUT_DAMP + n * n].reshape((n, n))
    _posture(J, q, prm, state, kpk[KPK_QREST:KPK_QREST + n], kpk[KPK_QMIN:KPK_QMIN + n],
             kpk[KPK_QMAX:KPK_QMAX + n], tau_spring, n_damp)
    for j in range(n):
        acc = J[0, j] * W0 + J[1, j] * W1 + J[2, j] * W2 + J[3, j] * W3 + J[4, j] * W4 + J[5, j] * W5
        acc += tau_spring[j]
        for k in range(n):
            acc -= n_damp[j, k] * dq[k]
        tau[j] = acc
    diag[0], diag[1], diag[2], diag[3], diag[4], diag[5] = tx, ty, tz, fx_, fy_, spin
    diag[6], diag[7], diag[8], diag[9], diag[10], diag[11] = wx, wy, wz, mx, my, mz
    diag[12] = state[CS_FFILT + 2]
    diag[13], diag[14], diag[15], diag[16], diag[17], diag[18] = ve0, ve1, ve2, ve3, ve4, ve5


@njit
def _posture(J, q, prm, state, q_rest, q_min, q_max, tau_spring, n_damp):
    # Posture spring, joint-limit repulsion and damper in the Jacobian's null space,
    # N = I - Jᵀ (J Jᵀ + 1e-4 I)⁻¹ J. The task damping cannot see self-motion, so the null-space
    # damper runs every step; N and the slowly varying spring terms are refreshed at 100 Hz.
    # (A 6-joint arm has no self-motion: N is ~0 away from singularities.)
    n = J.shape[1]
    if int(state[CS_AGE]) % 10 == 0:
        # A = J Jᵀ + 1e-4 I (SPD), Cholesky A = L Lᵀ, X = A⁻¹ J, N = I - Jᵀ X; written out (6×6:
        # no LAPACK call, and numba compiles it in a fraction of the time np.linalg takes).
        A = np.empty((6, 6))
        for r in range(6):
            for c in range(r + 1):
                acc = 0.0
                for k in range(n):
                    acc += J[r, k] * J[c, k]
                A[r, c] = acc
                A[c, r] = acc
            A[r, r] += 1e-4
        L = np.zeros((6, 6))
        for r in range(6):
            for c in range(r + 1):
                acc = A[r, c]
                for k in range(c):
                    acc -= L[r, k] * L[c, k]
                L[r, c] = math.sqrt(acc) if r == c else acc / L[c, c]
        X = np.empty((6, n))
        for col in range(n):
            y = np.empty(6)
            for r in range(6):  # L y = J[:, col]
                acc = J[r, col]
                for k in range(r):
                    acc -= L[r, k] * y[k]
                y[r] = acc / L[r, r]
            for r in range(5, -1, -1):  # Lᵀ x = y
                acc = y[r]
                for k in range(r + 1, 6):
                    acc -= L[k, r] * X[k, col]
                X[r, col] = acc / L[r, r]
        N = np.empty((n, n))
        for r in range(n):
            for c in range(n):
                acc = 0.0
                for k in range(6):
                    acc += J[k, r] * X[k, c]
                N[r, c] = (1.0 if r == c else 0.0) - acc
        zone = prm[CP_LIMIT_ZONE]
        s = np.empty(n)
        for j in range(n):
            lo = min(q[j] - (q_min[j] + zone), 0.0)
            hi = max(q[j] - (q_max[j] - zone), 0.0)
            s[j] = prm[CP_NS_K] * (q_rest[j] - q[j]) - prm[CP_LIM_K] * (lo + hi)
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += N[j, k] * s[k]
                n_damp[j, k] = prm[CP_NS_D] * N[j, k]
            tau_spring[j] = acc
    state[CS_AGE] += 1.0


# ----------------------------------------------------------------------------- safety limits
@njit
def state_fault(q, dq, pos, tcp_speed, q_lo, q_hi, dq_hi, tcp_max, ws_lo, ws_hi):
    """(code, index): the first limit broken (F_* code, joint index or -1), or (OK, -1).

    Joint positions in [q_lo, q_hi], |q̇| <= dq_hi, TCP speed <= tcp_max, TCP in the box [ws_lo, ws_hi].
    NaN breaks every limit.
    """
    for j in range(q.shape[0]):
        if not (q_lo[j] <= q[j] <= q_hi[j]):
            return F_JOINT_POS, j
    for j in range(dq.shape[0]):
        if not (-dq_hi[j] <= dq[j] <= dq_hi[j]):
            return F_JOINT_VEL, j
    if not tcp_speed <= tcp_max:
        return F_TCP_SPEED, -1
    for k in range(3):
        if not (ws_lo[k] <= pos[k] <= ws_hi[k]):
            return F_WORKSPACE, k
    return OK, -1


def lowpass_gain(hz: float, dt: float) -> float:
    """The gain per step of a first-order low-pass at ``hz`` (Hz) sampled every ``dt`` s (1: no filter)."""
    return 1.0 - math.exp(-2.0 * math.pi * hz * dt) if hz > 0 else 1.0


# The force guard (SafetyGuard.force_state), one float64 array: the low-pass coefficient per tick, the
# limit on the low-passed force, the hard limit on a single tick (N), then the state: the low-passed
# |f| and the last tick's |f| (N).
FG_ALPHA, FG_LIMIT, FG_RAW, FG_FILT, FG_F = 0, 1, 2, 3, 4
N_FG = 5


@njit
def force_fault(w, fg):
    """(code, |f|): the force magnitude of the wrench w (6,) against the guard ``fg`` (updated).

    F_IMPACT when this tick's |f| is over the hard limit fg[FG_RAW] (or NaN); F_FORCE when |f|
    low-passed (first order, fg[FG_ALPHA] per tick, from 0) is over fg[FG_LIMIT]; the |f| returned
    is the one that broke its limit (the tick's, or the low-passed). A NaN never enters the filter.
    """
    f = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    fg[FG_F] = f
    if not f <= fg[FG_RAW]:
        return F_IMPACT, f
    fg[FG_FILT] += fg[FG_ALPHA] * (f - fg[FG_FILT])
    if not fg[FG_FILT] <= fg[FG_LIMIT]:
        return F_FORCE, fg[FG_FILT]
    return OK, f


# ----------------------------------------------------------------------------- every tick counts
# Statistics of every 1 kHz tick (issue 15, item 4) in one float64 array, updated in place: running
# max and sums, a fixed tilt histogram, nothing allocated per tick. Set by Python: the surface
# normal at the contact (base frame, refreshed each explorer step), F_d, the contact threshold,
# the settling ticks, and TS_COUNT (1: these ticks count towards steady contact, i.e. explore).
TS_N, TS_FD, TS_THR, TS_SETTLE, TS_COUNT = 0, 3, 4, 5, 6
TS_PEAK, TS_PEAK_PHASE, TS_RUN, TS_NSTEADY, TS_SQERR, TS_TILT_SUM, TS_NTICKS = 7, 8, 9, 10, 11, 12, 13
TS_HIST = 14
TILT_BIN_DEG = 0.05
TILT_BINS = 1800  # 0..90 deg; the last bin also takes anything steeper
# The window since the run last logged one (ContactRun._log_window): max and sum of |f|, ticks.
TS_WIN_MAX = TS_HIST + TILT_BINS
TS_WIN_SUM, TS_WIN_N = TS_WIN_MAX + 1, TS_WIN_MAX + 2
N_TS = TS_WIN_MAX + 3


@njit
def tick_stats(T, w, ts):
    """Fold one tick into ``ts``: the contact force |f| of ``w`` (6,) into the peaks and the window; in steady contact
    (F/T force along the normal over the threshold for more than TS_SETTLE ticks, counted ticks only)
    the force error (F_n - F_d)/F_d and the tilt of the tool axis (T's z) from the normal. NaN is skipped."""
    f = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    ts[TS_NTICKS] += 1.0
    ts[TS_WIN_N] += 1.0
    ts[TS_WIN_SUM] += f
    if f > ts[TS_WIN_MAX]:
        ts[TS_WIN_MAX] = f
    if f > ts[TS_PEAK]:
        ts[TS_PEAK] = f
    if f > ts[TS_PEAK_PHASE]:
        ts[TS_PEAK_PHASE] = f
    if ts[TS_COUNT] == 0.0:
        return
    n0, n1, n2 = ts[TS_N], ts[TS_N + 1], ts[TS_N + 2]
    # F_n = -(R f)·n: the force the tool presses into the surface.
    fn = -((T[0, 0] * w[0] + T[0, 1] * w[1] + T[0, 2] * w[2]) * n0 + (T[1, 0] * w[0] + T[1, 1] * w[1] + T[1, 2] * w[2]) * n1
           + (T[2, 0] * w[0] + T[2, 1] * w[1] + T[2, 2] * w[2]) * n2)
    if fn >= ts[TS_THR]:
        ts[TS_RUN] += 1.0
    else:
        ts[TS_RUN] = 0.0
        return
    if ts[TS_RUN] <= ts[TS_SETTLE]:
        return
    e = (fn - ts[TS_FD]) / ts[TS_FD]
    ts[TS_SQERR] += e * e
    ts[TS_NSTEADY] += 1.0
    c = -(T[0, 2] * n0 + T[1, 2] * n1 + T[2, 2] * n2)
    tilt = math.degrees(math.acos(min(1.0, max(-1.0, c))))
    ts[TS_TILT_SUM] += tilt
    b = int(tilt / TILT_BIN_DEG)
    ts[TS_HIST + min(b, TILT_BINS - 1)] += 1.0


def tick_quantile(ts: np.ndarray, q: float) -> float | None:
    """The ``q`` quantile (0..1) of the steady-contact tilt (deg) from the histogram of ``ts`` (bin centre)."""
    h = ts[TS_HIST:TS_HIST + TILT_BINS]
    n = float(h.sum())
    if n <= 0:
        return None
    k = int(np.searchsorted(np.cumsum(h), q * n))
    return (min(k, TILT_BINS - 1) + 0.5) * TILT_BIN_DEG


def tick_figures(ts: np.ndarray) -> dict:
    """The figures of :func:`tick_stats` so far (cumulative; each robot sample carries them, so the
    summary can be recomputed from the log): the 1 kHz force peak, the steady-contact ticks, their
    RMS relative force error and tilt median / 95th percentile."""
    n = int(ts[TS_NSTEADY])
    return {"tick_force_peak_N": float(ts[TS_PEAK]), "tick_steady": n,
            "tick_force_rms_rel": math.sqrt(ts[TS_SQERR] / n) if n else None,
            "tick_tilt_median_deg": tick_quantile(ts, 0.5), "tick_tilt_p95_deg": tick_quantile(ts, 0.95)}


def new_tick_stats(force_desired: float, threshold: float, settle_ticks: int) -> np.ndarray:
    ts = np.zeros(N_TS)
    ts[TS_N + 2] = 1.0
    ts[TS_FD], ts[TS_THR], ts[TS_SETTLE] = force_desired, threshold, settle_ticks
    return ts


# ----------------------------------------------------------------------------- the PyBullet hot loop
# numba's dispatcher costs ~0.2 µs per array argument, more for tuples, and most for nested tuples
# of mixed types (typing and unboxing ``getJointStates``' tuple of (q, q̇, reaction 6-tuple, torque)
# tuples cost ~2.5 µs a call): the hot loop passes the joint positions and velocities as two flat
# tuples (``zip(*states)``), the controller's kpk and mut, and two packed arrays.
# cst (built by :func:`pack_constants` once per explorer interval): header [m, F_d, use_vref],
# v_ref (3), the chain (F (m, 4, 4), axis (m, 3), qidx (m,)), tcp offset (3), R_se (3, 3), p_se (3),
# m g, com (3), tare load (6), guard q_lo (n), q_hi (n), dq_hi (n), tcp speed max, workspace lo (3),
# hi (3), tau_max (n), inertial compensation on (1/0), tool mass, principal inertia (3); n = the arm's
# joints (the header's second number is the chain length m, the DoF n follows it).
# io (read back by SimArm.follow), MAX_DOF slots per joint vector, the first n used: q, q̇, w (6),
# tau (the total torque to send), diag (N_CD), T (16), J (6 x n, row-major, in 6 MAX_DOF slots).
IO_Q, IO_DQ = 0, MAX_DOF
IO_W = 2 * MAX_DOF
IO_TAU = IO_W + 6
IO_DIAG = IO_TAU + MAX_DOF
IO_T = IO_DIAG + N_CD
IO_J = IO_T + 16
N_IO = IO_J + 6 * MAX_DOF


def pack_constants(chain, contact, guard, tau_max, force_desired: float, v_ref) -> np.ndarray:
    """The ``cst`` array of :func:`pybullet_tick` (see the layout above)."""
    F, axis, qidx, off = chain
    use = v_ref is not None
    parts = [[len(qidx), float(force_desired), 1.0 if use else 0.0, int(np.max(qidx)) + 1], v_ref if use else np.zeros(3),
             F.ravel(), axis.ravel(), qidx.astype(float), off, contact.R_se_m.ravel(), contact.p_se_v, [contact.mg],
             contact.com, contact.tare_load, guard.q_lo, guard.q_hi, guard.dq_hi, [guard.cfg.tcp_speed_max],
             guard.ws_lo, guard.ws_hi, tau_max,
             [1.0 if contact.inertial else 0.0, contact.load.mass], contact.inertia]
    return np.ascontiguousarray(np.concatenate([np.asarray(x, dtype=float).ravel() for x in parts]))


@njit
def _unpack_constants(cst):
    """Views into the ``cst`` array of :func:`pack_constants` (layout above)."""
    m = int(cst[0])
    force_desired = cst[1]
    use_vref = cst[2] != 0.0
    n = int(cst[3])
    v_ref = cst[4:7]
    F = cst[7:7 + 16 * m].reshape((m, 4, 4))
    axis = cst[7 + 16 * m:7 + 19 * m].reshape((m, 3))
    qidx = cst[7 + 19 * m:7 + 20 * m].astype(np.int64)
    o = 7 + 20 * m  # the rest: sizes fixed by n
    tcp_off = cst[o:o + 3]
    R_se = cst[o + 3:o + 12].reshape((3, 3))
    p_se = cst[o + 12:o + 15]
    mg = cst[o + 15]
    com = cst[o + 16:o + 19]
    tare = cst[o + 19:o + 25]
    o += 25
    q_lo = cst[o:o + n]
    q_hi = cst[o + n:o + 2 * n]
    dq_hi = cst[o + 2 * n:o + 3 * n]
    o += 3 * n
    tcp_max = cst[o]
    ws_lo = cst[o + 1:o + 4]
    ws_hi = cst[o + 4:o + 7]
    tau_max = cst[o + 7:o + 7 + n]
    o += 7 + n
    inertial = cst[o] != 0.0
    mass = cst[o + 1]
    inertia = cst[o + 2:o + 5]
    return (force_desired, use_vref, v_ref, F, axis, qidx, tcp_off, R_se, p_se, mg, com, tare, q_lo, q_hi, dq_hi,
            tcp_max, ws_lo, ws_hi, tau_max, inertial, mass, inertia)


@njit
def pybullet_tick(i, A, D, qs, dqs, reading, bias, cst, kpk, mut, kd, io, ts, t, dyn, fg):
    """One 1 kHz tick after the joint read: FK + Jacobian, contact wrench, force check, the control
    law, state checks, and the torque to send (the law's + ``bias``, clamped to tau_max).

    The law: with ``kd`` empty, the "track" loop's line controller towards row i of A, D (n, 3),
    the gliding target line (kpk, mut: the controller's; ``mut`` is updated); else a joint-impedance
    move (the set-up moves), τ = K (q_d - q) + D (q̇_d - q̇) (:class:`JointImpedance`), q_d (rad)
    and q̇_d (rad/s) row i of A, D (k, n), kd (2n,) the joint stiffness (n) then damping (n); n the
    arm's joints (cst's header). qs, dqs : joint positions (rad) and velocities (rad/s), flat tuples
    whose first n entries are the arm's (``zip(*getJointStates(...))``). reading : the sensor's 6
    numbers (tare removed); bias : gravity + Coriolis (n numbers). ts : :func:`tick_stats` (updated). t : the sample time,
    s; dyn : the inertial compensation's state (:func:`inertial_wrench`, updated); fg : the force
    guard's limits and filter (:func:`force_fault`, updated).
    Returns an F_* code (OK: send io[IO_TAU:IO_TAU + n]). The separate kernels, chained.
    """
    n = int(cst[3])
    q = io[IO_Q:IO_Q + n]
    dq = io[IO_DQ:IO_DQ + n]
    for j in range(n):
        q[j] = qs[j]
        dq[j] = dqs[j]
    (force_desired, use_vref, v_ref, F, axis, qidx, tcp_off, R_se, p_se, mg, com, tare, q_lo, q_hi, dq_hi, tcp_max,
     ws_lo, ws_hi, tau_max, inertial, mass, inertia) = _unpack_constants(cst)
    T = io[IO_T:IO_T + 16].reshape((4, 4))
    J = io[IO_J:IO_J + 6 * n].reshape((6, n))
    w = io[IO_W:IO_W + 6]
    diag = io[IO_DIAG:IO_DIAG + N_CD]
    fk_jacobian(q, F, axis, qidx, tcp_off, T, J)
    r = np.empty(6)
    for k in range(6):
        r[k] = reading[k]
    if inertial:
        contact_wrench_dyn(r, t, T, J, dq, R_se, p_se, mg, com, tare, mass, inertia, dyn, w)
    else:
        contact_wrench(r, T, R_se, p_se, mg, com, tare, w)
    tick_stats(T, w, ts)
    code, _f = force_fault(w, fg)
    if code != OK:
        return code
    joint = kd.shape[0] > 0
    task = np.empty(n)
    if joint:
        v0, v1, v2, _w0, _w1, _w2 = tcp_twist(J, dq, n)
        diag[CD_VEE], diag[CD_VEE + 1], diag[CD_VEE + 2] = v0, v1, v2
    else:
        line_force_step(T, J, q, dq, A[i], D[i], w, MODE_TRACK, force_desired, 0.0, v_ref, use_vref,
                        kpk, mut, task, diag)
        v0, v1, v2 = diag[CD_VEE], diag[CD_VEE + 1], diag[CD_VEE + 2]
    pos = np.empty(3)
    pos[0], pos[1], pos[2] = T[0, 3], T[1, 3], T[2, 3]
    code, _j = state_fault(q, dq, pos, math.sqrt(v0 * v0 + v1 * v1 + v2 * v2), q_lo, q_hi, dq_hi, tcp_max, ws_lo, ws_hi)
    if code != OK:
        return code
    for j in range(n):
        lim = tau_max[j]
        tau = kd[j] * (A[i, j] - q[j]) + kd[n + j] * (D[i, j] - dq[j]) if joint else task[j]
        io[IO_TAU + j] = min(max(tau + bias[j], -lim), lim)
    return OK
