"""Independent numpy/scipy references for the tests (small N only: some are dense)."""

import itertools

import jax.numpy as jnp
import numpy as np
from scipy.spatial import ConvexHull, Delaunay, Voronoi


def scipy_neighbor_sets(points):
    indptr, indices = Delaunay(points).vertex_neighbor_vertices
    return [set(indices[indptr[i] : indptr[i + 1]].tolist()) for i in range(len(points))]


def padded_sets(neighbors, n):
    nbrs = np.asarray(neighbors)
    return [set(row[row < n].tolist()) for row in nbrs]


def scipy_voronoi_volumes(points):
    """Cell volumes from scipy's Voronoi + ConvexHull; NaN for unbounded cells."""
    vor = Voronoi(points)
    out = np.full(len(points), np.nan)
    for i, region_id in enumerate(vor.point_region):
        region = vor.regions[region_id]
        if region and -1 not in region:
            out[i] = ConvexHull(vor.vertices[region]).volume
    return out


def brute_force_tiers(points, box=None):
    """Tier classification straight from scipy's Voronoi diagram: tier 0 for unbounded cells
    and cells with a vertex outside the box (without a box: outside the convex hull)."""
    vor = Voronoi(points)
    hull = Delaunay(points)
    tier0 = np.zeros(len(points), bool)
    for i, region_id in enumerate(vor.point_region):
        region = vor.regions[region_id]
        if -1 in region:
            tier0[i] = True
        elif box is not None:
            verts = vor.vertices[region]
            tier0[i] = np.any((verts < box[0]) | (verts > box[1]))
        else:
            tier0[i] = np.any(hull.find_simplex(vor.vertices[region]) < 0)
    adjacent = np.zeros(len(points), bool)
    for a, b in vor.ridge_points:
        adjacent[a] |= tier0[b]
        adjacent[b] |= tier0[a]
    return np.where(tier0, 0, np.where(adjacent, 1, 2))


def tile(points, lower, upper, layers=1):
    """Periodic tiling; returns (tiled points, original index, integer shift), central copy first."""
    lower, upper = np.broadcast_to(lower, points.shape[1]), np.broadcast_to(upper, points.shape[1])
    d = points.shape[1]
    shifts = sorted(itertools.product(range(-layers, layers + 1), repeat=d), key=lambda s: any(s))
    pts = [points + np.asarray(s) * (upper - lower) for s in shifts]
    ids = [np.arange(len(points))] * len(shifts)
    sh = [np.tile(np.asarray(s), (len(points), 1)) for s in shifts]
    return np.concatenate(pts), np.concatenate(ids), np.concatenate(sh)


def periodic_neighbor_sets(points, lower, upper, layers=2):
    """{(j, shift)} for each walker, from scipy Delaunay of a tiled copy."""
    tiled, ids, shifts = tile(points, lower, upper, layers)
    indptr, indices = Delaunay(tiled).vertex_neighbor_vertices
    return [
        {(int(ids[j]), tuple(shifts[j].tolist())) for j in indices[indptr[i] : indptr[i + 1]]}
        for i in range(len(points))
    ]


def brute_knn(points, k, lengths=None):
    dx = points[None, :, :] - points[:, None, :]
    if lengths is not None:
        dx = dx - lengths * np.round(dx / lengths)
    d2 = np.sum(dx * dx, axis=-1)
    np.fill_diagonal(d2, np.inf)
    return np.argsort(d2, axis=1, kind="stable")[:, :k]


def random_rotation(d, rng):
    q, r = np.linalg.qr(rng.normal(size=(d, d)))
    return q * np.sign(np.diag(r))


def sphere(x):
    """Unit-sphere metric in stereographic coordinates, 4 / (1 + |x|^2)^2 I: curvature
    R = d (d - 1), geodesics the great circles."""
    return 4.0 / (1.0 + jnp.sum(x * x)) ** 2 * jnp.eye(x.shape[0], dtype=x.dtype)
