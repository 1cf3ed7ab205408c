"""The basis stage's configuration (standard library only: the verbs build their options from it at start-up)."""

from __future__ import annotations

from dataclasses import dataclass, field

from tergodic_cli.config import Config, option

#: The eigensolvers a basis can name (the one :func:`~tergodic_cli.basis.eigensolvers.smallest_eigenpairs` runs).
SOLVERS = ("lanczos-interior-shift",)


@dataclass(frozen=True)
class BasisConfig(Config):
    """Parameters of a basis; all of them are part of the cache key. Saved as the entry's ``config.json``.

    nk : number of eigenpairs. neighbors : neighbours of the robust Laplacian.
    solver : the eigensolver (:func:`~tergodic_cli.basis.eigensolvers.smallest_eigenpairs`).
    """

    nk: int = field(default=200, metadata=option(
        "--nk", "Number of eigenpairs nK (paper: 100 is a good trade-off, 200 the best)."))
    neighbors: int = field(default=30, metadata=option(
        "--neighbors", "Neighbours for robust_laplacian. 40 bridges scan gaps (the bunny's ear joins the body)."))
    solver: str = "lanczos-interior-shift"
