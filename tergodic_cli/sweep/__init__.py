"""Parameter sweeps over objects x starts x nK x alpha (x any explore option), locally (joblib)
or on a Ray cluster, through one code path; resumable; one results table and paper-style plots.

Entry points: :func:`load_grid` (GRID.toml, format in :mod:`tergodic_cli.sweep.grid`) and
:func:`run_sweep` (the whole ``tergodic sweep``).
"""

from tergodic_cli.sweep.grid import Grid, load_grid
from tergodic_cli.sweep.runner import ENGINES, SweepResult, read_table, run_sweep

__all__ = ["ENGINES", "Grid", "SweepResult", "load_grid", "read_table", "run_sweep"]
