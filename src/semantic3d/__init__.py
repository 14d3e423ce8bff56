"""semantic3d: semantic classification of huge terrestrial laser scans.

The package follows the semantic3D.net benchmark (Hackel et al. 2017): streaming IO for
the benchmark's ASCII scans and label files, the scan registry, evaluation, baselines and
a self-hostable benchmark server.
"""

import os as _os

# numba's OpenMP workers busy-wait after each parallel loop by default; on a machine with
# few cores they then starve scipy's k-d tree threads that run between the kernels (a 3-4x
# slowdown measured on 2 cores). The policy is read when the OpenMP runtime first loads,
# so set it at import, before any parallel kernel runs; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from semantic3d.core.classes import CLASSES, UNLABELLED, SemanticClass
from semantic3d.core.errors import Semantic3DError
from semantic3d.core.pointcloud import PointCloud

__version__ = "0.1.0"

__all__ = ["CLASSES", "UNLABELLED", "PointCloud", "Semantic3DError", "SemanticClass", "__version__"]
