"""jaxgeom: JAX geometry kernels for walker swarms."""

from ._cells import mean_curvature_estimate as mean_curvature_estimate
from ._cells import raychaudhuri_expansion as raychaudhuri_expansion
from ._cells import shape_distortion as shape_distortion
from ._cells import vertex_distance_variance as vertex_distance_variance
from ._cells import volume_distortion as volume_distortion
from ._cellclip import rebuild as rebuild
from ._curvature import angle_sums as angle_sums
from ._curvature import deficit_angles as deficit_angles
from ._curvature import ricci_resolution as ricci_resolution
from ._curvature import ricci_scalar as ricci_scalar
from ._delaunay import delaunay as delaunay
from ._dynamics import SwarmParams as SwarmParams
from ._dynamics import SwarmState as SwarmState
from ._estimation import EstimateInfo as EstimateInfo
from ._estimation import estimate_gradient as estimate_gradient
from ._estimation import estimate_hessian as estimate_hessian
from ._estimation import geometric_hessian as geometric_hessian
from ._forces import edge_weights as edge_weights
from ._forces import viscous_force as viscous_force
from ._geodesic import geodesic_distances as geodesic_distances
from ._graph import Capacity as Capacity
from ._graph import Tessellation as Tessellation
from ._graph import neighbor_displacements as neighbor_displacements
from ._graph import simplex_vertices as simplex_vertices
from ._knn import knn_graph as knn_graph
from ._metric import edge_lengths as edge_lengths
from ._metric import emergent_metric as emergent_metric
from ._metric import hessian_metric as hessian_metric
from ._metric import metric_at_walkers as metric_at_walkers
from ._metric import metric_defects as metric_defects
from ._metric import riemannian_mean as riemannian_mean
from ._metric import riemannian_volumes as riemannian_volumes
from ._observables import OBSERVABLES as OBSERVABLES
from ._plots import plot_estimation_quality as plot_estimation_quality
from ._simulate import init_swarm as init_swarm
from ._simulate import simulate as simulate
from ._spectral import GraphLaplacian as GraphLaplacian
from ._spectral import graph_laplacian as graph_laplacian
from ._spectral import spectral_gap as spectral_gap
from ._validation import compare_estimation_methods as compare_estimation_methods
from ._validation import validate_on_synthetic_function as validate_on_synthetic_function
from ._volumes import circumcenters as circumcenters
from ._volumes import voronoi_volumes as voronoi_volumes

__version__ = "0.1.0"
