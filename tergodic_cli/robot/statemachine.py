"""The robot's discrete states (paper V-A3) and their logged transitions.

picture -> hover -> approach -> explore -> retreat -> done; any fault -> hold or retreat -> stopped.
Where the tool cannot press across (a sharp edge, a gap in reach) it moves over: explore -> retreat
-> hover -> approach -> explore. The closed loop (issue 6) cycles: ... explore -> retreat -> picture (re-capture) -> hover -> ... -> picture -> done.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

PICTURE = "picture"  # at (or moving to) the picture pose, where the cloud is captured
HOVER = "hover"  # joint impedance move to, and wait at, the pose above the start point
APPROACH = "approach"  # along the surface normal until the contact force threshold, then press to F_d
EXPLORE = "explore"  # the agent drives the line target, the wrench PID holds F_d
RETREAT = "retreat"  # back along the tool axis
HOLD = "hold"  # a fault: joint impedance at the present position
DONE = "done"  # finished normally, holding still
STOPPED = "stopped"  # finished after a fault, holding still

ALLOWED = {
    PICTURE: {HOVER, DONE, RETREAT, HOLD, STOPPED},
    HOVER: {APPROACH, HOLD, RETREAT, STOPPED},
    APPROACH: {EXPLORE, RETREAT, HOLD, STOPPED},
    EXPLORE: {RETREAT, HOLD, STOPPED},
    RETREAT: {PICTURE, HOVER, DONE, HOLD, STOPPED},
    HOLD: {STOPPED},
    DONE: set(),
    STOPPED: set(),
}


@dataclass
class Transition:
    t: float  # robot clock, s
    step: int  # explorer steps done
    source: str
    target: str
    reason: str


@dataclass
class StateMachine:
    """Current state plus the list of transitions; every transition is reported to ``on_event``, and
    to ``before`` (with the :class:`Transition`) while the old state still holds."""

    state: str = PICTURE
    on_event: Callable[[int, str], None] | None = None
    history: list[Transition] = field(default_factory=list)
    before: Callable[[Transition], None] | None = None

    def go(self, target: str, t: float, step: int, reason: str) -> None:
        if target not in ALLOWED[self.state]:
            raise RuntimeError(f"illegal robot state transition {self.state} -> {target}")
        tr = Transition(t, step, self.state, target, reason)
        if self.before is not None:
            self.before(tr)
        self.history.append(tr)
        if self.on_event is not None:
            self.on_event(step, f"robot {self.state} -> {target} at t={t:.3f} s: {reason}")
        self.state = target

    @property
    def finished(self) -> bool:
        return self.state in (DONE, STOPPED)
