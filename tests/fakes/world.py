"""A quasi-static physical world behind the fake SDKs: a Panda (pygafro kinematics), a sponge-tipped
tool with an F/T sensor, and a rigid surface given as a point cloud with normals (base frame).

Time advances only through :meth:`FakeWorld.advance` (1 ms steps), so runs are deterministic. The arm is
massless: each SDK motion (fake franky) turns its control law into a TCP twist or joint velocities,
the world integrates them and enforces the surface as a unilateral constraint. The contact force is
what the impedance law pushes into the constraint:

    u = v_t + D⁻¹ K e          (the free tool's twist under the impedance law)
    v = u - min(u·n, 0) n       (no motion into the surface while touching it)
    f_n = max(0, -(u·n) nᵀ D n)  (the damper force the constraint absorbs = K e·(-n) in steady state)
"""

from __future__ import annotations

import math
import threading

import numpy as np
from scipy.spatial import cKDTree

from gafro_matrix import jacobian_spatial, skew

from tergodic_cli.robot.ga import matrix_to_rotvec
from tergodic_cli.backends.franka.gafro import FrankaModel

G = 9.81


class FakeWorld:
    """The plant shared by the fake robot and the fake sensors.

    points, normals : (n, 3) the rigid surface (base frame, m) and its unit normals pointing to the
        side the tool works on. q0 : (7,) initial joints. tool_length : m from gafro's hand TCP to the
        sponge tip along the hand's z-axis. tool_mass (kg), tool_com (3,) m in the sensor frame.
    sensor_in_ee : (4, 4) sensor frame in the TCP frame. noise : N (and N·dm) std of sensor noise.
    normal_force_bias : N added to the contact force the impedance law produces (joint friction and model
        error of a real arm: the force loop has to trim it away).
    """

    dt = 0.005
    #: steps between Jacobian refreshes (pygafro's Jacobian costs ~150 µs; it changes slowly)
    jacobian_every = 2

    def __init__(self, points, normals, q0, tool_length: float = 0.05, tool_mass: float = 0.3,
                 tool_com=(0.0, 0.0, 0.04), sensor_in_ee=None, noise: float = 0.01, seed: int = 0,
                 normal_force_bias: float = 0.0):
        self.points = np.asarray(points, dtype=float)
        self.normals = np.asarray(normals, dtype=float)
        self.kd = cKDTree(self.points)
        tool = np.eye(4)
        tool[2, 3] = tool_length
        self.model = FrankaModel(tool=tool)
        self.ne_t_ee = np.eye(4)
        self.q = np.asarray(q0, dtype=float).copy()
        self.q_rest = self.q.copy()
        self.dq = np.zeros(7)
        self.t = 0.0
        self.tool_mass = float(tool_mass)
        self.tool_com = np.asarray(tool_com, dtype=float)
        if sensor_in_ee is None:
            sensor_in_ee = np.eye(4)
            sensor_in_ee[2, 3] = -(tool_length + 0.1034)  # at the flange, axes of the TCP
        self.sensor_in_ee = np.asarray(sensor_in_ee, dtype=float)
        self.noise = float(noise)
        self.rng = np.random.default_rng(seed)
        self.bias = np.array([0.4, -0.3, 1.2, 0.02, -0.01, 0.03])  # what a tare must remove
        self.f_n = 0.0
        self.contact_normal = np.array([0.0, 0.0, 1.0])
        self.robot = None  # the fake franky Robot driving the arm
        self.lock = threading.Lock()
        self.sensor_fault = None  # "freeze" | "nan" to inject sensor faults
        self._frozen = None
        self.max_force = 0.0
        #: N added to the normal contact force the impedance law produces (joint friction, model error)
        self.normal_force_bias = float(normal_force_bias)
        self.J = None
        self._j_age = 0
        self._refresh()
        self._s, self._n = self.surface(self.T[:3, 3])

    # ------------------------------------------------------------------ kinematics
    def _refresh(self, jacobian: bool = True) -> None:
        self.T = self.model.fk(self.q) @ self.ne_t_ee
        if jacobian or self.J is None:
            Js = jacobian_spatial(self.model, self.q)  # (v at the base origin, ω)
            p = self.T[:3, 3]
            self.J = np.vstack([Js[:3] - skew(p) @ Js[3:], Js[3:]])  # v of the TCP point
            self._j_age = 0

    def surface(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """Signed distance of x above the surface (m) and the surface normal there (nearest cloud point's plane)."""
        _, i = self.kd.query(x)
        n = self.normals[i]
        return float((x - self.points[i]) @ n), n

    # ------------------------------------------------------------------ time
    def advance(self, seconds: float) -> None:
        n = max(1, int(round(seconds / self.dt)))
        for _ in range(n):
            self.step()

    def step(self) -> None:
        dt = self.dt
        with self.lock:
            cmd = self.robot._control(self, dt) if self.robot is not None else None
            self.f_n = 0.0
            if cmd is None:
                self.dq = np.zeros(7)
            elif cmd[0] == "dq":
                self.dq = np.asarray(cmd[1], dtype=float)
            else:  # ("twist", u (6,), D (6, 6))
                u, D = cmd[1], cmd[2]
                v = u.copy()
                s, n = self._s, self._n
                if s <= 1e-4 and u[:3] @ n < 0:
                    self.f_n = max(0.0, float(-(u[:3] @ n) * (n @ D[:3, :3] @ n)) + self.normal_force_bias)
                    v[:3] = u[:3] - (u[:3] @ n) * n
                    self.contact_normal = n
                self.dq = self._ik_rate(v)
            self.q = self.q + self.dq * dt
            self._j_age += 1
            self._refresh(self._j_age >= self.jacobian_every)
            s, n = self.surface(self.T[:3, 3])
            if s < 0:  # numerical penetration: push back onto the surface
                corr = np.zeros(6)
                corr[:3] = -s * n
                self.q = self.q + self._ik_rate(corr)
                self._refresh(False)
                s = 0.0
            self._s, self._n = s, n
            self.t += dt
            self.max_force = max(self.max_force, self.f_n)

    def _ik_rate(self, twist: np.ndarray) -> np.ndarray:
        J = self.J
        JJt = J @ J.T + 1e-6 * np.eye(6)
        Jp = J.T @ np.linalg.inv(JJt)
        return Jp @ twist + (np.eye(7) - Jp @ J) @ (2.0 * (self.q_rest - self.q))

    # ------------------------------------------------------------------ what the sensors see
    def arm_wrench_on_tool(self) -> tuple[np.ndarray, np.ndarray]:
        """(force, moment about the sensor origin), base frame: the arm holds the tool up and presses it."""
        T_s = self.T @ self.sensor_in_ee
        R_s, o = T_s[:3, :3], T_s[:3, 3]
        f_w = np.array([0.0, 0.0, self.tool_mass * G])  # against gravity
        f_c = -self.contact_normal * self.f_n  # the tool pushes into the surface
        r_com = R_s @ self.tool_com
        r_tip = self.T[:3, 3] - o
        return f_w + f_c, np.cross(r_com, f_w) + np.cross(r_tip, f_c)

    def sensor_wrench(self) -> np.ndarray:
        """(6,) what a wrist F/T sensor reads: arm-on-tool wrench in the sensor frame, plus bias and noise."""
        if self.sensor_fault == "freeze" and self._frozen is not None:
            return self._frozen
        with self.lock:
            f, m = self.arm_wrench_on_tool()
            R_s = (self.T @ self.sensor_in_ee)[:3, :3]
        w = np.concatenate([R_s.T @ f, R_s.T @ m]) + self.bias + self.rng.normal(0.0, self.noise, 6) * np.array([1, 1, 1, .1, .1, .1])
        if self.sensor_fault == "nan":
            w[:] = np.nan
        self._frozen = w
        return w

    def external_wrench_K(self) -> np.ndarray:
        """libfranka's K_F_ext_hat_K: the wrench the environment applies to the robot, TCP frame."""
        R = self.T[:3, :3]
        f = self.contact_normal * self.f_n
        return np.concatenate([R.T @ f, np.zeros(3)])

    def tilt_deg(self) -> float:
        return math.degrees(math.acos(max(-1.0, min(1.0, float(-self.T[:3, 2] @ self.contact_normal)))))

    def rotvec_error(self, R_target: np.ndarray) -> np.ndarray:
        return matrix_to_rotvec(R_target @ self.T[:3, :3].T)
