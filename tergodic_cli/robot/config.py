"""The robot stage's configuration (saved in summary.json and config.json beside the explorer's)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from tergodic_cli.config import Config, option, parse_floats
from tergodic_cli.errors import require

BACKENDS = ("pybullet",)


@dataclass
class ControllerGains(Config):
    """Gains of eq. 47 and the wrench PID (eq. 40), SI units; see :data:`PAPER_GAINS`.

    k_trans, k_rot : K_L on the translational (N/m) and rotational (N m/rad) error, ee axes x, y, z.
    d_trans, d_rot : D_V on the ee velocity (N s/m) and angular velocity (N m s/rad).
    kp, ki, kd : wrench PID on the force along the tool axis (N/N, 1/s, s).
    force_filter_hz : cut-off of the first-order filter on the measured force.
    integral_max : the PID integral term is kept in [0, integral_max × F_d].
    spin_stiffness : N m/rad holding the rotation about the tool axis (free for a line).
    nullspace_stiffness, nullspace_damping : posture spring (N m/rad, N m s/rad) in the null space.
    limit_stiffness : N m/rad pushing joints out of the last LIMIT_ZONE rad before a limit (null space).
    guard_speed, guard_damping : while pressing ("track"), a tool moving into the surface faster than
        guard_speed (m/s) gets guard_damping (N s/m) more damping on the excess: when contact is lost
        the force PID's push no longer flies it into the surface (issue 15: 38 N at F_d = 1 N).
    pid_wrench : the PID acts on the full wrench (eqs. 40-41, W_d = (0, 0, F_d, 0, 0, 0), zero desired
        torque): kp and kd on all six components, ki on the axial force (across the line the integral
        winds up against the friction until the tool sticks); False: on the axial force only.
    derivative_filter_hz : cut-off of a second first-order filter (after force_filter_hz) on the
        wrench the derivative term differentiates (0: none).
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
    guard_speed: float = 0.005
    guard_damping: float = 1000.0
    pid_wrench: bool = False
    derivative_filter_hz: float = 0.0


#: The paper's gains (V-A3), for comparison runs.
PAPER_GAINS = ControllerGains(k_trans=(750.0, 750.0, 300.0), k_rot=(30.0, 30.0, 30.0), d_trans=(150.0, 150.0, 50.0),
                              d_rot=(10.0, 10.0, 10.0), kp=0.5, ki=5.0, kd=0.5, pid_wrench=True,
                              derivative_filter_hz=5.0)


def gains_preset(name: str) -> dict:
    """The gains a ``--gains`` name stands for, as a config dict: "tuned" (:class:`ControllerGains`' defaults)
    or "paper" (:data:`PAPER_GAINS`).

    Parameters
    ----------
    name : str

    Returns
    -------
    dict
        :class:`ControllerGains` fields.
    """
    require(name in ("tuned", "paper"), f"unknown --gains {name!r}", "use --gains tuned or --gains paper")
    return (PAPER_GAINS if name == "paper" else ControllerGains()).to_dict()


@dataclass
class SafetyConfig(Config):
    """Limits, SI units.

    force_limit : N: the contact force |F|, low-passed at force_filter_hz, over this is an overload
        (retreat); None = force_limit_factor × F_d, at least F_d + force_limit_margin. The filter
        passes a sustained overload and not the contact's single-tick spikes (1 kHz peaks of
        1.9-3.2 × F_d in normal runs stopped them on a raw 3 × F_d limit; docs/robot.md, "Force limits").
    force_filter_hz : cut-off of the first-order low-pass the force limit applies to, Hz (0: none).
    force_limit_margin : N: the low-passed limit's floor above F_d (a light press jitters as many
        newtons as a firm one: 3 × 2 N = 6 N stopped 2 N runs).
    force_impact_limit : N: one tick's |F| over this is an impact (retreat at once, no filter);
        None = force_impact_factor × F_d, at least force_impact_min and the force limit.
    joint_margin : rad kept inside the joint position limits.
    velocity_factor : share of the joint velocity limits allowed.
    tcp_speed_max : m/s allowed at the TCP.
    workspace_min, workspace_max : corners of the box (base frame, m) the TCP and every target must stay in.
    sensor_timeout : s without a new F/T sample before holding.
    explorer_timeout : s (robot clock) without a fresh explorer target before holding.
    """

    force_limit: float | None = field(default=None, metadata=option(
        "--force-limit", "Contact force, low-passed at 10 Hz, that makes the robot retreat and stop (one tick over "
        "5 x --force, at least 30 N, is an impact and stops at once)", unit="N", group="robot",
        default="3 x --force, at least --force + 5"))
    force_limit_factor: float = 3.0
    force_limit_margin: float = 5.0
    force_filter_hz: float = 10.0
    force_impact_limit: float | None = None
    force_impact_factor: float = 5.0
    force_impact_min: float = 30.0
    joint_margin: float = 0.02
    velocity_factor: float = 0.9
    tcp_speed_max: float = 0.5
    workspace_min: tuple[float, float, float] = field(default=(0.15, -0.6, -0.01), metadata=option(
        "--workspace", "Workspace box xmin,ymin,zmin,xmax,ymax,zmax in the base frame", unit="m", group="robot",
        type=str, sets=("workspace_min", "workspace_max"),
        parse=lambda text: (lambda b: (b[:3], b[3:]))(parse_floats(text, 6, "--workspace", "0.15,-0.6,0,0.85,0.6,0.9"))))
    workspace_max: tuple[float, float, float] = (0.85, 0.6, 0.9)
    sensor_timeout: float = 0.02
    explorer_timeout: float = 0.5


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
