"""One safety guard for every backend: force limit, joint limits, workspace box, watchdogs.

The guard only judges; the state machine acts. Each check returns a :class:`Fault` with a
one-line reason and the action that makes the robot safe:

- "retreat": pull the tool back along its axis, then stop (excess contact force: backing
  off is what reduces it);
- "hold": hold the present joint position, then stop (limits, workspace, a stalled
  explorer, a silent sensor: moving anywhere would act on bad information).

:func:`stop_action` overrides "hold" while the tool may touch the object (approach, explore, a
retreat not finished) or anything touches (a set-up move that ran into something):
the tool first lifts along its axis under position control, which needs no force reading, since
a hold while pressed leaves a force nobody watches any more (issue 15).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from tergodic_cli.errors import require
# the limits' config lives with the robot's (numpy-free: the CLI builds its options at start-up)
from tergodic_cli.robot.config import SafetyConfig  # noqa: F401


@dataclass
class Fault:
    """A safety fault: kind ("force", "joint_position", ...), action ("retreat" | "hold"), one-line reason."""

    kind: str
    action: str
    reason: str
    t: float = 0.0
    data: dict = field(default_factory=dict)


#: States in which the tool may be pressed on the object (a retreat is still lifting it off).
CONTACT_STATES = ("approach", "explore", "retreat")
#: Exit code of a run that ended on a fault, made safe.
FAULT_EXIT_CODE = 3


def stop_action(fault: Fault, state: str, touching: bool = False) -> str:
    """How to make the robot safe after ``fault`` in state ``state``: "retreat", "hold" or "stop"
    (the robot's own controller already stopped it). Never "hold" while the tool may be pressed
    (approach, explore, a retreat not finished) or while anything touches (``touching``: a set-up
    move that ran into something)."""
    if fault.action == "stop":
        return "stop"
    if state in CONTACT_STATES or touching:
        return "retreat"
    return fault.action


def resolve_stop(fault: Fault, state: str, touching: bool = False) -> Fault:
    """``fault`` with the action of :func:`stop_action` and, when that lifts instead of holding,
    the reason saying so."""
    action = stop_action(fault, state, touching)
    if action == fault.action:
        return fault
    reason = fault.reason.replace("; holding position", "") + "; lifting the tool off the surface"
    return Fault(fault.kind, action, reason, fault.t, dict(fault.data))


def fault_exit_code(summary: dict) -> int:
    """0 for a run that ended normally, :data:`FAULT_EXIT_CODE` for one stopped on a fault (made safe)."""
    return FAULT_EXIT_CODE if summary.get("final_state") == "stopped" and not summary.get("interrupted") else 0


class SafetyGuard:
    """Checks states, sensor samples and targets against :class:`SafetyConfig`.

    Parameters
    ----------
    cfg : the limits.
    q_min, q_max, dq_max : (dof,) the arm's joint limits (rad, rad/s).
    force_desired : F_d, N (sets the default force limits).
    dt : s between two force checks (the control period: the force filter's sampling time).
    """

    def __init__(self, cfg: SafetyConfig, q_min: np.ndarray, q_max: np.ndarray, dq_max: np.ndarray,
                 force_desired: float, dt: float = 0.001):
        self.cfg = cfg
        lo, hi = np.ascontiguousarray(cfg.workspace_min, float), np.ascontiguousarray(cfg.workspace_max, float)
        require(lo.shape == (3,) and hi.shape == (3,) and bool(np.all(lo < hi)),
                "the workspace box needs min < max on every axis", "e.g. min 0.15,-0.6,0 and max 0.85,0.6,0.9 (metres)")
        self.ws_lo, self.ws_hi = lo, hi
        self.force_limit = (float(cfg.force_limit) if cfg.force_limit is not None
                            else max(cfg.force_limit_factor * force_desired, force_desired + cfg.force_limit_margin))
        require(self.force_limit > max(force_desired, 0.0),
                f"the force limit {self.force_limit:g} N is not above the desired force {force_desired:g} N",
                "raise --force-limit or lower --force")
        self.force_impact_limit = (float(cfg.force_impact_limit) if cfg.force_impact_limit is not None
                                   else max(cfg.force_impact_factor * force_desired, cfg.force_impact_min, self.force_limit))
        require(self.force_impact_limit >= self.force_limit,
                f"the impact limit {self.force_impact_limit:g} N is below the force limit {self.force_limit:g} N",
                "raise the impact limit (robot_options safety.force_impact_limit) or lower the force limit")
        require(cfg.force_filter_hz >= 0 and float(dt) > 0, f"force_filter_hz must be >= 0 Hz, got {cfg.force_filter_hz}",
                "e.g. 10")
        # new arrays, so contiguous as the compiled checks want them
        self.q_lo = np.asarray(q_min, float) + cfg.joint_margin
        self.q_hi = np.asarray(q_max, float) - cfg.joint_margin
        self.dq_hi = np.asarray(dq_max, float) * cfg.velocity_factor
        from tergodic_cli.robot import kernels

        self._k = kernels
        #: The force check's limits and filter state (kernels.FG_*), updated by every check, compiled or not.
        self.force_state = np.zeros(kernels.N_FG)
        self.force_state[kernels.FG_ALPHA] = kernels.lowpass_gain(cfg.force_filter_hz, float(dt))
        self.force_state[kernels.FG_LIMIT] = self.force_limit
        self.force_state[kernels.FG_RAW] = self.force_impact_limit
        self._sensor_t: float | None = None
        self._sensor_seen_at = 0.0
        self._target_t: float | None = None

    # ------------------------------------------------------------------ per control step
    def check_state(self, t: float, q: np.ndarray, dq: np.ndarray, tcp, tcp_speed: float) -> Fault | None:
        """Joint position/velocity limits, TCP speed and the workspace box (compiled: runs at 1 kHz)."""
        q = np.asarray(q, dtype=float)
        dq = np.asarray(dq, dtype=float)
        k = self._k
        code, j = k.state_fault(q, dq, np.asarray(tcp, dtype=float), float(tcp_speed), self.q_lo, self.q_hi,
                                self.dq_hi, float(self.cfg.tcp_speed_max), self.ws_lo, self.ws_hi)
        if code == k.OK:
            return None
        if code == k.F_JOINT_POS:
            return Fault("joint_position", "hold",
                         f"joint {j + 1} at {q[j]:+.3f} rad is outside its limits [{self.q_lo[j]:+.3f}, {self.q_hi[j]:+.3f}] rad; "
                         "holding position", t)
        if code == k.F_JOINT_VEL:
            return Fault("joint_velocity", "hold",
                         f"joint {j + 1} moves at {dq[j]:+.2f} rad/s, over its {self.dq_hi[j]:.2f} rad/s limit; holding position", t)
        if code == k.F_TCP_SPEED:
            return Fault("tcp_speed", "hold", f"the tool moves at {tcp_speed:.2f} m/s, over {self.cfg.tcp_speed_max:.2f} m/s; "
                         "holding position", t)
        return Fault("workspace", "hold", f"the tool at {fmt_xyz(tcp)} m left the workspace box "
                     f"{fmt_xyz(self.ws_lo)}..{fmt_xyz(self.ws_hi)} m; holding position", t)

    def check_force(self, t: float, wrench_ee) -> Fault | None:
        """|F| of the contact force: one tick over the impact limit, or low-passed over the force limit
        (one call per control period: the filter's clock)."""
        code, _f = self._k.force_fault(np.asarray(wrench_ee, dtype=float), self.force_state)
        return None if code == self._k.OK else self.force_fault(t, code)

    def force_fault(self, t: float, code: int) -> Fault:
        """The fault of a failed force check (code F_FORCE or F_IMPACT), from the guard's force state.
        A NaN force is an impact too."""
        k, fg = self._k, self.force_state
        f = float(fg[k.FG_F])
        if code == k.F_IMPACT:
            return Fault("force", "retreat", f"contact force {f:.1f} N in one tick, over the {self.force_impact_limit:.1f} N "
                         "impact limit; retreating", t, {"force": f, "force_tick": f})
        ff = float(fg[k.FG_FILT])
        return Fault("force", "retreat", f"contact force {ff:.1f} N (low-passed at {self.cfg.force_filter_hz:g} Hz) over "
                     f"the {self.force_limit:.1f} N limit; retreating", t, {"force": ff, "force_tick": f})

    @property
    def force_filtered(self) -> float:
        """|F| low-passed as the force limit sees it, N (after the last check)."""
        return float(self.force_state[self._k.FG_FILT])

    def check_sensor(self, t: float, sample_t: float, wrench) -> Fault | None:
        """Watchdog on the F/T stream: a sample time that stops advancing, or non-finite values."""
        w = wrench.tolist() if isinstance(wrench, np.ndarray) else wrench
        if not math.isfinite(w[0] + w[1] + w[2] + w[3] + w[4] + w[5]):
            return Fault("sensor", "hold", "the force/torque sensor returned non-finite values; holding position", t)
        if sample_t != self._sensor_t:
            self._sensor_t = sample_t
            self._sensor_seen_at = t
        elif t - self._sensor_seen_at > self.cfg.sensor_timeout:
            return Fault("sensor", "hold", f"the force/torque sensor stopped updating (no new sample for "
                         f"{(t - self._sensor_seen_at) * 1e3:.0f} ms); holding position", t)
        return None

    def check_reading(self, t: float, reading, wrench_ee) -> Fault | None:
        """:meth:`check_sensor` on the sample, then :meth:`check_force` unless the sample is no
        measurement (``reading.valid`` False: a simulated sensor before its first physics step)."""
        return self.check_sensor(t, reading.t, reading.wrench) or (
            self.check_force(t, wrench_ee) if getattr(reading, "valid", True) else None)

    # ------------------------------------------------------------------ targets and the explorer
    def inside(self, x: np.ndarray) -> bool:
        return bool(np.all(x >= self.ws_lo) and np.all(x <= self.ws_hi))

    def check_target(self, t: float, point: np.ndarray) -> Fault | None:
        """A new explorer target must be finite and inside the workspace box."""
        if not np.all(np.isfinite(point)):
            return Fault("target", "hold", "the explorer produced a non-finite target; holding position", t)
        if not self.inside(point):
            return Fault("workspace", "hold", f"target {fmt_xyz(point)} m is outside the workspace box "
                         f"{fmt_xyz(self.ws_lo)}..{fmt_xyz(self.ws_hi)} m; holding position", t)
        return None

    def feed_target(self, t: float) -> None:
        """Record that a fresh explorer target arrived at time ``t``."""
        self._target_t = t

    def check_explorer(self, t: float) -> Fault | None:
        """Watchdog on the explorer: no fresh target for ``explorer_timeout`` seconds."""
        if self._target_t is not None and t - self._target_t > self.cfg.explorer_timeout:
            return Fault("explorer", "hold", f"the explorer stalled (no new target for {t - self._target_t:.2f} s); "
                         "holding position", t)
        return None


def fmt_xyz(x) -> str:
    """A point in messages: "(x, y, z)" in metres, 3 decimals."""
    return "(" + ", ".join(f"{float(v):.3f}" for v in x) + ")"
