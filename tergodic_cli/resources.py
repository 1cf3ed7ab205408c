"""What the machine has free, for the guards that refuse work that cannot fit (issue 27)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path


def free_memory() -> int | None:
    """Physical memory free now, bytes; None where the OS does not say (then nothing is refused)."""
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def free_disk(path: str | os.PathLike) -> int | None:
    """Bytes free on the disk that holds ``path`` (or its nearest existing parent); None if none exists."""
    p = Path(path).resolve()
    parent = next((q for q in (p, *p.parents) if q.exists()), None)
    return None if parent is None else shutil.disk_usage(parent).free
