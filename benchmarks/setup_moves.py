"""Contact and clearance during the set-up moves of a simulated robot run (issue 24, item 3).

Two sub-commands, so the same measurement runs against any version of the code:

    python benchmarks/setup_moves.py run CAPTURE OUT.npz [explore options...]
        runs ``tergodic explore CAPTURE --robot pybullet ...`` in this process and records, every
        physics tick outside the approach and exploring (picture, hover, retreat: the set-up moves),
        the joints, the state and the summed normal force of every contact between the robot and any
        other body; prints the exit code, the peak force and where it happened.
    python benchmarks/setup_moves.py clearance OUT.npz
        replays the recorded joints in the collision check of this code (plan.CollisionWorld, every link
        with its collision shape) against the run's object and prints the smallest distance per state.

The object's mesh and pose are saved with the joints (the run's own, whatever code made it).
"""

from __future__ import annotations

import _env  # noqa: F401  (first: BLAS threads, sys.path)

import os
import sys

# Off the path again: numba imports ``coverage`` when it is there, and benchmarks/coverage.py is not it.
sys.path[:] = [p for p in sys.path if os.path.abspath(p or os.curdir) != os.path.dirname(os.path.abspath(__file__))]

import numpy as np

SETUP = ("picture", "hover", "retreat")


def run(capture: str, out: str, args: list[str]) -> None:
    import tergodic_cli.backends.pybullet.arm as A
    import tergodic_cli.robot.statemachine as S
    from tergodic_cli.cli import main

    rec = {"q": [], "state": [], "force": [], "t": []}
    state = {"now": S.PICTURE, "arm": None}
    go = S.StateMachine.go

    def tracked_go(self, target, *a, **k):
        state["now"] = target
        return go(self, target, *a, **k)

    S.StateMachine.go = tracked_go
    physics = A.SimArm._physics

    def recorded(self):
        physics(self)
        state["arm"] = self
        if state["now"] in SETUP:
            sc = self.scene
            p, cid = sc.p, sc.cid
            f = sum(c[9] for c in p.getContactPoints(sc.robot, physicsClientId=cid) if c[2] != sc.robot)
            rec["q"].append([s[0] for s in p.getJointStates(sc.robot, sc.arm_joints, physicsClientId=cid)])
            rec["state"].append(state["now"])
            rec["force"].append(f)
            rec["t"].append(sc.t)

    A.SimArm._physics = recorded
    init = A.SimArm.__init__

    def keep(self, cfg, mesh, T_mesh):
        init(self, cfg, mesh, T_mesh)
        state["arm"] = self

    A.SimArm.__init__ = keep
    code = main(["explore", capture, "--robot", "pybullet", *args])
    arm = state["arm"]
    sc = arm.scene

    T = sc.object_pose
    f = np.asarray(rec["force"])
    np.savez(out, q=np.asarray(rec["q"]), state=np.asarray(rec["state"]), force=f, t=np.asarray(rec["t"]),
             vertices=np.asarray(arm.mesh.vertices), triangles=np.asarray(arm.mesh.triangles), T_mesh=T,
             exit_code=code)
    if len(f):
        i = int(np.argmax(f))
        print(f"exit {code}; set-up ticks {len(f)}; peak contact force {f[i]:.1f} N at t = {rec['t'][i]:.3f} s "
              f"({rec['state'][i]}); ticks with contact {int(np.sum(f > 0))}")
    else:
        print(f"exit {code}; no set-up tick ran")


def clearance(path: str) -> None:
    from tergodic_cli.backends.pybullet.plan import CollisionWorld
    from tergodic_cli.backends.pybullet.scene import PyBulletScene

    d = np.load(path, allow_pickle=False)
    if len(d["q"]) == 0:
        print("no set-up tick recorded")
        return
    sc = PyBulletScene()
    sc.add_object(d["vertices"], d["triangles"], d["T_mesh"])
    w = CollisionWorld(sc)
    states = d["state"]
    for s in SETUP:
        idx = np.flatnonzero(states == s)[::10]
        if len(idx) == 0:
            continue
        res = [w.clearance(d["q"][i]) for i in idx]
        j = int(np.argmin([r[0] for r in res]))
        far = "" if res[j][1] else ">= "  # nothing within clearance()'s reach
        print(f"{s}: {len(idx)} postures (every 10th tick); smallest distance {far}{1e3 * res[j][0]:.1f} mm "
              f"({res[j][1] or 'no link nearer'})")
    w.close()
    sc.close()


if __name__ == "__main__":
    if len(sys.argv) < 3 or sys.argv[1] not in ("run", "clearance"):
        sys.exit(__doc__)
    if sys.argv[1] == "run":
        run(sys.argv[2], sys.argv[3], sys.argv[4:])
    else:
        clearance(sys.argv[2])
