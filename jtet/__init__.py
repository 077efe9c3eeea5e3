"""jtet: a JAX-based batch optimizer for the quality of tetrahedral meshes."""

from . import _config  # noqa: F401  (float64 + compilation cache, before any kernel)
from ._driver import ImproveResult as ImproveResult
from ._driver import improve as improve
from ._errors import InvariantError as InvariantError
from ._errors import JtetError as JtetError
from ._errors import MeshFileError as MeshFileError
from ._errors import MeshInputError as MeshInputError
from ._io import demo_mesh as demo_mesh
from ._io import load as load
from ._io import save as save
from ._mesh import CurvedEdges as CurvedEdges
from ._mesh import NodeSet as NodeSet
from ._mesh import TetMesh as TetMesh
from ._options import Options as Options
from ._options import load_options as load_options
from ._predicates import orient3d as orient3d
from ._predicates import orient3d_tets as orient3d_tets
from ._predicates import segment_crosses_triangle as segment_crosses_triangle
from ._quality import MEASURES as MEASURES
from ._report import plot_stats as plot_stats
from ._stats import MeshStats as MeshStats
from ._stats import format_table as format_table
from ._stats import mesh_stats as mesh_stats
from ._stats import region_stats as region_stats
from ._stats import worst_tets as worst_tets
from ._tetrahedralize import read_surface as read_surface
from ._tetrahedralize import tetrahedralize as tetrahedralize
from ._validity import ValidityReport as ValidityReport

stats = mesh_stats  # ``jtet.stats(mesh)``: statistics of a mesh


def quality(mesh: TetMesh, measure: str = "min_sine"):
    """(m,) quality of every tet of ``mesh`` under ``measure`` (see ``MEASURES``)."""
    return mesh.quality(measure)


__version__ = "0.1.0"
