"""Heat diffusion on the point cloud: spectral (eq. 19) and the implicit baseline.

Both operate on full (n,) fields with the basis' weak Laplacian L and lumped mass M, with
Neumann boundaries implicit in L (its rows sum to zero), so ∫u = Σ M u is conserved.

- Spectral (eq. 19): u(t + δt) = Φ (e^{-λ δt} ⊙ Φᵀ M u(t)), δt = α h₀² (eq. 21, h₀ fixed).
- Implicit: one backward-Euler step u(t + δt) = (M + δt L)⁻¹ M u(t), factorised once per δt.

The :class:`~tergodic_cli.explore.explorer.Explorer` uses a reduced form of the spectral
operator (it keeps spectral coefficients and evaluates the field only where needed).
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


class SpectralDiffusion:
    """e^{-δt L} in the truncated eigenbasis Φ (n, nK) with eigenvalues λ (nK,)."""

    def __init__(self, evecs: np.ndarray, evals: np.ndarray, mass: np.ndarray, dt: float):
        self.evecs, self.evals, self.mass = evecs, evals, mass
        self.set_dt(dt)

    def set_dt(self, dt: float) -> None:
        """Change the time step.

        Parameters
        ----------
        dt : float
            δt, m².
        """
        self.dt = float(dt)
        self.decay = np.exp(-self.evals * self.dt)

    def coefficients(self, u: np.ndarray) -> np.ndarray:
        """Spectral coefficients Φᵀ M u.

        Parameters
        ----------
        u : (n,) float
            A field on the cloud.

        Returns
        -------
        (nK,) float
        """
        return self.evecs.T @ (self.mass * u)

    def apply(self, u: np.ndarray) -> np.ndarray:
        """One step of eq. 19.

        Parameters
        ----------
        u : (n,) float

        Returns
        -------
        (n,) float
            Φ e^{-λδt} Φᵀ M u.
        """
        return self.evecs @ (self.decay * self.coefficients(u))

    def kernel(self, i: int, t: float | None = None) -> np.ndarray:
        """Heat kernel k_t(·, x_i): the field at time ``t`` from a unit mass at point i.

        Parameters
        ----------
        i : int
            Point index.
        t : float, optional
            m²; default δt.

        Returns
        -------
        (n,) float
        """
        decay = self.decay if t is None else np.exp(-self.evals * float(t))
        return self.evecs @ (decay * self.evecs[i])


class ImplicitDiffusion:
    """(M + δt L)⁻¹ M, the exact (untruncated) backward-Euler baseline, factorised once."""

    def __init__(self, L: sp.spmatrix, mass: np.ndarray, dt: float):
        from scipy.sparse.linalg import splu

        self.mass = mass
        self.dt = float(dt)
        # M + δt L is symmetric positive definite: a symmetric fill-reducing ordering and no
        # pivoting roughly halve the factor's fill (and the per-step solve) against COLAMD.
        self._lu = splu((sp.diags(mass) + self.dt * L).tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
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
