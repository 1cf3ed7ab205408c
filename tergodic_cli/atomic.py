"""Atomic file writes: write to a temporary file beside the target, then rename.

A crash or an error half-way never leaves a partial artefact behind.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np

# os_cause: one wording of the OS's causes, for every verb
from tergodic_cli.errors import TergodicError, os_cause, require


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it over ``target`` on success."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix + ".tmp", dir=target.parent)
    except OSError as exc:
        raise _file_error(exc, target) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; artefacts are ordinary files
        os.replace(tmp_path, target)
    except BaseException as exc:
        tmp_path.unlink(missing_ok=True)
        if isinstance(exc, OSError):  # one line, not a traceback
            raise _file_error(exc, target) from None
        raise


def _file_error(exc: OSError, target: Path):
    return TergodicError(f"cannot write {target}: {os_cause(exc)}",
                         ("free space, or " if _full(exc) else "") + "check the path and its permissions")


def check_output_file(path: str | os.PathLike, overwrite: bool, option: str, inputs=()) -> None:
    """Refuse, before any work, an output file that is a folder, not a regular file (a FIFO, a
    device), one of the command's ``inputs``, lies under a file, sits in a folder we cannot write,
    or exists without ``overwrite`` (it is then written atomically).

    Parameters
    ----------
    path : path-like
        The output file.
    overwrite : bool
        An existing regular file may be replaced.
    option : str
        The option that names it, for the one-line error.
    inputs : iterable of path-like
        The command's input files; the output may be none of them.
    """
    shown = Path(path)
    target = Path(os.path.abspath(path))
    require(not target.is_dir(), f"{option} {shown} is a folder, not a file", f"choose another {option}")
    kind = special_kind(target)
    require(kind is None, f"{option} {shown} is a {kind}, not a regular file", f"choose another {option}")
    for src in inputs:
        require(not same_file(target, src), f"{option} {shown} is the command's own input {src}",
                f"choose another {option}")
    check_parent_writable(target, shown, option)
    require(overwrite or not target.exists(), f"{option} {shown} already exists",
            f"pass --overwrite to replace it, or choose another {option}")


def special_kind(path: Path) -> str | None:
    """What an existing ``path`` is when it is neither a regular file nor a folder (a link is followed).

    Parameters
    ----------
    path : Path

    Returns
    -------
    str or None
        "FIFO", "socket" or "device node"; None otherwise (also when it does not exist).
    """
    import stat

    try:
        mode = os.stat(path).st_mode
    except OSError:
        return None
    if stat.S_ISFIFO(mode):
        return "FIFO"
    if stat.S_ISSOCK(mode):
        return "socket"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "device node"
    return None


def same_file(a, b) -> bool:
    """Whether ``a`` and ``b`` name the same file.

    Parameters
    ----------
    a, b : path-like

    Returns
    -------
    bool
        The same absolute path, or the same inode (through a link); False when one is missing.
    """
    if os.path.abspath(a) == os.path.abspath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_parent_writable(target: Path, shown, option: str) -> None:
    """Refuse, before any work, a ``target`` whose nearest existing ancestor is a file or a
    folder we may not write into (also for root on a read-only filesystem). ``option`` names
    the flag to change."""
    parent = Path(os.path.abspath(target)).parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    require(parent.is_dir(), f"{option} {shown} is under {parent}, which is a file, not a folder", f"choose another {option}")
    if not os.access(parent, os.W_OK | os.X_OK):
        ro = bool(os.statvfs(parent).f_flag & os.ST_RDONLY)
        raise TergodicError(f"cannot write {option} {shown}: {'read-only filesystem' if ro else 'permission denied'}"
                            f" at {parent}", f"choose another {option}")


def file_sha256(path: str | os.PathLike) -> str:
    """sha256 of a file's bytes."""
    with open(path, "rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(target: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, default=_json_default) + "\n")


def write_npz(dest: str | os.PathLike, **arrays: np.ndarray) -> None:
    """Write arrays to an uncompressed ``.npz``, atomically (no pickled objects)."""
    with atomic_path(dest, suffix=".npz") as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, (np.generic, np.ndarray)):  # numpy scalars' tolist() is their item()
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


# ------------------------------------------------------------------------------ whole folders
def _full(exc: BaseException) -> bool:
    return isinstance(exc, OSError) and os_cause(exc) in ("no space left on device", "disk quota exceeded")


class AtomicFolder:
    """Build a folder in a temporary sibling (``.NAME.tmp-XXXX``) and rename it into place when complete.

    ``check()`` refuses, before any work, a target that is a file, lies under a file, sits in a
    folder we cannot write, already holds files without ``overwrite``, or is being written by
    another process: it takes a lock (``flock`` on ``.NAME.lock`` beside the target) that is held
    until the folder is renamed in or dropped (:meth:`release`). An existing folder is replaced
    whole (moved aside, the new one renamed in, the old one removed), never merged, and only by a
    complete new one: a body that sets ``partial`` (a run stopped by a robot fault or an interrupt
    absorbed by the robot's safe stop) or is left by Ctrl-C/SIGTERM with ``keep_partial`` puts what
    it built beside the old one (``NAME.partial-TIME``, ``NAME.interrupted-TIME``, in ``placed``);
    with no old one it goes into place. On any other error the temporary folder is removed and an
    operating-system error becomes one line (:class:`TergodicError`).
    """

    def __init__(self, target: str | os.PathLike, overwrite: bool = False, option: str = "--out",
                 what: str = "folder", keep_partial: bool = False, owned=None):
        #: ``owned(name)``: whether an entry may be in a folder of this kind; --overwrite replaces
        #: only such a folder (never, say, a home folder given as --out by mistake)
        self.owned = owned
        self.shown = Path(target)
        self.target = Path(os.path.abspath(target))
        self.overwrite, self.option, self.what, self.keep_partial = overwrite, option, what, keep_partial
        self.tmp: Path | None = None
        self.kept = False
        #: set by the body: "partial" or "interrupted" when what it built is not a complete artefact
        self.partial: str | None = None
        #: where the folder went: the target, or beside it when an old one was kept
        self.placed: Path | None = None
        self._created: list[Path] = []
        self._lock_fd: int | None = None

    @property
    def lock_path(self) -> Path:
        return self.target.parent / f".{self.target.name}.lock"

    def check(self, renamed: bool = True) -> None:
        """``renamed=False``: only the checks of a folder written into in place (a resumable sweep).
        Takes the target's lock (kept until :meth:`release`)."""
        shown, target, opt = self.shown, self.target, self.option
        other = f"choose another {opt}"
        if renamed and os.path.commonpath([str(target), os.getcwd()]) == str(target):  # renaming would pull it from under us
            raise TergodicError(f"{opt} {shown} is the current folder or holds it", f"give {opt} a folder of its own")
        if target.is_symlink() or (target.exists() and not target.is_dir()):  # a link would be replaced, not followed
            kind = "symbolic link" if target.is_symlink() else special_kind(target) or "file"
            raise TergodicError(f"{opt} {shown} is a {kind}, not a folder", other)
        check_parent_writable(target, shown, opt)
        if target.is_dir() and not os.access(target, os.W_OK | os.X_OK):
            raise TergodicError(f"cannot write {opt} {shown}: permission denied or read-only filesystem", other)
        self._lock()
        try:
            if target.is_dir() and renamed:
                self._check_contents(other)
        except BaseException:
            self.release()
            raise

    def _check_contents(self, other: str) -> None:
        shown, opt = self.shown, self.option
        try:
            names = sorted(p.name for p in self.target.iterdir())
        except OSError as exc:
            raise TergodicError(f"cannot read {opt} {shown}: {os_cause(exc)}", other) from None
        foreign = [n for n in names if self.owned is not None and not self.owned(n)]
        if foreign:
            raise TergodicError(f"{opt} {shown} holds files that are not a {self.what}'s ({foreign[0]}"
                                f"{', ...' if len(foreign) > 1 else ''})", f"{other}; only a {self.what} is replaced")
        if names and not self.overwrite:
            raise TergodicError(f"{opt} {shown} already holds a {self.what}",
                                f"pass --overwrite to replace it, or {other}")

    # -------------------------------------------------------------------------- the lock
    def _lock(self) -> None:
        """Take ``.NAME.lock`` beside the target (its parents are made, and removed again on failure)."""
        import fcntl

        if self._lock_fd is not None:
            return
        try:
            for parent in reversed(self.target.parents):  # remember what we create, to remove it on failure
                if not parent.exists():
                    parent.mkdir()
                    self._created.append(parent)
            while True:
                fd = os.open(self.lock_path, os.O_RDWR | os.O_CREAT, 0o666)
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    os.close(fd)
                    self._remove_created()
                    raise TergodicError(f"{self.option} {self.shown} is being written by another tergodic process "
                                        f"(it holds {self.lock_path.name})",
                                        f"wait for it to finish, or choose another {self.option}") from None
                try:  # the holder before us may have removed the file after we opened it: lock the one in place
                    if os.fstat(fd).st_ino == os.stat(self.lock_path).st_ino:
                        break
                except FileNotFoundError:
                    pass
                os.close(fd)
        except OSError as exc:
            self._remove_created()
            raise self._error(exc) from None
        self._lock_fd = fd

    def release(self) -> None:
        """Drop the lock (the lock file is removed while still held, so no writer locks a stale one)
        and the parents made for a folder that was never placed. Idempotent."""
        if self._lock_fd is not None:
            with contextlib.suppress(OSError):
                self.lock_path.unlink()
            os.close(self._lock_fd)
            self._lock_fd = None
        if self.placed is None:
            self._remove_created()

    def leftovers(self) -> list[Path]:
        """Temporary siblings (``.NAME.tmp-*``) left by a run that was killed (SIGKILL, power loss):
        with the lock held, no live process is building them."""
        with contextlib.suppress(OSError):
            return sorted(p for p in self.target.parent.glob(f".{self.target.name}.tmp-*") if p != self.tmp)
        return []

    # -------------------------------------------------------------------------- building
    def __enter__(self) -> Path:
        self.check()
        try:
            self.tmp = Path(tempfile.mkdtemp(prefix=f".{self.target.name}.tmp-", dir=self.target.parent))
        except OSError as exc:
            self._discard()
            self.release()
            raise self._error(exc) from None
        return self.tmp

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            return self._exit(exc_type, exc)
        finally:
            self.release()

    def _exit(self, exc_type, exc) -> bool:
        if exc_type is None:
            try:
                self._place(self.partial)
            except OSError as err:
                self._discard()
                raise self._error(err) from None
            return False
        if issubclass(exc_type, KeyboardInterrupt) and self.keep_partial and self.tmp is not None:
            with contextlib.suppress(OSError):  # keep the interrupt; the partial folder is lost
                if any(self.tmp.iterdir()):
                    self._place("interrupted")
                    self.kept = True
                    return False
        tmp = str(self.tmp) if self.tmp is not None else None
        # a write into our folder that failed on a full disk: looked at before the discard frees the space
        ours = isinstance(exc, TergodicError) and tmp is not None and tmp in str(exc)
        full = _full(exc) if isinstance(exc, OSError) else (ours and self._disk_full())
        self._discard()

        if isinstance(exc, OSError) or (full and isinstance(exc, TergodicError)):
            raise self._error(exc, full) from None
        if ours:  # name the folder, not its temporary sibling
            raise TergodicError(exc.problem.replace(tmp, str(self.shown)),
                                exc.fix.replace(tmp, str(self.shown)) if exc.fix else None) from None
        return False

    def _disk_full(self) -> bool:
        try:
            return shutil.disk_usage(self.target.parent).free < (1 << 20)
        except OSError:
            return False

    def _old_exists(self) -> bool:
        try:
            return self.target.is_dir() and any(self.target.iterdir())
        except OSError:
            return True

    def _place(self, partial: str | None) -> None:
        """Rename the built folder into place, or beside an old one it must not replace."""
        assert self.tmp is not None
        os.chmod(self.tmp, 0o777 & ~_umask())  # mkdtemp makes 0700; an artefact is an ordinary folder
        if partial and self._old_exists():
            stamp = time.strftime("%Y%m%d-%H%M%S")
            beside = self.target.with_name(f"{self.target.name}.{partial}-{stamp}")
            n = 1
            while beside.exists() or beside.is_symlink():  # under our lock: no other tergodic takes the name
                n += 1
                beside = self.target.with_name(f"{self.target.name}.{partial}-{stamp}-{n}")
            os.rename(self.tmp, beside)
            self.tmp, self.placed = None, beside
            return
        self._swap_in()
        self.placed = self.target

    def _swap_in(self) -> None:
        assert self.tmp is not None
        target = self.target
        if target.exists():  # move the old one aside, put the new one in place, then drop the old
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, old / target.name)
            try:
                os.replace(self.tmp, target)
            except BaseException:
                os.replace(old / target.name, target)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(self.tmp, target)
        self.tmp = None

    def _discard(self) -> None:
        if self.tmp is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            self.tmp = None
        if self._lock_fd is None:
            self._remove_created()

    def _remove_created(self) -> None:
        for parent in reversed(self._created):
            with contextlib.suppress(OSError):
                parent.rmdir()
        self._created = []

    def _error(self, exc: BaseException, full: bool | None = None):
        full = _full(exc) if full is None else full
        cause = "no space left on device" if full else os_cause(exc)
        return TergodicError(f"cannot write the {self.what} {self.shown}: {cause}",
                             ("free space or " if full else "") + f"choose another {self.option}")


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an RGB image (h, w, 3) in [0, 1] as a PNG, atomically."""
    from PIL import Image

    with atomic_path(path, suffix=".png") as tmp:
        Image.fromarray(np.clip(np.rint(rgb * 255), 0, 255).astype(np.uint8)).save(tmp, format="PNG")
