"""The footprint and the source term: one definition each, for the explorer, the metric and the robot.

- The footprint (eq. 30) of an agent or a contact at distance r from a point is φ(r) = exp(-ε² r²),
  with ε = 2 / r_a by default (:func:`~tergodic_cli.explore.config.footprint_epsilon`): the disc
  r <= r_a holds 98 % of the Gaussian's mass.
- The source term (eq. 1) is s = max(p̄ - c̄, 0)² with p̄ the target and c̄ the coverage, each
  normalised (eq. 2); :func:`residual` is its square root, max(p̄ - c̄, 0), which the footprint
  gain weighs.

They are numba functions, callable from the compiled kernels (:mod:`~tergodic_cli.explore.kernels`,
where the explorer deposits the footprint, a robot's contacts included, and scores a trajectory)
and from NumPy code alike: on scalars or on arrays (:func:`~tergodic_cli.explore.metrics.source_term`).
"""

from __future__ import annotations

import numba
import numpy as np

from tergodic_cli.explore.config import FOOTPRINT_EPS_RA, footprint_epsilon

__all__ = ["FOOTPRINT_EPS_RA", "footprint", "footprint_epsilon", "residual", "source"]


@numba.njit(cache=True, nogil=True)
def footprint(eps2, r2):
    """φ = exp(-ε² r²) (eq. 30).

    Parameters
    ----------
    eps2 : float
        ε², 1/m².
    r2 : float or ndarray
        Squared distance r², m² (tangent-plane or 3-D, as the caller measures it).

    Returns
    -------
    float or ndarray
        φ in (0, 1], unitless; the shape of ``r2``.
    """
    return np.exp(-eps2 * r2)


@numba.njit(cache=True, nogil=True)
def residual(pbar, cbar):
    """e = max(p̄ - c̄, 0): the target density the coverage has not yet met.

    Parameters
    ----------
    pbar, cbar : float or ndarray
        Normalised target and coverage (1/m² on the surface, or unitless in plain sums).

    Returns
    -------
    float or ndarray
        e >= 0, in the units of ``pbar``.
    """
    return np.maximum(pbar - cbar, 0.0)


@numba.njit(cache=True, nogil=True)
def source(pbar, cbar):
    """s = max(p̄ - c̄, 0)² (eq. 1).

    Parameters
    ----------
    pbar, cbar : float or ndarray
        Normalised target and coverage.

    Returns
    -------
    float or ndarray
        s >= 0, the square of ``pbar``'s units.
    """
    e = residual(pbar, cbar)
    return e * e
