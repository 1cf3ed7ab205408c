"""tergodic: tactile ergodic control on coloured point clouds.

Data flows one way: cloud -> basis -> explorer -> robot -> log.
Heavy libraries (open3d, pybullet, robust_laplacian) are imported only inside
the functions that need them, so ``import tergodic_cli`` stays cheap.
"""

__version__ = "0.1.0"

#: Bumped whenever an on-disk artefact layout changes; part of every cache key.
FORMAT_VERSION = 1
