"""The geometry basis: robust Laplacian L, lumped mass M, the smallest nK eigenpairs of
L φ = λ M φ, the spacing h and a KD-tree, cached on disk by geometry content.

Entry point: :func:`get_basis`.
"""

from tergodic_cli.basis.config import BasisConfig


def __getattr__(name):  # the solver pulls in scipy and robust_laplacian: load on first use
    if name == "get_basis":
        from tergodic_cli.basis.cache import get_basis

        return get_basis
    if name in ("Basis", "compute_basis"):
        from tergodic_cli.basis import core

        return getattr(core, name)
    raise AttributeError(name)


__all__ = ["Basis", "BasisConfig", "compute_basis", "get_basis"]
