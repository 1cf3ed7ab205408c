"""The controller's geometric algebra (paper eqs. 13-17, 35-47) against pygafro and plain linear algebra."""

from __future__ import annotations

import math

import numpy as np
import pytest

pygafro = pytest.importorskip("pygafro")

from gafro_matrix import adjoint, skew, twist_from_gafro  # noqa: E402

from tergodic_cli.robot import ga  # noqa: E402
from tergodic_cli.robot.controller import ControllerGains, LineForceController  # noqa: E402
from tergodic_cli.robot.interfaces import ArmState, ContactWrench, ToolLoad  # noqa: E402


def _rng(seed=0):
    return np.random.default_rng(seed)


# ------------------------------------------------------------ the matrix forms' CGA counterparts (test-only)
def motor_log(T):
    """gafro's motor logarithm in the decoupled chart: (t, φ) as a twist (6,) = (v, ω)."""
    return np.concatenate([T[:3, 3], ga.matrix_to_rotvec(T[:3, :3])])


def motor_exp(V):
    """Inverse of motor_log: the (4, 4) transform T(v) R(ω)."""
    return ga.pose_matrix(ga.rotvec_to_matrix(V[3:]), V[:3])


def coadjoint(T):
    """6×6 matrix of M W M̃ on wrenches (f, m): f' = R f, m' = R m + t × R f."""
    R, t = T[:3, :3], T[:3, 3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, :3] = skew(t) @ R
    A[3:, 3:] = R
    return A


def line_from_point_dir(a, d):
    d = np.asarray(d, dtype=float) / np.linalg.norm(d)
    return d, np.cross(np.asarray(a, dtype=float), d)


def line_transform(T, d, m):
    """M L M̃ on a Plücker line: d' = R d, m' = R m + t × R d."""
    R, t = T[:3, :3], T[:3, 3]
    return R @ d, R @ m + np.cross(t, R @ d)


def line_motor_z(a, d):
    out = ga.line_motor_z(*(float(x) for x in a), *(float(x) for x in d))
    return np.array(out[:3]), np.array(out[3:])


def twist_to_gafro(V):  # [e12, e13, e23, e1∞, e2∞, e3∞]
    return np.array([V[5], -V[4], V[3], V[0], V[1], V[2]])


def wrench_to_gafro(W):  # [e01, e02, e12, e03, e13, e23]
    return np.array([W[0], W[1], W[5], W[2], -W[4], W[3]])


def wrench_from_gafro(c):
    return np.array([c[0], c[1], c[3], c[5], -c[4], c[2]])


def line_from_gafro(c):  # [e01∞, e02∞, e12∞, e03∞, e13∞, e23∞] = [dx, dy, mz, dz, -my, mx], |d| = 1
    d, m = np.array([c[0], c[1], c[3]]), np.array([c[5], -c[4], c[2]])
    return d / np.linalg.norm(d), m / np.linalg.norm(d)


def gafro_motor(T):
    return pygafro.Motor(pygafro.MotorGenerator(twist_to_gafro(motor_log(T))))


def gafro_motor_matrix(M):
    return np.asarray(M.toTransformationMatrix(), dtype=float)


def gafro_line(a, d):
    """P(a) ∧ P(a + d) ∧ e∞, oriented along d."""
    a = np.asarray(a, dtype=float)
    return pygafro.Line(pygafro.Point(*a), pygafro.Point(*(a + np.asarray(d, dtype=float))))


def _random_motor(rng, scale=1.0) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return ga.pose_matrix(ga.rotvec_to_matrix(axis * rng.uniform(0.1, 2.5)), rng.normal(size=3) * scale)


def _gafro_twist_vec(obj) -> np.ndarray:
    return np.array([obj.get_e12(), obj.get_e13(), obj.get_e23(), obj.get_e1i(), obj.get_e2i(), obj.get_e3i()])


def test_power_is_twist_wrench_inner_product():
    # III-B: V·W = -p with p = v·f + ω·m, for the coefficient maps used everywhere.
    rng = _rng(1)
    for _ in range(20):
        V, W = rng.normal(size=6), rng.normal(size=6)
        inner = pygafro.Twist(twist_to_gafro(V)).multivector() | pygafro.Wrench(wrench_to_gafro(W)).multivector()
        assert inner.vector()[0] == pytest.approx(-(V[:3] @ W[:3] + V[3:] @ W[3:]), abs=1e-12)


def test_power_is_invariant_under_motors():
    # The same motor moves a twist (adjoint) and a wrench (its sandwich): the power must not change.
    rng = _rng(2)
    for _ in range(10):
        T = _random_motor(rng)
        V, W = rng.normal(size=6), rng.normal(size=6)
        assert (adjoint(T) @ V) @ (coadjoint(T) @ W) == pytest.approx(V @ W, rel=1e-12, abs=1e-12)


def test_sandwich_matrices_match_pygafro():
    rng = _rng(3)
    for _ in range(10):
        T = _random_motor(rng, 0.5)
        M = gafro_motor(T)
        np.testing.assert_allclose(gafro_motor_matrix(M), T, atol=1e-12)
        V, W = rng.normal(size=6), rng.normal(size=6)
        Vg = pygafro.Twist(twist_to_gafro(V)).transform(M)
        Wg = pygafro.Wrench(wrench_to_gafro(W)).transform(M)
        np.testing.assert_allclose(twist_from_gafro(np.asarray(Vg.vector())), adjoint(T) @ V, atol=1e-12)
        np.testing.assert_allclose(wrench_from_gafro(np.asarray(Wg.vector())), coadjoint(T) @ W, atol=1e-12)
        a, d = rng.normal(size=3), rng.normal(size=3)
        d /= np.linalg.norm(d)
        Lg = M.apply(gafro_line(a, d))
        d2, m2 = line_transform(T, *line_from_point_dir(a, d))
        np.testing.assert_allclose(line_from_gafro(np.asarray(Lg.vector()))[0], d2, atol=1e-12)
        np.testing.assert_allclose(line_from_gafro(np.asarray(Lg.vector()))[1], m2, atol=1e-12)


def test_log_exp_round_trips():
    rng = _rng(4)
    for _ in range(20):
        T = _random_motor(rng)
        np.testing.assert_allclose(motor_exp(motor_log(T)), T, atol=1e-12)
        V = np.concatenate([rng.normal(size=3), rng.normal(size=3)])
        V[3:] *= rng.uniform(0.05, 3.0) / np.linalg.norm(V[3:])  # |φ| < π: the log's principal branch
        np.testing.assert_allclose(motor_log(motor_exp(V)), V, atol=1e-10)
        # pygafro: exp(B) then MotorLogarithm gives B back, and its exp is our exp.
        M = pygafro.Motor(pygafro.MotorGenerator(twist_to_gafro(V)))
        np.testing.assert_allclose(gafro_motor_matrix(M), motor_exp(V), atol=1e-12)
        np.testing.assert_allclose(twist_from_gafro(_gafro_twist_vec(pygafro.MotorLogarithm(M))), V, atol=1e-9)


def test_rotation_helpers_round_trip():
    rng = _rng(5)
    for _ in range(20):
        R = ga.rotvec_to_matrix(rng.normal(size=3))
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(ga.quat_to_matrix(ga.matrix_to_quat(R)), R, atol=1e-12)
    R_pi = ga.rotvec_to_matrix(np.array([0.0, math.pi, 0.0]))
    np.testing.assert_allclose(ga.rotvec_to_matrix(ga.matrix_to_rotvec(R_pi)), R_pi, atol=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_line_motor_maps_ee_axis_onto_target_and_matches_gafro(seed):
    rng = _rng(10 + seed)
    a = rng.normal(size=3) * 0.1
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 0.2  # the tool never points away from the surface
    d /= np.linalg.norm(d)
    t, phi = line_motor_z(a, d)
    T = motor_exp(np.concatenate([t, phi]))
    # It maps the ee z-axis (e0 ∧ e3 ∧ e∞) onto the target line, orientation included ...
    d2, m2 = line_transform(T, np.array([0.0, 0.0, 1.0]), np.zeros(3))
    d_t, m_t = line_from_point_dir(a, d)
    np.testing.assert_allclose(d2, d_t, atol=1e-12)
    np.testing.assert_allclose(m2, m_t, atol=1e-12)
    # ... it is the motor of ref. [54] as pygafro computes it ...
    Mg = pygafro.Line.Z().getMotor(gafro_line(a, d))
    np.testing.assert_allclose(gafro_motor_matrix(Mg), T, atol=1e-10)
    # ... and eq. 37's logarithm is pygafro's.
    np.testing.assert_allclose(twist_from_gafro(_gafro_twist_vec(pygafro.MotorLogarithm(Mg))),
                               np.concatenate([t, phi]), atol=1e-9)
    # It is the smallest such screw: the rotation angle is the angle between the lines.
    assert np.linalg.norm(phi) == pytest.approx(math.acos(d[2]), abs=1e-12)


def test_line_motor_of_parallel_lines_is_the_offset():
    t, phi = line_motor_z(np.array([0.01, -0.02, 0.3]), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(t, [0.01, -0.02, 0.0], atol=1e-15)
    np.testing.assert_allclose(phi, 0.0, atol=1e-15)
    Mg = pygafro.Line.Z().getMotor(gafro_line(np.array([0.01, -0.02, 0.3]), np.array([0.0, 0.0, 1.0])))
    np.testing.assert_allclose(gafro_motor_matrix(Mg)[:3, 3], [0.01, -0.02, 0.0], atol=1e-12)


def _ga_control_law(T, J_base, dq, a, d, W_meas, g: ControllerGains, f_cmd_z) -> np.ndarray:
    """Eq. 47 written with pygafro objects only (motors, lines, MotorLogarithm, sandwiches, GA inner products)."""
    M = gafro_motor(T)
    Mr = pygafro.Motor(M.reverse())  # M̃
    # Eq. 35-36 in the ee frame: L_ee = e0 ∧ e3 ∧ e∞ and M̃ L_a⊥ M.
    L_a_ee = Mr.apply(gafro_line(a, d))
    M_line = pygafro.Line.Z().getMotor(L_a_ee)
    V_L = twist_from_gafro(_gafro_twist_vec(pygafro.MotorLogarithm(M_line)))  # eq. 37, (t, φ)
    K = np.array(g.k_trans + g.k_rot)
    W_L = K * V_L  # eq. 38 read as an identity inertia (see controller.py)
    W_L[2] = 0.0  # no stiffness along the line
    # Eq. 45: ee-frame Jacobian columns B_i^ee = M̃ B_i M, here from the base-frame screws at the TCP.
    cols = []
    for i in range(J_base.shape[1]):
        B_tcp = J_base[:, i]  # (v at the TCP, ω), base axes
        # as a screw at the base origin, then into the ee frame by the reverse motor
        B0 = np.concatenate([B_tcp[:3] - np.cross(B_tcp[3:], T[:3, 3]), B_tcp[3:]])
        Bg = pygafro.Twist(twist_to_gafro(B0)).transform(Mr)
        cols.append(Bg)
    V_ee = sum((twist_from_gafro(np.asarray(c.vector())) * dq[i] for i, c in enumerate(cols)), np.zeros(6))
    W_V = np.array(g.d_trans + g.d_rot) * V_ee  # eq. 46
    # eq. 40's output: on the tool axis (a float), or the full wrench (6,)
    W_C = np.array([0.0, 0.0, f_cmd_z, 0.0, 0.0, 0.0]) if np.ndim(f_cmd_z) == 0 else np.asarray(f_cmd_z)
    W = W_L - W_V + W_C
    Wg = pygafro.Wrench(wrench_to_gafro(W)).multivector()
    # τ_i = -B_i^ee · W (III-B: B · W = -τ)
    return np.array([-(c.multivector() | Wg).vector()[0] for c in cols])


def _random_line_state(rng):
    """A random TCP motor, Jacobian, joint state, target line (a, unit d) near the tool and a measured wrench."""
    T = _random_motor(rng, 0.3)
    J = rng.normal(size=(6, 7)) * 0.5
    q, dq = rng.normal(size=7), rng.normal(size=7) * 0.3
    a = T[:3, 3] + rng.normal(size=3) * 0.01
    d = T[:3, :3] @ np.array([0.0, 0.0, 1.0]) + rng.normal(size=3) * 0.1
    d /= np.linalg.norm(d)
    return T, J, q, dq, a, d, rng.normal(size=6)


@pytest.mark.parametrize("seed", range(5))
def test_matrix_control_law_equals_geometric_algebra(seed):
    rng = _rng(20 + seed)
    T, J, q, dq, a, d, W_meas = _random_line_state(rng)
    g = ControllerGains(spin_stiffness=0.0, nullspace_stiffness=0.0, nullspace_damping=0.0, limit_stiffness=0.0,
                        force_filter_hz=0.0, guard_damping=0.0)  # (the speed guard is no part of eq. 47)
    ctrl = LineForceController(g, 1e-3, q_rest=q, x_ref=np.array([1.0, 0.0, 0.0]))
    ctrl.start_tracking(5.0, 3.0)
    out = ctrl.step(ArmState(0.0, q, dq, T, J), a.tolist(), d.tolist(), W_meas, "track", 5.0)
    # the PID output of this step, from its own definition (eqs. 40-41, filter off):
    e = 5.0 - W_meas[2]
    f_cmd = g.kp * e + g.ki * ctrl.integral
    expected = _ga_control_law(T, J, dq, a, d, W_meas, g, f_cmd)
    # (pygafro's logarithm adds 1e-10 to a denominator: agreement to ~1e-9 relative)
    np.testing.assert_allclose(out.tau, expected, rtol=1e-7, atol=1e-6)


@pytest.mark.parametrize("full", [False, True])
def test_wrench_pid_on_the_full_wrench(full):
    """Eqs. 40-41: W_C = K_p W_e + K_i ∫ W_e, W_e = W_d - W'_m, W_d = (0, 0, F_d, 0, 0, 0) (zero desired
    torque): K_p on all six components with ``pid_wrench`` (K_i on the axial one), else on the axial force only."""
    rng = _rng(40)
    T, J, q, dq, a, d, W_meas = _random_line_state(rng)
    g = ControllerGains(spin_stiffness=0.0, nullspace_stiffness=0.0, nullspace_damping=0.0, limit_stiffness=0.0,
                        force_filter_hz=0.0, guard_damping=0.0, pid_wrench=full, kp=0.5, ki=5.0, kd=0.0)
    ctrl = LineForceController(g, 1e-3, q_rest=q, x_ref=np.array([1.0, 0.0, 0.0]))
    ctrl.start_tracking(5.0, 3.0)
    out = ctrl.step(ArmState(0.0, q, dq, T, J), a.tolist(), d.tolist(), W_meas, "track", 5.0)
    e = np.array([0.0, 0.0, 5.0, 0.0, 0.0, 0.0]) - W_meas
    W_C = g.kp * e * full  # the integral acts on the axial force only
    W_C[2] = g.kp * e[2] + g.ki * ctrl.integral
    np.testing.assert_allclose(out.tau, _ga_control_law(T, J, dq, a, d, W_meas, g, W_C), rtol=1e-7, atol=1e-6)


def test_force_pid_integrates_to_the_desired_force():
    # A static contact: measured force = commanded force (quasi-static spring). The PID must settle at F_d.
    g = ControllerGains(force_filter_hz=0.0)
    ctrl = LineForceController(g, 1e-3, q_rest=np.zeros(7), x_ref=np.array([1.0, 0.0, 0.0]))
    T = np.eye(4)
    J = np.vstack([np.eye(6), np.zeros((1, 6))]).T  # 6×7, joint i drives task axis i
    st = ArmState(0.0, np.zeros(7), np.zeros(7), T, J)
    f = 0.0
    for _ in range(3000):
        out = ctrl.step(st, [0.0, 0.0, 0.1], [0.0, 0.0, 1.0], np.array([0, 0, f, 0, 0, 0.0]), "track", 5.0)
        f += 0.05 * (out.wrench_cmd[2] - f)  # a first-order plant: the force follows the command
    assert f == pytest.approx(5.0, abs=1e-3)


def test_contact_wrench_removes_tool_weight_and_moves_to_tcp():
    rng = _rng(30)
    load = ToolLoad(1.2, np.array([0.001, -0.002, 0.05]))
    frame = ga.pose_matrix(ga.rotvec_to_matrix(np.array([0, 0, 0.3])), np.array([0.0, 0.0, -0.1]))  # sensor in ee
    cw = ContactWrench(load, frame)
    R_tare = ga.rotvec_to_matrix(rng.normal(size=3))
    R_now = ga.rotvec_to_matrix(rng.normal(size=3))
    # What a perfect sensor reads: tool weight support + the contact wrench, in the sensor frame.
    F_ee = np.array([0.3, -0.2, 5.0])  # force the tool applies, ee frame, at the TCP (moment 0 there)
    R_se = frame[:3, :3]
    f_s = R_se.T @ F_ee
    p_tcp_in_s = R_se.T @ (-frame[:3, 3])
    m_s = np.cross(p_tcp_in_s, f_s)  # moment about the sensor origin of a force acting at the TCP

    def weight(R_base_sensor):  # what the arm applies to hold the tool still: Rᵀ (0, 0, m g) at the centre of mass
        f = R_base_sensor.T @ np.array([0.0, 0.0, load.mass * 9.81])
        return np.concatenate([f, np.cross(load.com, f)])

    raw_tare = weight(R_tare @ R_se)
    raw_now = weight(R_now @ R_se) + np.concatenate([f_s, m_s])
    cw.tare_at(R_tare)
    out = cw(raw_now - raw_tare, R_now)
    np.testing.assert_allclose(out[:3], F_ee, atol=1e-12)
    np.testing.assert_allclose(out[3:], 0.0, atol=1e-12)
