"""semantic3d: semantic classification of huge terrestrial laser scans.

The package follows the semantic3D.net benchmark (Hackel et al. 2017): streaming IO for
the benchmark's ASCII scans and label files, the scan registry, evaluation, baselines and
a self-hostable benchmark server.

Importing the package is cheap: the names below, and those of every subpackage, are
imported on first use (so ``semantic3d --version`` does not load numpy or numba).
"""

import os as _os
from typing import TYPE_CHECKING

# numba's OpenMP workers busy-wait after each parallel loop by default; on a machine with
# few cores they then starve scipy's k-d tree threads that run between the kernels (a 3-4x
# slowdown measured on 2 cores). The policy is read when the OpenMP runtime first loads,
# so set it at import, before any parallel kernel runs; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from semantic3d.core.lazy import lazy_exports

if TYPE_CHECKING:
    from semantic3d.core.classes import CLASSES, UNLABELLED, SemanticClass
    from semantic3d.core.errors import Semantic3DError
    from semantic3d.core.pointcloud import PointCloud

__version__ = "0.1.0"

__all__ = ["CLASSES", "UNLABELLED", "PointCloud", "Semantic3DError", "SemanticClass", "__version__"]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "CLASSES": "semantic3d.core.classes",
        "UNLABELLED": "semantic3d.core.classes",
        "SemanticClass": "semantic3d.core.classes",
        "Semantic3DError": "semantic3d.core.errors",
        "PointCloud": "semantic3d.core.pointcloud",
    },
)
