"""Which Delaunay edges are contacts of positive measure between two Voronoi cells.

On degenerate input (a square or cubic lattice, co-circular or co-spherical walkers)
Qhull must split a cell of the Delaunay subdivision into simplices, and the diagonals it
adds join cells that meet in a point or a segment only (zero (d-1)-measure). Those edges
stay in the simplices (volumes and curvature do not depend on the split) but are not
neighbours: `neighbors` lists the cells sharing a face of positive measure.

The Voronoi face dual to edge (i, j) is the convex hull of the circumcentres of the
simplices around the edge, in the bisector plane of (i, j). It has zero measure exactly
when those circumcentres span fewer than d - 1 dimensions: the covariance C of their
offsets from the edge midpoint then has a (d-1)-th elementary symmetric function
e_{d-1}(C) ~ (product of its in-plane eigenvalues) that vanishes. The test is relative:
zero when the thinnest in-plane extent is below `CONTACT_RTOL(dtype)` |x_j - x_i|.
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from ..base._simplex import simplex_circumcenter, simplex_circumcenter_and_flat, small_det
from ._graph import Tessellation, edge_slots, simplex_coords, take_or_zero


def contact_rtol(dtype) -> float:
    """Relative extent below which a dual face counts as degenerate (1000 ulps)."""
    return 1e3 * float(jnp.finfo(dtype).eps)


def _elementary_symmetric(cov, order: int):
    """Sum of the principal minors of size `order` of (..., d, d) matrices."""
    d = cov.shape[-1]
    if order == 0:
        return jnp.ones(cov.shape[:-2], cov.dtype)
    total = 0.0
    for rows in itertools.combinations(range(d), order):
        idx = np.array(rows)
        total = total + small_det(cov[..., idx[:, None], idx[None, :]])
    return total


def _directed_edges(tess: Tessellation):
    """Every (simplex, edge) in both directions: flat neighbour-slot ids (n K where the edge
    is absent, on padding or on a flat simplex), the offset of the simplex's circumcentre from the edge midpoint
    (the same in both directions), and the squared edge length."""
    n, k_cap = tess.neighbors.shape
    coords = simplex_coords(tess)
    center, flat = jax.vmap(simplex_circumcenter_and_flat)(coords)
    pairs = list(itertools.combinations(range(tess.dim + 1), 2))
    src = jnp.concatenate([tess.simplices[:, a] for a, _ in pairs])
    dst = jnp.concatenate([tess.simplices[:, b] for _, b in pairs])
    shift = None
    if tess.simplex_shifts is not None:
        shift = jnp.concatenate([tess.simplex_shifts[:, b] - tess.simplex_shifts[:, a] for a, b in pairs])
    offset = jnp.concatenate([center - jnp.stack([0.5 * (c[:, a] + c[:, b]) for c in coords], -1) for a, b in pairs])
    sq = jnp.concatenate([sum((c[:, b] - c[:, a]) ** 2 for c in coords) for a, b in pairs])
    src, dst = jnp.concatenate([src, dst]), jnp.concatenate([dst, src])
    shift = None if shift is None else jnp.concatenate([shift, -shift])
    slot = edge_slots(tess, src, dst, shift)
    flat = jnp.tile(flat, 2 * len(pairs))  # flat simplices (slivers of a lattice) have no circumcentre
    ids = jnp.where((src < n) & (slot < k_cap) & ~flat, src * k_cap + slot, n * k_cap)
    return ids, jnp.concatenate([offset, offset]), jnp.concatenate([sq, sq])


@jax.jit
def circumcenters_and_flat(tess: Tessellation):
    """(S, d) circumcentres (periodic images applied) and (S,) flat flags; padding rows flat=False."""
    center, flat = jax.vmap(simplex_circumcenter_and_flat)(simplex_coords(tess))
    return center, flat & tess.simplex_mask


@jax.jit
def positive_measure_contacts(tess: Tessellation):
    """(N, K) bool: the neighbour slots whose Voronoi face has positive measure (padding
    False). Edges between two hull walkers are kept (their faces may be unbounded)."""
    n, k_cap = tess.neighbors.shape
    slots, d = n * k_cap, tess.dim
    ids, offset, sq = _directed_edges(tess)
    count = jnp.maximum(jax.ops.segment_sum(jnp.ones_like(sq), ids, num_segments=slots), 1.0)
    mean = jax.ops.segment_sum(offset, ids, num_segments=slots) / count[:, None]
    centred = offset - take_or_zero(mean, ids)
    cov = jax.ops.segment_sum(centred[:, :, None] * centred[:, None, :], ids, num_segments=slots) / count[:, None, None]
    sq_edge = jax.ops.segment_sum(sq, ids, num_segments=slots) / count
    trace = jnp.trace(cov, axis1=-2, axis2=-1)
    degenerate = _elementary_symmetric(cov, d - 1) <= contact_rtol(cov.dtype) ** 2 * sq_edge * trace ** (d - 2)
    both_hull = tess.hull[:, None] & jnp.concatenate([tess.hull, jnp.zeros((1,), bool)])[tess.neighbors]
    return (~degenerate.reshape(n, k_cap) | both_hull) & tess.neighbor_mask


def planar_degenerate_corners(points, simplices, adjacency):
    """(S, 3) bool, 2D: whether the edge (t[a], t[a + 1]) of triangle t has a dual Voronoi
    edge of zero length, i.e. t and the triangle across that edge (opposite t[a + 2])
    share their circumcircle. Hull edges (no triangle across) are never degenerate."""
    padded = jnp.concatenate([points, jnp.zeros((1, 2), points.dtype)])
    coords = tuple(padded[:, k][simplices] for k in range(2))
    center = jax.vmap(simplex_circumcenter)(coords)
    across = jnp.roll(adjacency, -2, axis=1)  # triangle opposite t[a + 2]
    other = center.at[across].get(mode="fill", fill_value=jnp.nan)
    gap = jnp.sum((center[:, None, :] - other) ** 2, axis=-1)
    edge = sum((jnp.roll(c, -1, axis=1) - c) ** 2 for c in coords)
    return (across >= 0) & (gap <= contact_rtol(points.dtype) ** 2 * edge)
