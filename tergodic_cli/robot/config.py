"""The robot stage's configuration (saved in summary.json and config.json beside the explorer's)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tergodic_cli.config import Config, option, parse_floats
from tergodic_cli.errors import require
from tergodic_cli.robot.controller import ControllerGains, gains_preset
from tergodic_cli.robot.safety import SafetyConfig

BACKENDS = ("pybullet",)


@dataclass
class SpongeSpec:
    """The sponge: a compliant ball on a stiff holder beyond the hand.

    offset : hand origin -> ball centre along the hand's z, metres (beyond the closed fingertips).
    radius : ball radius, metres; the TCP is the ball's tip, offset + radius from the hand.
    stiffness, damping : contact stiffness (N/m) and damping (N s/m) of the ball.
    friction : Coulomb friction coefficient sponge/object.
    mass : kg.
    """

    offset: float = 0.13
    radius: float = 0.012
    stiffness: float = 5000.0
    damping: float = 500.0
    friction: float = 0.3
    mass: float = 0.03


@dataclass
class RobotConfig(Config):
    """Everything that determines a robot run; saved in a run's ``config.json`` (``robot_config``).

    backend : "pybullet" (real backends come later behind the same Arm/WrenchSensor protocols).
    arm : the simulated arm (pybullet): a name in ``backends.pybullet.arms.ARMS`` (panda, xarm6, iiwa).
    force : desired contact force F_d along the tool axis, N.
    gui : open the PyBullet GUI (DIRECT otherwise); realtime : pace the GUI to wall-clock time.
    object_pose : the capture frame's pose in the robot base frame: x,y,z[,roll,pitch,yaw] (m, deg)
        or x,y,z,qx,qy,qz,qw; None = the cloud's footprint centre 0.5 m in front of the base, on the table.
    explore_dt : simulated seconds per explorer step; the explorer must run with this dt
        (see :func:`~tergodic_cli.robot.run.robot_explore_config`). One explorer step is
        explore_dt / physics_dt control steps.
    physics_dt : control and physics period, s (1 kHz).
    hover_height : m above the start point (along the normal) where the approach begins.
    approach_speed, retreat_speed : m/s along the tool axis; retreat_distance : m.
    contact_speed : m/s at which the approach meets the surface (it slows down over the last
        ~approach_speed × 0.25 s; at 20 mm/s the impact reached 10-28 N on the bowl).
    contact_force : N of contact normal force that counts as touching (coverage is deposited
        only above it); None = 20 % of ``force``.
    normal_side : which side of the sheet the tool works on: auto (= outward), outward, up, out.
    mesh_edge : target triangle edge of the collision mesh, m.
    move_speed : peak joint speed of the picture -> hover move, rad/s.
    solver_iterations : PyBullet constraint-solver iterations.
    jacobian_every : control steps per Jacobian refresh, for backends where it costs (the PyBullet
        arm computes pose and Jacobian together in compiled code every step and ignores it).
    dynamics_every : control steps per refresh of the gravity + Coriolis compensation
        (``calculateInverseDynamics``); 4 = 250 Hz: at < 0.3 rad/s the joints move 1.2 mrad in 4 ms,
        ~0.03 N m of gravity torque on the shoulder (measured: no change in the force, tilt or
        tracking figures, docs/robot.md).
    velocity_feedforward : damp the tool's velocity relative to the moving target line (its
        glide between explorer steps) instead of its absolute velocity (eq. 46): no damping lag.
    max_tool_tilt_deg : hardware runs only: the commanded tool axis is kept within this angle of
        straight down. The simulated run follows the normal and drops what the arm cannot reach
        (:mod:`tergodic_cli.robot.reach`).
    picture_q : the picture posture, rad (one angle per joint); None: the arm's own ("ready" pose).
    inertial_compensation : remove the tool's inertial wrench (mass × acceleration from the arm's
        state) from the F/T reading as well as its weight, so the wrench is the contact's.
    """

    backend: str = "pybullet"
    arm: str = field(default="panda", metadata=option(
        "--arm", "The simulated arm: panda, xarm6 (UFactory xArm 6, 6 DoF) or iiwa (KUKA LBR iiwa).", group="pybullet"))
    force: float = field(default=5.0, metadata=option(
        "--force", "Desired contact force along the tool axis", unit="N", group="robot"))
    gui: bool = field(default=False, metadata=option(
        "--gui", "Open the PyBullet GUI (needs a display).", group="pybullet"))
    realtime: bool = field(default=False, metadata=option(
        "--realtime", "Pace the simulation to wall-clock time (with --gui).", group="pybullet"))
    object_pose: tuple[float, ...] | None = field(default=None, metadata=option(
        "--object-pose", "Capture frame in the robot base frame: x,y,z[,roll,pitch,yaw] (m, deg) or x,y,z,qx,qy,qz,qw",
        group="robot", type=str, parse=lambda text: parse_floats(text, None, "--object-pose", "0.5,0,0.2"),
        default="the identity for a capture taken in the base frame (--source sim, or a calibrated --camera-pose); "
                "otherwise, pybullet only, the cloud's footprint centre 0.5 m in front of the base with its lowest "
                "point on a 0.2 m stand, turned 0, 90, -90 or 180 deg about the vertical, then the same at 0.4 m: the "
                "first pose where the arm reaches the whole target, else the one reaching most of it (the pose is "
                "printed and saved in summary.json); franka refuses to guess"))
    explore_dt: float = field(default=0.2, metadata=option(
        "--explore-dt", "Simulated seconds per explorer step (agent limits are rescaled so a step moves the same "
        "path)", group="robot"))
    physics_dt: float = 0.001
    hover_height: float = 0.04
    approach_speed: float = 0.02
    contact_speed: float = 0.002
    retreat_speed: float = 0.05
    retreat_distance: float = 0.05
    contact_force: float | None = field(default=None, metadata=option(
        "--contact-force", "Force that counts as touching (coverage is deposited above it)", unit="N", group="robot",
        default="20% of --force"))
    normal_side: str = field(default="auto", metadata=option(
        "--normal-side", "Side of the sheet the tool works on: auto (= outward: consistent over the sheet, facing the "
        "side the cloud is seen from), outward, up or out.", group="robot"))
    mesh_edge: float = 0.01
    move_speed: float = 0.8
    solver_iterations: int = 10
    jacobian_every: int = 4
    dynamics_every: int = 4
    velocity_feedforward: bool = True
    max_tool_tilt_deg: float = 60.0
    inertial_compensation: bool = True
    picture_q: tuple[float, ...] | None = None
    sponge: SpongeSpec = field(default_factory=SpongeSpec)
    gains: ControllerGains = field(default_factory=ControllerGains, metadata=option(
        "--gains", "Controller gains: tuned or paper (the paper's K, D and wrench PID on the full wrench, V-A3).",
        group="pybullet", type=str, parse=gains_preset, default="tuned"))
    safety: SafetyConfig = field(default_factory=SafetyConfig)

    @property
    def contact_threshold(self) -> float:
        return float(self.contact_force) if self.contact_force is not None else 0.2 * self.force


def validate_robot_config(cfg: RobotConfig) -> None:
    """Refuse impossible settings with a one-line problem; fix."""
    require(cfg.backend in BACKENDS, f"unknown robot backend '{cfg.backend}'", f"use one of {', '.join(BACKENDS)}")
    require(math.isfinite(cfg.force) and cfg.force > 0, f"--force must be > 0 N, got {cfg.force}", "e.g. --force 5")
    require(cfg.force <= 40, f"--force {cfg.force} N is more than a sponge should press", "use a force up to 40 N (paper: 5 N)")
    require(0.0001 <= cfg.physics_dt <= 0.005, f"physics_dt {cfg.physics_dt} s is outside 0.1-5 ms", "use 0.001 (1 kHz)")
    ratio = cfg.explore_dt / cfg.physics_dt
    require(cfg.explore_dt > 0 and abs(ratio - round(ratio)) < 1e-6 and round(ratio) >= 1,
            f"the explorer step {cfg.explore_dt} s is not a whole number of {cfg.physics_dt * 1e3:g} ms control steps",
            "use e.g. --explore-dt 0.1")
    require(cfg.hover_height > 0.005, "hover_height must be > 5 mm", "e.g. 0.04")
    require(cfg.approach_speed > 0 and cfg.retreat_speed > 0, "approach and retreat speeds must be > 0", "e.g. 0.03 m/s")
    require(0 < cfg.contact_speed <= cfg.approach_speed, "contact_speed must be > 0 and <= approach_speed",
            "e.g. 0.005 m/s")
    require(cfg.contact_threshold < cfg.force, f"the contact threshold {cfg.contact_threshold:g} N is not below --force",
            "lower --contact-force")
    require(cfg.sponge.radius > 0.002, "the sponge radius must be > 2 mm", "e.g. 0.012")
    require(cfg.mesh_edge >= 0, "mesh_edge must be >= 0 m", "e.g. 0.006")
    require(1 <= int(cfg.jacobian_every) <= 10, "jacobian_every must be 1..10 control steps", "use 4 (250 Hz)")
    require(1 <= int(cfg.dynamics_every) <= 10, "dynamics_every must be 1..10 control steps", "use 4 (250 Hz)")
    require(0 < cfg.max_tool_tilt_deg <= 90, "max_tool_tilt_deg must be in (0, 90]", "e.g. 60")
