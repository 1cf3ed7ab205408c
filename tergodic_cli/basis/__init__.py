"""The geometry basis: robust Laplacian L, lumped mass M, the smallest nK eigenpairs of
L φ = λ M φ, the spacing h and a KD-tree, cached on disk by geometry content.

Entry point: :func:`get_basis`.
"""

from tergodic_cli.basis.cache import BasisConfig, get_basis
from tergodic_cli.basis.core import Basis, compute_basis

__all__ = ["Basis", "BasisConfig", "compute_basis", "get_basis"]
