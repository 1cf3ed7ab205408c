"""tergodic: tactile ergodic control on coloured point clouds.

Data flows one way: cloud -> basis -> explorer -> robot -> log.
Heavy libraries (open3d, pybullet, robust_laplacian) are imported only inside
the functions that need them, so ``import tergodic_cli`` stays cheap.
"""

__version__ = "0.1.0"

#: Version of the basis-cache layout and solver; part of every cache key, bumped when either changes.
FORMAT_VERSION = 2
