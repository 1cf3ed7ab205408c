"""The diffusion time step (eq. 21) and the implicit baseline (M + δt L)⁻¹ M on full (n,) fields.

The :class:`~tergodic_cli.explore.explorer.Explorer` keeps the spectral form (eq. 19) in its coefficients.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp


#: Reference spacing h₀ of δt = α h₀² (metres): the mean spacing of a 3 mm voxel grid, where the
#: paper's α was tuned. A fixed length (not the cloud's own h) makes α mean the same diffusion on
#: any sampling of an object (docs/explore.md).
H0 = 0.0025


def time_step(alpha: float) -> float:
    """The diffusion time step δt = α h₀² (eq. 21 with a fixed reference spacing h₀ = :data:`H0`).

    Parameters
    ----------
    alpha : float
        The diffusion scalar α.

    Returns
    -------
    float
        δt, m².
    """
    return float(alpha) * H0 ** 2


class ImplicitDiffusion:
    """(M + δt L)⁻¹ M, the exact (untruncated) backward-Euler baseline, factorised once."""

    def __init__(self, L: sp.spmatrix, mass: np.ndarray, dt: float):
        from scipy.sparse.linalg import splu

        self.mass = mass
        # M + δt L is symmetric positive definite: a symmetric fill-reducing ordering and no
        # pivoting roughly halve the factor's fill (and the per-step solve) against COLAMD.
        self._lu = splu((sp.diags(mass) + float(dt) * L).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                        options={"SymmetricMode": True})

    def apply(self, u: np.ndarray) -> np.ndarray:
        """One implicit step.

        Parameters
        ----------
        u : (n,) float

        Returns
        -------
        (n,) float
            (M + δt L)⁻¹ M u.
        """
        return self._lu.solve(self.mass * u)
