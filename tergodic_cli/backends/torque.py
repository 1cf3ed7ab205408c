"""The paper's controller on a torque-controlled arm: a 1 kHz loop in a process of its own.

The loop (:class:`TorqueLoop`) reads the arm and the F/T sensor, computes the torque and writes it,
once per millisecond: the line impedance with the wrench PID of the simulation
(:class:`~tergodic_cli.robot.controller.LineForceController`, compiled
:func:`~tergodic_cli.robot.kernels.line_force_step`), the joint impedance of the set-up moves
(:class:`~tergodic_cli.robot.controller.JointImpedance`) or a Cartesian impedance on a pose (the
free-space moves, :func:`pose_impedance`), plus the SDK's Coriolis torque (the SDK adds gravity), and
the one-tick force guard (:func:`~tergodic_cli.robot.kernels.force_fault`): over the limit it lifts
the tool along its axis at once and reports the fault.

Why a process. libfranka stops the arm when a torque is late (its ``communication_constraints``
reflex: a few missed 1 ms packets). In the run's own process a control *thread* shares the GIL with
the explorer, the MCAP writer and the viewers: CPython hands the GIL over only every
``sys.getswitchinterval()`` (5 ms), and a garbage collection runs, GIL held, in whichever thread
allocated last, for as long as the heap takes to walk (tens of ms for a run's log buffers). The
loop process has its own interpreter: its own GIL, nothing else allocating, and its collector is
switched off (:func:`_serve`: the per-tick temporaries hold no cycles, reference counts free
them). The run process writes commands into a shared-memory record and reads the latest state
from it (:func:`link_dtype`: named fields, a sequence counter each way so neither side reads a
half-written record); nothing the run process does (a collection, a log flush, a slow explorer
step) can delay a tick. The process is forked at connect, before the run's log and viewers start
their threads.

``isolate="inline"`` runs the same :class:`TorqueLoop` in the caller, ticked by :meth:`LoopHandle.run_for`
(tests with a fake SDK, deterministic like the streamed backend's ``pace``).
"""

from __future__ import annotations

import gc
import math
import multiprocessing
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from tergodic_cli.backends.impedance import ImpedanceTarget
from tergodic_cli.errors import TergodicError
from tergodic_cli.robot.interfaces import ArmState, LineTarget, WrenchReading, WrenchSensor

#: The loop's laws (the ``law`` field of the command).
LAW_NONE, LAW_HOLD, LAW_LINE, LAW_POSE, LAW_JOINT = 0, 1, 2, 3, 4
#: Fault codes beyond the kernels' F_*: an SDK exception in the loop.
F_SDK = 100
#: Seconds the run process waits for the loop process to connect.
CONNECT_TIMEOUT_S = 30.0


def link_dtype(n: int) -> np.dtype:
    """The shared record between the run process and the loop process, for an arm of ``n`` joints.

    Command (run -> loop, ``cmd_seq`` odd while it is written): ``law``; the line target ``a``,
    ``d``, ``v_ref`` (m, m/s, base frame), ``use_vref``, ``line_mode`` (kernels.MODE_*), ``x_ref`` (the
    tool x-axis's spin reference, base frame; zeros: keep the controller's), ``threshold`` (N, contact),
    ``force`` (N), ``speed`` (m/s); the pose target ``pose`` (4, 4), ``K``, ``D`` (6, 6), ``twist``
    (6,); the joint move ``q_goal`` (n,) rad over ``move_s`` s; the contact-wrench constants
    (sensor frame ``R_se``, ``p_se``, tool weight ``mg`` N, ``com`` m, ``tare_load``); the force
    guard ``fg`` (kernels.N_FG); ``tare_req`` (a counter: tare the sensor), ``quit``.
    State (loop -> run, ``state_seq`` odd while it is written): ``tick``, ``t`` (s), ``q``, ``dq``,
    ``T``, ``J``, ``tau`` (the torque sent, N m), ``tau_measured``, ``reading`` (the sensor's, tare
    removed, sensor frame), ``reading_t``, ``wrench`` (the contact wrench, ee frame), ``f_filt`` (N),
    ``tare_done``, ``ready``, ``fault`` (a kernels.F_* code or F_SDK), ``fault_force`` (N),
    ``message`` (the SDK's error, UTF-8).
    """
    from tergodic_cli.robot import kernels as Kn

    return np.dtype([
        ("cmd_seq", "i8"), ("law", "i8"), ("a", "f8", 3), ("d", "f8", 3), ("v_ref", "f8", 3), ("use_vref", "i8"),
        ("line_mode", "i8"), ("x_ref", "f8", 3), ("force", "f8"), ("threshold", "f8"), ("speed", "f8"), ("pose", "f8", (4, 4)), ("K", "f8", (6, 6)),
        ("D", "f8", (6, 6)), ("twist", "f8", 6), ("q_goal", "f8", n), ("move_s", "f8"),
        ("R_se", "f8", (3, 3)), ("p_se", "f8", 3), ("mg", "f8"), ("com", "f8", 3), ("tare_load", "f8", 6),
        ("fg", "f8", Kn.N_FG), ("tare_req", "i8"), ("quit", "i8"),
        ("state_seq", "i8"), ("tick", "i8"), ("t", "f8"), ("q", "f8", n), ("dq", "f8", n), ("T", "f8", (4, 4)),
        ("J", "f8", (6, n)), ("tau", "f8", n), ("tau_measured", "f8", n), ("reading", "f8", 6), ("reading_t", "f8"),
        ("wrench", "f8", 6), ("f_filt", "f8"), ("tare_done", "i8"), ("ready", "i8"), ("fault", "i8"),
        ("fault_force", "f8"), ("message", "S200"),
    ])


#: Command fields the loop copies under the sequence counter.
CMD_FIELDS = ("law", "a", "d", "v_ref", "use_vref", "line_mode", "x_ref", "threshold", "force", "speed", "pose", "K", "D", "twist",
              "q_goal", "move_s", "R_se", "p_se", "mg", "com", "tare_load", "fg", "tare_req", "quit")
STATE_FIELDS = ("tick", "t", "q", "dq", "T", "J", "tau", "tau_measured", "reading", "reading_t", "wrench", "f_filt",
                "tare_done", "ready", "fault", "fault_force", "message")


class TorqueDevice(Protocol):
    """A torque-controlled arm's SDK, as the loop process uses it (e.g.
    :class:`~tergodic_cli.backends.franka.libfranka.LibfrankaDevice`). Created and used in the loop
    process only."""

    def connect(self) -> None:
        """Open the connection."""

    def read(self) -> tuple:
        """The next state, blocking until the SDK has it (1 kHz): (t s, q (n,), dq (n,), T (4, 4),
        J (6, n) base-frame Jacobian of the TCP, coriolis (n,) N m, measured joint torques (n,) N m)."""

    def start(self) -> None:
        """Start torque control; :meth:`read` then waits for the control's next state."""

    def write(self, tau: np.ndarray) -> None:
        """Send (n,) N m for the state just read (the SDK adds gravity)."""

    def finish(self) -> None:
        """End torque control gracefully (the arm comes to rest and the SDK holds it)."""

    def close(self) -> None:
        """Close the connection."""


@dataclass
class LoopSpec:
    """What the loop process builds and runs.

    device : () -> TorqueDevice; sensor : () -> WrenchSensor (both created in the loop process).
    gains : :class:`~tergodic_cli.robot.controller.ControllerGains`. dt : s, the SDK's period.
    q_rest : (n,) the null-space posture; q_min, q_max : (n,) rad; tau_max : (n,) N m;
    joint_k, joint_d : (n,) the set-up moves' joint impedance (N m/rad, N m s/rad).
    lift_speed : m/s, the lift along the tool axis after a force fault in the loop.
    tare_samples : sensor samples averaged by a tare.
    """

    device: Callable[[], object]
    sensor: Callable[[], WrenchSensor]
    gains: object
    q_rest: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    tau_max: np.ndarray
    joint_k: np.ndarray
    joint_d: np.ndarray
    dt: float = 0.001
    lift_speed: float = 0.02
    tare_samples: int = 50
    x_ref: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))


def pose_impedance(T: np.ndarray, J: np.ndarray, dq: np.ndarray, target: ImpedanceTarget) -> np.ndarray:
    """τ = Jᵀ (K e - D (J q̇ - twist)): the Cartesian impedance on a pose (free-space moves, holds).

    Parameters
    ----------
    T : (4, 4) TCP pose; J : (6, n) base-frame Jacobian; dq : (n,) rad/s.
    target : the pose, stiffness and damping (6, 6) and feed-forward twist of
        :func:`~tergodic_cli.backends.impedance.hold_target` (base frame).

    Returns
    -------
    (n,) N m. The error e = (p_d - p, log(R_d Rᵀ)) (m, rad), base frame.
    """
    from tergodic_cli.robot.ga import matrix_to_rotvec

    e = np.concatenate([target.pose[:3, 3] - T[:3, 3], matrix_to_rotvec(target.pose[:3, :3] @ T[:3, :3].T)])
    return J.T @ (target.stiffness @ e - target.damping @ (J @ dq - target.twist))


class TorqueLoop:
    """One 1 kHz tick after another (:meth:`tick`), commanded through ``link`` (see :func:`link_dtype`)."""

    def __init__(self, spec: LoopSpec, link: np.ndarray):
        from tergodic_cli.robot import kernels as Kn
        from tergodic_cli.robot.controller import JointImpedance, LineForceController

        self.Kn, self.spec, self.link = Kn, spec, link
        self.n = len(spec.q_rest)
        self.ctrl = LineForceController(spec.gains, spec.dt, spec.q_rest, spec.x_ref, spec.q_min, spec.q_max)
        self.joint = JointImpedance(spec.joint_k, spec.joint_d)
        self.device = self.sensor = None
        self.cmd = np.zeros((), dtype=link.dtype)
        self.seq = -1
        self.active = False  # torque control running
        self.law = LAW_NONE
        self.line = None  # the LineTargetLaw of the line law (robot/controller.py), new at each switch to it
        self.hold_q = None
        self.move = None  # (t0, q0, q1, duration) of a joint move
        self.fault = Kn.OK
        self.lift = None  # (a, d) of the lift after a force fault
        self.bias = np.zeros(6)
        self._tare = None  # samples of a tare in progress
        self.w = np.empty(6)
        self.fg = np.zeros(Kn.N_FG)  # the force guard's limits and filter state (kernels.force_fault)

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        self.device = self.spec.device()
        self.device.connect()
        self.sensor = self.spec.sensor()
        if hasattr(self.sensor, "connect"):
            self.sensor.connect()
        self._publish(*self.device.read(), np.zeros(self.n))
        self.link["ready"] = 1

    def close(self) -> None:
        try:
            if self.active and int(self.link["fault"]) != F_SDK:  # (after an SDK error the control is gone)
                self.device.finish()
        finally:
            self.active = False
            for dev in (self.sensor, self.device):
                if dev is not None and hasattr(dev, "disconnect" if dev is self.sensor else "close"):
                    getattr(dev, "disconnect" if dev is self.sensor else "close")()

    # ------------------------------------------------------------------ one tick
    def _command(self) -> None:
        """Copy the run's command when it is complete and new (the sequence counter even and unchanged)."""
        link = self.link
        s0 = int(link["cmd_seq"])
        if s0 == self.seq or s0 % 2:
            return
        fg = self.cmd["fg"].copy()
        for k in CMD_FIELDS:
            self.cmd[k] = link[k]
        if int(link["cmd_seq"]) == s0:
            self.seq = s0
            if not np.array_equal(fg[:3], self.cmd["fg"][:3]):  # new limits: the filter starts again
                self.fg = np.ascontiguousarray(self.cmd["fg"], dtype=float)

    def tick(self) -> bool:
        """Read, compute, write and publish one tick. Returns False once the run asked to quit."""
        Kn, cmd = self.Kn, self.cmd
        self._command()
        if int(cmd["quit"]):
            return False
        law = int(cmd["law"])
        if law != LAW_NONE and not self.active:  # the torque computed from the control's own first state
            self.device.start()
            self.active = True
        t, q, dq, T, J, coriolis, tau_measured = self.device.read()
        rd = self.sensor.read()
        r = np.asarray(rd.wrench, dtype=float) - self.bias
        self._tare_step(r)
        c = np.ascontiguousarray
        Kn.contact_wrench(c(r), T, c(cmd["R_se"]), c(cmd["p_se"]), float(cmd["mg"]), c(cmd["com"]), c(cmd["tare_load"]),
                          self.w)
        if law != LAW_NONE and self.fault == Kn.OK and self.fg[Kn.FG_RAW] > 0:
            code, f = Kn.force_fault(self.w, self.fg)
            if code != Kn.OK:  # lift along the tool's own axis now; the run hears of it with the next state
                self.fault = code
                self.fg[Kn.FG_F] = f
                self.lift = (T[:3, 3].copy(), T[:3, 2].copy())
        tau = np.zeros(self.n)
        if law != LAW_NONE:
            tau = self._law(law, t, q, dq, T, J)
            tau = np.clip(tau + coriolis, -self.spec.tau_max, self.spec.tau_max)
            self.device.write(tau)
        elif self.active:  # the run stopped the controller: end it, the SDK holds the arm
            self.device.finish()
            self.active = False
        self._publish(t, q, dq, T, J, tau_measured, tau, rd.t, r)
        return True

    def _law(self, law: int, t, q, dq, T, J) -> np.ndarray:
        cmd, Kn, c = self.cmd, self.Kn, np.ascontiguousarray
        if self.lift is not None and law == LAW_LINE and int(cmd["line_mode"]) == Kn.MODE_TRACK:
            a, d = self.lift  # after a force fault nothing presses again: lift until the run retreats itself
            return self.ctrl.step(ArmState(t, q, dq, T, J), a, d, self.w, "retreat", 0.0, self.spec.lift_speed).tau
        if law != self.law:
            from tergodic_cli.robot.controller import LineTargetLaw

            self.law, self.move, self.hold_q, self.line = law, None, q.copy(), LineTargetLaw()
        if law == LAW_LINE:
            if np.any(cmd["x_ref"] != 0.0):
                self.ctrl.x_ref = cmd["x_ref"]
            v_ref = c(cmd["v_ref"]) if int(cmd["use_vref"]) else None
            mode = int(cmd["line_mode"])
            target = LineTarget(c(cmd["a"]), c(cmd["d"]), "press" if mode == Kn.MODE_TRACK else "move",
                                float(cmd["force"]), float(cmd["speed"]) * (-1.0 if mode == Kn.MODE_RETREAT else 1.0), v_ref)
            return self.line.step(self.ctrl, ArmState(t, q, dq, T, J), self.w, target, float(cmd["threshold"])).tau
        if law == LAW_POSE:
            return pose_impedance(T, J, dq, ImpedanceTarget(c(cmd["pose"]), c(cmd["K"]), c(cmd["D"]), c(cmd["twist"])))
        if law == LAW_JOINT:
            from tergodic_cli.robot.controller import min_jerk

            key = (cmd["q_goal"].tobytes(), float(cmd["move_s"]))
            if self.move is None or self.move[0] != key:
                self.move = (key, t, q.copy())
            _, t0, q0 = self.move
            q_d, dq_d = min_jerk(q0, np.array(cmd["q_goal"]), float(cmd["move_s"]), t - t0)
            return self.joint(q, dq, q_d, dq_d)
        return self.joint(q, dq, self.hold_q)  # LAW_HOLD: the joints where they were at the switch

    def _tare_step(self, r: np.ndarray) -> None:
        req = int(self.cmd["tare_req"])
        if req == int(self.link["tare_done"]):
            return
        if self._tare is None:
            self._tare = []
        self._tare.append(r + 0.0)
        if len(self._tare) >= self.spec.tare_samples:
            ws = np.array(self._tare)
            if np.all(np.isfinite(ws)):
                self.bias = self.bias + ws.mean(axis=0)
            self._tare = None
            self.link["tare_done"] = req

    def _publish(self, t, q, dq, T, J, tau_measured, tau=None, reading_t=None, reading=None) -> None:
        link = self.link
        link["state_seq"] += 1
        link["tick"] += 1
        link["t"], link["q"], link["dq"], link["T"], link["J"] = t, q, dq, T, J
        link["tau_measured"] = tau_measured
        if tau is not None:
            link["tau"] = tau
        if reading is not None:
            link["reading"], link["reading_t"], link["wrench"] = reading, reading_t, self.w
            link["f_filt"] = self.ctrl.f_filt
        link["fault"] = self.fault
        link["fault_force"] = self.fg[self.Kn.FG_F] if self.fault != self.Kn.OK else 0.0
        link["state_seq"] += 1


def _report(link: np.ndarray, exc: BaseException) -> None:
    """An SDK exception that ended the loop (a reflex, a lost connection), for the run to read."""
    from tergodic_cli.backends.extras import one_line

    link["message"] = one_line(exc).encode("utf-8", "replace")[:200]
    link["fault"] = F_SDK


def _serve(spec: LoopSpec, link: np.ndarray) -> None:
    """The loop process: connect, tick until told to quit, end torque control, close."""
    gc.disable()  # nothing here may stall a tick; the per-tick temporaries hold no cycles
    loop = TorqueLoop(spec, link)
    try:
        loop.open()
        while loop.tick():
            pass
    except BaseException as exc:  # noqa: BLE001 - any end of the loop is reported to the run
        _report(link, exc)
    finally:
        try:
            loop.close()
        except Exception:  # noqa: BLE001 - already ending on an error
            pass


class LoopHandle:
    """The run process's side of a :class:`TorqueLoop`: the shared record, commands and state.

    isolate : "process" (the loop in a forked process: production) or "inline" (the loop in the
    caller, ticked by :meth:`run_for`: tests with a fake SDK).
    """

    def __init__(self, spec: LoopSpec, isolate: str = "process"):
        if isolate not in ("process", "inline"):
            raise ValueError(f"isolate must be 'process' or 'inline', got {isolate!r}")
        self.spec, self.isolate = spec, isolate
        dtype = link_dtype(len(spec.q_rest))
        self._shm = self.proc = self.loop = None
        if isolate == "process":
            from multiprocessing.shared_memory import SharedMemory

            self._shm = SharedMemory(create=True, size=dtype.itemsize)
            self.link = np.ndarray((), dtype=dtype, buffer=self._shm.buf)
            self.link[()] = np.zeros((), dtype=dtype)
        else:
            self.link = np.zeros((), dtype=dtype)

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        """Start the loop and wait until it has connected (the SDK's error as a TergodicError)."""
        if self.isolate == "process":
            ctx = multiprocessing.get_context("fork")  # the spec's factories need no pickling
            self.proc = ctx.Process(target=_serve, args=(self.spec, self.link), name="tergodic-1kHz", daemon=True)
            self.proc.start()
            t_end = time.monotonic() + CONNECT_TIMEOUT_S
            while not int(self.link["ready"]) and int(self.link["fault"]) != F_SDK:
                if time.monotonic() > t_end or not self.proc.is_alive():
                    break
                time.sleep(0.005)
        else:
            self.loop = TorqueLoop(self.spec, self.link)
            try:
                self.loop.open()
            except Exception as exc:  # noqa: BLE001 - reported as the process would
                _report(self.link, exc)
        if not int(self.link["ready"]):
            msg = self.message() or "the loop did not start in time"
            self.close()
            raise TergodicError(f"the 1 kHz torque loop could not connect: {msg}",
                                "check the cable and the address, unlock the joints and activate FCI in Desk")

    def close(self) -> None:
        """Tell the loop to quit (ending torque control), wait for it and free the shared record."""
        self.command(quit=1)
        if self.proc is not None:
            self.proc.join(5.0)
            if self.proc.is_alive():
                self.proc.terminate()
                self.proc.join(1.0)
            self.proc = None
        if self.loop is not None:
            self.loop.close()
            self.loop = None
        if self._shm is not None:
            link = np.array(self.link)  # keep the last state readable after the memory goes
            self.link = link
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    # ------------------------------------------------------------------ commands and state
    def command(self, **fields) -> None:
        """Write command fields (see :func:`link_dtype`) as one update."""
        link = self.link
        link["cmd_seq"] += 1  # odd: being written
        for k, v in fields.items():
            link[k] = v
        link["cmd_seq"] += 1

    def state(self) -> np.ndarray:
        """A consistent copy of the state fields (a 0-d record)."""
        for _ in range(1000):
            s0 = int(self.link["state_seq"])
            if s0 % 2 == 0:
                out = np.array(self.link)
                if int(self.link["state_seq"]) == s0:
                    return out
            time.sleep(0)
        return np.array(self.link)

    def message(self) -> str:
        return bytes(self.link["message"]).decode("utf-8", "replace")

    def alive(self) -> bool:
        return self.proc.is_alive() if self.proc is not None else self.loop is not None

    def run_for(self, seconds: float) -> None:
        """Inline: run the loop for ``seconds`` (ticks of spec.dt). Process: sleep as long."""
        if self.loop is None:
            time.sleep(seconds)
            return
        if int(self.link["fault"]) == F_SDK:
            return  # the loop ended on an SDK error, as its process would have
        for _ in range(max(1, int(round(seconds / self.spec.dt)))):
            try:
                if not self.loop.tick():
                    break
            except Exception as exc:  # noqa: BLE001 - reported as the process would
                _report(self.link, exc)
                break

    def wait(self, done: Callable[[], bool], timeout: float) -> bool:
        """Until ``done()`` (loop time when inline, wall time otherwise); False on time-out."""
        steps = int(math.ceil(timeout / 0.005))
        for _ in range(steps):
            if done():
                return True
            if int(self.link["fault"]) == F_SDK:
                return False
            self.run_for(0.005)
        return done()


class LoopSensor(WrenchSensor):
    """The F/T sensor as the run process sees it: the loop's latest reading (tare removed), its
    frame that of the real sensor; :meth:`tare` asks the loop to tare (it averages samples
    between ticks) and waits."""

    def __init__(self, arm: "TorqueArm", frame_in_ee: np.ndarray):
        super().__init__(frame_in_ee)
        self.arm = arm

    def read(self) -> WrenchReading:
        s = self.arm._require().state()
        return WrenchReading(float(s["reading_t"]), np.array(s["reading"]))

    def tare(self) -> None:
        h = self.arm._require()
        req = int(h.link["tare_req"]) + 1
        h.command(tare_req=req)
        if not h.wait(lambda: int(h.link["tare_done"]) == req, 5.0):
            raise TergodicError("the F/T sensor tare did not finish", "check the sensor's connection and retry")

    def disconnect(self) -> None:
        """The loop owns the sensor."""


class TorqueArm:
    """A torque-controlled arm run by a :class:`TorqueLoop`, for
    :class:`~tergodic_cli.backends.streamed.StreamedArm` (an ImpedanceArm that also takes line targets).

    Parameters
    ----------
    spec : the loop's :class:`LoopSpec`. name, joint_names, home, dq_max : the arm's.
    stream_hz : Hz at which the run sends commands (the loop runs at 1 / spec.dt).
    sensor_frame : (4, 4) the F/T sensor in the TCP frame. isolate : see :class:`LoopHandle`.
    """

    controller = "line impedance + wrench PID, 1 kHz torque loop"

    def __init__(self, spec: LoopSpec, name: str, joint_names, home, dq_max, sensor_frame=None,
                 stream_hz: float = 100.0, isolate: str = "process", reason: Callable[[str], str] | None = None):
        self.spec, self.name, self.joint_names = spec, name, list(joint_names)
        self.q_min, self.q_max = np.asarray(spec.q_min, float), np.asarray(spec.q_max, float)
        self.dq_max, self.home = np.asarray(dq_max, float), np.asarray(home, float)
        self.stream_hz, self.isolate = float(stream_hz), isolate
        self.sensor_frame = np.eye(4) if sensor_frame is None else np.asarray(sensor_frame, float)
        self.h: LoopHandle | None = None
        #: The F/T sensor as the run process reads it (through the loop).
        self.wrench_sensor = LoopSensor(self, self.sensor_frame)
        #: () -> TorqueDevice for a read-only arm (the dry run): connected here, never controlled.
        self.reader: Callable[[], object] | None = None
        self._dev = None
        self._reason = reason or (lambda msg: f"the arm's 1 kHz loop stopped: {msg}")
        self._pose = None  # the last pose command's gains, for the hold

    @property
    def is_connected(self) -> bool:
        return self.h is not None or self._dev is not None

    def connect(self) -> None:
        if self.is_connected:
            return
        if self.reader is not None:
            dev = self.reader()
            dev.connect()
            self._dev = dev
            return
        h = LoopHandle(self.spec, self.isolate)
        h.start()
        self.h = h

    def _require(self) -> LoopHandle:
        if self.h is None:
            raise TergodicError(f"the {self.name} is not connected", "call connect() first")
        return self.h

    def disconnect(self) -> None:
        if self._dev is not None:
            self._dev, dev = None, self._dev
            dev.close()
        if self.h is None:
            return
        try:
            self.stop()
        finally:
            self.h.close()
            self.h = None

    # ------------------------------------------------------------------ state
    def read_state(self) -> ArmState:
        if self._dev is not None:
            t, q, dq, T, J, *_ = self._dev.read()
            return ArmState(t, q, dq, T, J)
        s = self._require().state()
        return ArmState(float(s["t"]), np.array(s["q"]), np.array(s["dq"]), np.array(s["T"]), np.array(s["J"]))

    @property
    def measured_tau(self) -> np.ndarray:
        return np.array(self.h.link["tau_measured"]) if self.h is not None else np.zeros(len(self.joint_names))

    @property
    def last_tau(self) -> np.ndarray:
        """(n,) N m, the torque the loop sent last (Coriolis included, gravity added by the SDK)."""
        return np.array(self.h.link["tau"]) if self.h is not None else np.zeros(len(self.joint_names))

    def fault(self):
        """A :class:`~tergodic_cli.robot.safety.Fault` (lift) for the loop's force guard, a one-line
        reason for the SDK's own stop, else None."""
        from tergodic_cli.robot import kernels as Kn
        from tergodic_cli.robot.safety import Fault

        if self._dev is not None:
            return self._dev.errors() if hasattr(self._dev, "errors") else None
        h = self._require()
        code = int(h.link["fault"])
        if code == Kn.OK:
            return None
        if code == F_SDK:
            return self._reason(h.message())
        f = float(h.link["fault_force"])
        lim = float(h.link["fg"][Kn.FG_RAW if code == Kn.F_IMPACT else Kn.FG_LIMIT])
        what = "in one tick" if code == Kn.F_IMPACT else "low-passed"
        return Fault("force", "retreat", f"the 1 kHz loop saw a contact force of {f:.1f} N ({what}) over its "
                                         f"{lim:.1f} N limit; retreating", float(h.link["t"]))

    # ------------------------------------------------------------------ commands
    def bind(self, contact, guard) -> None:
        """The contact-wrench constants (a :class:`~tergodic_cli.robot.interfaces.ContactWrench`) and the
        force guard's limits (a :class:`~tergodic_cli.robot.safety.SafetyGuard`, its filter at the loop's rate)."""
        from tergodic_cli.robot import kernels as Kn

        fg = np.zeros(Kn.N_FG)
        if guard is not None:
            fg[Kn.FG_ALPHA] = Kn.lowpass_gain(guard.cfg.force_filter_hz, self.spec.dt)
            fg[Kn.FG_LIMIT], fg[Kn.FG_RAW] = guard.force_limit, guard.force_impact_limit
        self._require().command(R_se=contact.R_se_m, p_se=contact.p_se_v, mg=contact.mg, com=contact.com,
                                tare_load=contact.tare_load, fg=fg)

    def command_line(self, target: LineTarget, x_ref=None, threshold: float = 1.0, wrench=None) -> None:
        """The paper's controller on the line of ``target`` ("press": track ``force``; "move": along d at
        ``speed``, the approach's push servo capped by the contact ``threshold`` N), the tool's x-axis held
        near ``x_ref`` (3,) (base frame; None: as before); the law is
        :class:`~tergodic_cli.robot.controller.LineTargetLaw`, as in the simulation. ``wrench`` is unused:
        the loop reads the sensor itself at 1 kHz."""
        from tergodic_cli.robot import kernels as Kn

        if target.mode == "press":
            mode, speed = Kn.MODE_TRACK, 0.0
        else:
            mode = Kn.MODE_APPROACH if target.speed >= 0 else Kn.MODE_RETREAT
            speed = abs(float(target.speed))
        use = target.v_line is not None
        self._require().command(law=LAW_LINE, a=target.a, d=target.d, line_mode=mode, force=float(target.force),
                                speed=speed, use_vref=int(use), v_ref=target.v_line if use else np.zeros(3),
                                x_ref=np.zeros(3) if x_ref is None else x_ref, threshold=float(threshold))

    def command_impedance(self, target: ImpedanceTarget) -> None:
        """Hold (or track) a pose with the Cartesian impedance of ``target`` (set-up moves)."""
        self._require().command(law=LAW_POSE, pose=target.pose, K=target.stiffness, D=target.damping, twist=target.twist)

    def move_joints(self, q: np.ndarray, speed: float | None = None) -> None:
        """Blocking min-jerk joint move in joint impedance, at ``speed`` (0, 1] of the joints' speed limits."""
        from tergodic_cli.errors import require

        h = self._require()
        qd = np.asarray(q, dtype=float).reshape(len(self.joint_names))
        require(bool(np.all(qd >= self.q_min) and np.all(qd <= self.q_max)),
                f"joint target {np.round(qd, 3).tolist()} rad is outside the joint limits", "choose a reachable pose")
        f = 0.1 if speed is None else float(speed)
        require(0.0 < f <= 1.0, f"move speed {f} is not in (0, 1]", "e.g. 0.1")
        q0 = self.read_state().q
        duration = max(0.5, 1.875 * float(np.max(np.abs(qd - q0) / (f * self.dq_max))))  # min-jerk peak speed 1.875x mean
        t_end = float(h.link["t"]) + duration + 0.3
        h.command(law=LAW_JOINT, q_goal=qd, move_s=duration)
        ok = h.wait(lambda: float(h.link["t"]) >= t_end or int(h.link["fault"]) != 0, duration + 5.0)
        reason = self.fault()
        if reason is not None or not ok:  # (after the move the joint law holds the goal)
            raise TergodicError(f"the {self.name} stopped during a joint move: {getattr(reason, 'reason', reason) or 'time-out'}",
                                "check the workspace for obstacles, recover the robot in Desk and retry")

    def stop(self) -> None:
        """End torque control (the SDK holds the arm at rest)."""
        h = self._require()
        h.command(law=LAW_NONE)
        h.wait(lambda: not (h.loop.active if h.loop is not None else False), 0.05)  # inline: let the loop finish
