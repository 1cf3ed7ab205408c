"""A fake ``rtde_control`` (ur_rtde 1.6.5): ``RTDEControlInterface`` with the signatures its pybind11
module reports and the range checks ur_rtde makes (servoL's lookahead 0.03-0.2 s and gain 100-2000,
force mode's type 1-3 and damping 0-1: out of range raises ValueError, as pybind11 maps
std::range_error), driving :class:`fakes.ur_world.URWorld`. Commands on a protective-stopped
robot return False."""

from __future__ import annotations

import math

import numpy as np

from fakes.rtde_receive import _NETWORK
from fakes.ur_world import _rotm


def _pose(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotm(v[3:]), v[:3]
    return T


class RTDEControlInterface:
    FLAG_UPLOAD_SCRIPT = 1

    def __init__(self, hostname: str, frequency: float = -1.0, flags: int = 1, ur_cap_port: int = 50002, rt_priority: int = 0):
        world = _NETWORK.get(hostname)
        if world is None:
            raise RuntimeError(f"Failed to connect to {hostname}:30004 - Connection refused")
        self.world = world
        world.control_created += 1
        self.connected = True

    def _ok(self, name: str) -> bool:
        self.world.calls.append(name)
        return not self.world.protective and self.world.program_running

    def setTcp(self, arg0) -> bool:
        if len(arg0) != 6:
            raise TypeError("setTcp(): incompatible function arguments")
        self.world.tool = float(arg0[2])
        return self._ok("setTcp")

    def forceModeSetDamping(self, arg0: float) -> bool:
        if not 0.0 <= arg0 <= 1.0:
            raise ValueError("forceModeSetDamping: damping must be between 0 and 1")
        return self._ok("forceModeSetDamping")

    def forceMode(self, arg0, arg1, arg2, arg3, arg4) -> bool:
        if int(arg3) not in (1, 2, 3):
            raise ValueError("forceMode: type must be 1, 2 or 3")
        if len(arg0) != 6 or len(arg1) != 6 or len(arg2) != 6 or len(arg4) != 6:
            raise TypeError("forceMode(): incompatible function arguments")
        if not self._ok("forceMode"):
            return False
        w = self.world
        w.mode = "force"
        w.force_cmd = (_pose(arg0), np.asarray(arg1, dtype=float), np.asarray(arg2, dtype=float), np.asarray(arg4, dtype=float))
        return True

    def forceModeStop(self) -> bool:
        if self.world.mode == "force":
            self.world.mode = None
        return self._ok("forceModeStop")

    def servoL(self, arg0, arg1: float, arg2: float, arg3: float, arg4: float, arg5: float) -> bool:
        if not 0.03 <= arg4 <= 0.2:
            raise ValueError("servoL: lookahead_time must be between 0.03 and 0.2")
        if not 100 <= arg5 <= 2000:
            raise ValueError("servoL: gain must be between 100 and 2000")
        if not self._ok("servoL"):
            return False
        self.world.mode, self.world.servo_target = "servo", _pose(arg0)
        return True

    def servoStop(self, a: float = 10.0) -> bool:
        if self.world.mode == "servo":
            self.world.mode = None
        return self._ok("servoStop")

    def speedStop(self, a: float = 10.0) -> bool:
        self.world.mode = None
        return self._ok("speedStop")

    def moveJ(self, q, speed: float = 1.05, acceleration: float = 1.4, asynchronous: bool = False) -> bool:
        if len(q) != 6:
            raise TypeError("moveJ(): incompatible function arguments")
        if not self._ok("moveJ"):
            return False
        w = self.world
        dist = float(np.max(np.abs(np.asarray(q) - w.q)))
        w.mode = None
        w.q = np.asarray(q, dtype=float).copy()
        w.t += dist / max(speed, 1e-6) + 0.2 + math.sqrt(dist / max(acceleration, 1e-6))
        return True

    def isProgramRunning(self) -> bool:
        return self.world.program_running and not self.world.protective

    def stopScript(self) -> None:
        self.world.calls.append("stopScript")

    def isConnected(self) -> bool:
        return self.connected

    def disconnect(self) -> None:
        self.connected = False
