"""jaxgeom: JAX geometry kernels for walker swarms."""

from ._delaunay import delaunay as delaunay
from ._graph import Capacity as Capacity
from ._graph import Tessellation as Tessellation
from ._graph import neighbor_displacements as neighbor_displacements
from ._graph import simplex_vertices as simplex_vertices
from ._knn import knn_graph as knn_graph
from ._volumes import circumcenters as circumcenters
from ._volumes import voronoi_volumes as voronoi_volumes

__version__ = "0.1.0"
