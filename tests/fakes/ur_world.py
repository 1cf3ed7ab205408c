"""The physical world behind the fake ``rtde_control`` / ``rtde_receive``: a UR5e (its own DH forward
kinematics and a finite-difference Jacobian, written here independently of tergodic's chain), a
tool on its flange and a rigid horizontal table at ``plane_z``.

Time advances only through :meth:`URWorld.advance` (2 ms steps). The controller's modes, as the
real UR's are documented: force mode is an admittance (along each compliant axis of the task frame
the TCP moves at (commanded wrench - reached wrench) / damping, within the axis' speed limit); at the
table the tool stops and the wrench it applies is what the admittance pushes into the table;
``servoL`` tracks its pose; ``moveJ`` moves the joints to their target (time advances by the move's
duration). A contact force over ``protective_limit`` is a protective stop.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

UR5E_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
UR5E_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
UR5E_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)


def _rotvec(R):
    """Rotation matrix -> rotation vector (scipy: exact near pi, where UR's tool-down poses live)."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def _rotm(v):
    return Rotation.from_rotvec(np.asarray(v, dtype=float)).as_matrix()


class URWorld:
    dt = 0.002

    def __init__(self, q0, plane_z: float, tool_length: float = 0.0, damping=(150.0, 150.0, 150.0, 3.0, 3.0, 3.0),
                 noise: float = 0.0, seed: int = 0, protective_limit: float = 150.0):
        self.q = np.asarray(q0, dtype=float).copy()
        self.dq = np.zeros(6)
        self.t = 0.0
        self.plane_z = float(plane_z)
        self.tool = float(tool_length)
        self.damping = np.asarray(damping, dtype=float)
        self.rng = np.random.default_rng(seed)
        self.noise = float(noise)
        self.protective_limit = float(protective_limit)
        self.mode = None  # None | "force" | "servo"
        self.force_cmd = None  # (task frame (4, 4), selection (6,), wrench (6,), limits (6,))
        self.servo_target = None
        self.f_n = 0.0
        self.max_force = 0.0
        self.protective = False
        self.program_running = True
        self.force_bias = 0.0  # N added to the contact force (something pushes back)
        self.control_created = 0
        self.calls: list[str] = []

    # ------------------------------------------------------------------ kinematics (standard DH)
    def fk(self, q) -> np.ndarray:
        T = np.eye(4)
        for i in range(6):
            ct, st = math.cos(q[i]), math.sin(q[i])
            ca, sa = math.cos(UR5E_ALPHA[i]), math.sin(UR5E_ALPHA[i])
            A = np.array([[ct, -st * ca, st * sa, UR5E_A[i] * ct], [st, ct * ca, -ct * sa, UR5E_A[i] * st],
                          [0, sa, ca, UR5E_D[i]], [0, 0, 0, 1.0]])
            T = T @ A
        tool = np.eye(4)
        tool[2, 3] = self.tool
        return T @ tool

    def jacobian(self, q, h: float = 1e-7) -> np.ndarray:
        T0 = self.fk(q)
        J = np.empty((6, 6))
        for j in range(6):
            qh = np.array(q, dtype=float)
            qh[j] += h
            Th = self.fk(qh)
            J[:3, j] = (Th[:3, 3] - T0[:3, 3]) / h
            J[3:, j] = _rotvec(Th[:3, :3] @ T0[:3, :3].T) / h
        return J

    @property
    def T(self) -> np.ndarray:
        return self.fk(self.q)

    # ------------------------------------------------------------------ time
    def advance(self, seconds: float) -> None:
        for _ in range(max(1, int(round(seconds / self.dt)))):
            self.step()

    def step(self) -> None:
        dt = self.dt
        T = self.T
        v = np.zeros(6)
        self.f_n = 0.0
        if self.protective:
            self.mode = None
        if self.mode == "force":
            Tf, sel, w, lim = self.force_cmd
            R = Tf[:3, :3]
            u = w / self.damping * sel  # task-frame twist of the admittance in free space
            v_task = np.clip(u, -lim, lim)
            v[:3], v[3:] = R @ v_task[:3], R @ v_task[3:]
            f_base = R @ w[:3]
            touching = T[2, 3] <= self.plane_z + 1e-4  # (0.1 mm: the joint update is not exactly linear)
            if touching and v[2] < 0.0:  # the table stops the tool: what the admittance pushes into it is the force
                self.f_n = max(0.0, -f_base[2] + self.force_bias)
                v[2] = 0.0
        elif self.mode == "servo":
            Td = self.servo_target
            v[:3] = (Td[:3, 3] - T[:3, 3]) / (5 * dt)
            v[3:] = _rotvec(Td[:3, :3] @ T[:3, :3].T) / (5 * dt)
        J = self.jacobian(self.q)
        self.dq = np.linalg.solve(J, v) if abs(np.linalg.det(J)) > 1e-9 else np.zeros(6)
        self.q = self.q + self.dq * dt
        T = self.T
        if T[2, 3] < self.plane_z:  # numerical penetration: back onto the table
            corr = np.zeros(6)
            corr[2] = self.plane_z - T[2, 3]
            self.q = self.q + np.linalg.solve(self.jacobian(self.q), corr)
        self.t += dt
        self.max_force = max(self.max_force, self.f_n)
        if self.f_n > self.protective_limit:
            self.protective = True

    # ------------------------------------------------------------------ what the UR reports
    def tcp_force(self) -> np.ndarray:
        """actual_TCP_force: the table's push on the tool at the TCP, base-frame axes (payload compensated)."""
        w = np.array([0.0, 0.0, self.f_n, 0.0, 0.0, 0.0])
        return w + self.rng.normal(0.0, self.noise, 6) * np.array([1, 1, 1, 0.1, 0.1, 0.1])
