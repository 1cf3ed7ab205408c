"""Export a run's time series as ``.npz`` or ``.csv`` (one row per step, float64 as logged).

The columns (and the csv's flattened vectors) are listed in docs/logging.md (``--export``).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from tergodic_cli.atomic import atomic_path, write_npz
from tergodic_cli.errors import TergodicError
from tergodic_cli.runlog.reader import RunLogData

FORMATS = ("npz", "csv")


def export_series(data: RunLogData, fmt: str, dest: str | os.PathLike) -> Path:
    """Write the series to ``dest`` in ``fmt`` (npz or csv), atomically; returns ``dest``."""
    if fmt not in FORMATS:
        raise TergodicError(f"--export '{fmt}' is not a format", "use --export npz or --export csv")
    dest = Path(dest)
    table = {k: v for k, v in data.series.items() if v.dtype != object}  # first axis = step
    table.update({f"robot_{k}": v.astype(np.float64) if v.dtype == bool else v
                  for k, v in data.robot_series().items()
                  if len(v) == data.steps and v.dtype != object})
    if fmt == "npz":
        write_npz(dest, **table)
        return dest
    header, cols = [], []
    for k, v in table.items():  # (T,) one column, (T, k) k columns, (T, N, 3) per agent x y z
        if v.ndim > 3 or (v.ndim == 3 and v.shape[2] != 3):
            continue
        header += ([k] if v.ndim == 1 else [f"{k}_{j}" for j in range(v.shape[1])] if v.ndim == 2
                   else [f"{k}_{a}_{c}" for a in range(v.shape[1]) for c in "xyz"])
        cols += list(v.reshape(len(v), -1).T)
    with atomic_path(dest, suffix=".csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            w.writerows([_cell(c[i]) for c in cols] for i in range(data.steps))
    return dest


def _cell(x) -> str:
    if isinstance(x, (np.floating, float)):
        return repr(float(x))  # shortest exact form: the csv round-trips float64
    return str(x)  # integers (numpy's print as Python's)
