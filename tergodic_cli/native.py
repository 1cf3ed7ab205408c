"""Long native calls that still answer Ctrl-C and SIGTERM within a second (issue 27).

Python runs a signal handler only when the main thread is between bytecodes, so a native call of
many seconds on the main thread delays Ctrl-C until it returns. Two ways round it, chosen by what
the call does with the GIL:

- :func:`in_thread`: the call releases the GIL (qdldl's LDLᵀ factorisation, scipy's SuperLU):
  it runs in a worker thread while the main thread waits in 0.1 s steps, so the handlers run at once.
  An interrupted worker is left to finish on its own (a daemon thread; the process is exiting).
- :func:`in_fork`: the call holds the GIL (open3d's Poisson reconstruction and decimation):
  it runs in a forked child that is killed when the wait is interrupted. A fork starts in
  milliseconds with the parent's modules and arrays (a fresh interpreter would spend 2-6 s importing
  open3d); the results come back as ``.npy`` files read with ``allow_pickle=False`` (never a pickle),
  an error as one JSON line.

robust_laplacian has its own child, started as a fresh interpreter (``basis/_laplacian_child.py``).
docs/speed.md, "Ctrl-C during long native calls", has the measured answer times.
"""

from __future__ import annotations

import json
import os
import signal
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, TypeVar

import numpy as np

from tergodic_cli.errors import TergodicError

T = TypeVar("T")

#: How often the waiting main thread wakes up to let the signal handlers run, seconds.
POLL_S = 0.05
#: Name prefix of :func:`in_thread`'s workers.
WORKER = "tergodic-native-"


def may_exit_now() -> bool:
    """Whether an interrupted console script may end with ``os._exit``, skipping the interpreter's
    teardown: no child process is alive (a sweep's pool and its resource tracker are shut down at
    exit) and no thread but the main one, the daemons and :func:`in_thread`'s workers is running."""
    import multiprocessing
    import sys

    if multiprocessing.active_children():
        return False
    tasks = Path("/proc/self/task")
    if tasks.is_dir():
        try:
            if any((t / "children").read_text().strip() for t in tasks.iterdir()):
                return False
        except OSError:
            return False
    elif "joblib" in sys.modules or "ray" in sys.modules:  # no /proc to see their processes by
        return False
    main = threading.main_thread()
    return all(t is main or t.daemon or not t.is_alive() for t in threading.enumerate())


def in_thread(fn: Callable[..., T], *args, **kwargs) -> T:
    """``fn(*args, **kwargs)`` in a worker thread, the main thread waiting in short steps.

    Only worth it for a call that releases the GIL. Off the main thread (no signal handlers run
    there anyway) the call is made directly.

    Parameters
    ----------
    fn : callable
        The native call. args, kwargs : its arguments.

    Returns
    -------
    What ``fn`` returns; what it raises is raised here.
    """
    if threading.current_thread() is not threading.main_thread():
        return fn(*args, **kwargs)
    box: dict = {}
    done = threading.Event()

    def work() -> None:
        try:
            box["value"] = fn(*args, **kwargs)
        except BaseException as exc:  # noqa: BLE001  (handed to the waiting thread)
            box["error"] = exc
        finally:
            done.set()

    worker = threading.Thread(target=work, name=f"{WORKER}{getattr(fn, '__name__', 'call')}", daemon=True)
    worker.start()
    # An Event, not join(): a join interrupted by a signal marks the worker stopped while it still runs.
    # A KeyboardInterrupt/Terminated raised here leaves the worker to finish alone.
    while not done.wait(POLL_S):
        pass
    if "error" in box:
        raise box.pop("error")
    return box["value"]


def in_fork(fn: Callable[[], dict[str, np.ndarray]], what: str) -> dict[str, np.ndarray]:
    """``fn()`` in a forked child, killed (SIGKILL) if the wait is interrupted.

    Parameters
    ----------
    fn : callable returning {name: array}
        Runs in the child; plain numeric or string arrays (saved as ``.npy``, no objects). A
        :class:`TergodicError` it raises is raised again here with its problem and fix.
    what : str
        The work's name in the message when the child dies without an answer (e.g. killed for memory).

    Returns
    -------
    dict of name -> array
        As ``fn`` returned them.
    """
    if not hasattr(os, "fork"):
        return fn()
    with tempfile.TemporaryDirectory(prefix="tergodic-native-") as tmp:
        folder = Path(tmp)
        pid = os.fork()
        if pid == 0:  # the child: never returns into the parent's code, never flushes its buffers
            code = 1
            try:
                signal.signal(signal.SIGINT, signal.SIG_DFL)  # the parent answers signals; the child just dies
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
                out = fn()
                for name, arr in out.items():
                    np.save(folder / f"{name}.npy", np.asarray(arr))
                (folder / "names.json").write_text(json.dumps(list(out)))
                code = 0
            except TergodicError as exc:
                (folder / "error.json").write_text(json.dumps({"problem": exc.problem, "fix": exc.fix}))
            except BaseException as exc:  # noqa: BLE001  (reported by the parent in one line)
                text = str(exc).splitlines()[0][:160] if str(exc) else ""
                (folder / "error.json").write_text(json.dumps({"problem": f"{what} failed ({type(exc).__name__}"
                                                                          f"{': ' + text if text else ''})"}))
            finally:
                os._exit(code)
        try:
            while True:
                done, status = os.waitpid(pid, os.WNOHANG)
                if done:
                    break
                time.sleep(POLL_S)
        except BaseException:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            raise
        if (folder / "error.json").exists():
            err = json.loads((folder / "error.json").read_text())
            raise TergodicError(err["problem"], err.get("fix"))
        if not os.WIFEXITED(status) or os.WEXITSTATUS(status) != 0 or not (folder / "names.json").exists():
            cause = (f"killed by signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status)
                     else f"exit {os.WEXITSTATUS(status)}")
            raise TergodicError(f"{what} failed in its process ({cause})",
                                "check free memory, or voxel the capture more coarsely")
        names = json.loads((folder / "names.json").read_text())
        return {name: np.load(folder / f"{name}.npy", allow_pickle=False) for name in names}
