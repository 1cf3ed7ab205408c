"""What a run is made of besides the stage configs: its starts, its log, the closed loop and the real
robot's connection. Each is a small dataclass whose fields carry their command-line option
(:func:`~tergodic_cli.config.option`), saved in a run's ``config.json`` (:mod:`tergodic_cli.run`).

Standard library only, so the verbs can build their options at start-up.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from tergodic_cli.config import Config, option

_STARTS = "Start positions (n, 3) metres: .npz with key x0_arr (the reference starts), x0 or starts; .npy; or .csv rows x,y,z."


@dataclass
class StartSpec(Config):
    """Where the agents start: ``start`` is "random", a point index, or "x,y,z" (metres);
    or ``starts_file`` (see :func:`~tergodic_cli.run.read_starts`: (m, 3) metres) from ``start_index`` on."""

    start: str | None = field(default=None, metadata=option(
        "--start", "Start: x,y,z in metres, a point index, or 'random'", default="random"))
    starts_file: str | None = field(default=None, metadata=option("--starts", _STARTS, type=Path, parse=str))
    start_index: int | None = field(default=None, metadata=option(
        "--start-index", "Row of --starts to use", default="0"))


@dataclass
class LogSpec(Config):
    """The run log: the per-point cloud every ``cloud_every`` steps (and at the end); ``live``
    ("HOST:PORT") also streams the log to Foxglove over WebSocket while the run goes on."""

    cloud_every: int = field(default=50, metadata=option(
        "--log-cloud-every", "Log coverage/heat/source per point every N steps (and at the end)."))
    live: str | None = field(default=None, metadata=option(
        "--live", "Stream the log's channels to Foxglove over WebSocket while the run goes on (Open connection: "
        "ws://HOST:PORT); --live alone: 127.0.0.1:8765.", metavar="[HOST:PORT]"))
    #: with ``live``: start once a viewer has connected; keep serving the final state until Ctrl-C
    live_wait: bool = field(default=False, metadata=option(
        "--live-wait", "With --live (implied, at 127.0.0.1:8765 unless given): start only once a viewer has "
        "connected, and keep serving the final state until Ctrl-C."))


@dataclass
class ClosedLoopSpec(Config):
    """The closed loop of a simulated robot on a ``--source sim`` capture (docs/closed_loop.md):
    re-capture every ``recapture_every`` explorer steps (None: no loop, one pass), stop once the camera
    sees less than ``until_clean`` of the initial marking or ``max_steps`` are spent (None: the run's steps)."""

    recapture_every: int | None = field(default=None, metadata=option(
        "--recapture-every", "Closed loop: re-capture with the camera every K explorer steps and update the target "
        "(basis reused).", group="pybullet, sim capture"))
    until_clean: float = field(default=0.05, metadata=option(
        "--until-clean", "Stop when the camera sees less than this share of the initial marking.",
        group="closed loop"))
    max_steps: int | None = field(default=None, metadata=option(
        "--max-steps", "Step budget", group="closed loop", default="--steps"))


@dataclass
class HardwareSpec(Config):
    """A real robot's connection (``--robot franka``, ``franka-torque`` or ``ur``): the controller's address and the force source
    (:func:`~tergodic_cli.backends.factory.make_hardware`), and whether the run only plans (``dry_run``:
    connect, read, report; nothing moves and only ``config.json`` is written, which repeats the dry run)."""

    robot_ip: str | None = field(default=None, metadata=option(
        "--robot-ip", "IP address of the robot controller.", group="franka, franka-torque, ur"))
    ft: str | None = field(default=None, metadata=option(
        "--ft", "Force source: franka (the arm's own estimate, default with --robot franka), ur (the UR's own, "
        "default with --robot ur), bota or netft (franka-torque needs one of these two).", group="franka, franka-torque, ur"))
    ft_address: str | None = field(default=None, metadata=option(
        "--ft-address", "Bota config JSON or Net F/T address.", group="franka, franka-torque, ur"))
    dry_run: bool = field(default=False, metadata=option(
        "--dry-run/--no-dry-run", "Connect read-only (no real-time kernel needed), read the sensors and print the plan without moving; OUT/config.json "
        "records it, and --config repeats it as a dry run unless --no-dry-run is given.", group="franka, franka-torque, ur"))

    def connection(self) -> dict:
        """The :func:`~tergodic_cli.backends.factory.make_hardware` arguments (robot_ip, ft, ft_address)."""
        return {"robot_ip": self.robot_ip, "ft": self.ft, "ft_address": self.ft_address}
