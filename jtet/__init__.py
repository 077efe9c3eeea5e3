"""jtet: a JAX-based batch optimizer for the quality of tetrahedral meshes."""

from . import _config  # noqa: F401  (float64 + compilation cache, before any kernel)
from ._errors import InvariantError as InvariantError
from ._errors import JtetError as JtetError
from ._errors import MeshFileError as MeshFileError
from ._errors import MeshInputError as MeshInputError
from ._mesh import TetMesh as TetMesh
from ._quality import MEASURES as MEASURES

__version__ = "0.1.0"
