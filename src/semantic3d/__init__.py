"""semantic3d: semantic classification of huge terrestrial laser scans.

The package follows the semantic3D.net benchmark (Hackel et al. 2017): streaming IO for
the benchmark's ASCII scans and label files, the scan registry, evaluation, baselines and
a self-hostable benchmark server.
"""

from semantic3d.core.classes import CLASSES, UNLABELLED, SemanticClass
from semantic3d.core.errors import Semantic3DError
from semantic3d.core.pointcloud import PointCloud

__version__ = "0.1.0"

__all__ = ["CLASSES", "UNLABELLED", "PointCloud", "Semantic3DError", "SemanticClass", "__version__"]
