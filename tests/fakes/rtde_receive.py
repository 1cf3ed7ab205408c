"""A fake ``rtde_receive`` (ur_rtde 1.6.5): ``RTDEReceiveInterface`` with the signature its pybind11
module reports, reading :class:`fakes.ur_world.URWorld` (``_NETWORK[hostname] = world``)."""

from __future__ import annotations

import numpy as np

from fakes.ur_world import _rotvec

_NETWORK: dict = {}


class RTDEReceiveInterface:
    def __init__(self, hostname: str, frequency: float = -1.0, variables: list = [], verbose: bool = False,  # noqa: B006
                 use_upper_range_registers: bool = False, rt_priority: int = 0):
        world = _NETWORK.get(hostname)
        if world is None:
            raise RuntimeError(f"Failed to connect to {hostname}:30004 - Connection refused")
        self.world, self.connected = world, True

    def getActualQ(self) -> list:
        return self.world.q.tolist()

    def getActualQd(self) -> list:
        return self.world.dq.tolist()

    def getActualTCPPose(self) -> list:
        T = self.world.T
        return [*T[:3, 3].tolist(), *_rotvec(T[:3, :3]).tolist()]

    def getActualTCPForce(self) -> list:
        return self.world.tcp_force().tolist()

    def getTimestamp(self) -> float:
        return float(self.world.t)

    def isProtectiveStopped(self) -> bool:
        return bool(self.world.protective)

    def isEmergencyStopped(self) -> bool:
        return False

    def isConnected(self) -> bool:
        return self.connected

    def disconnect(self) -> None:
        self.connected = False
