"""Voronoi cells on the device, one walker at a time (2D; groundwork of the jittable rebuild).

After Ray, Sokolov, Lefebvre and Levy, "Meshless Voronoi on the GPU" (2018): walker i's
cell starts as the box and is clipped by the bisector half-plane
{y : (y - (x_i + x_j) / 2) . (x_j - x_i) <= 0} of each candidate j, nearest first. A
candidate farther than twice the cell's largest vertex distance (the security radius)
cannot cut it, so the cell is *certified* once the security radius is below the distance
to the first candidate not used. Every cell is independent: one walker's kernel, vmapped.

The cell is a convex polygon of at most `max_vertices` vertices in fixed-shape arrays;
each edge carries the label of the walker whose bisector made it (-1 for the box), so
the cell's Voronoi neighbours are the labels of its edges of positive length.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._knn import _brute_neighbors

BOX_LABEL = -1


def box_polygon(box: Float[Array, "2 2"], max_vertices: int):
    """The box as a counter-clockwise polygon with `max_vertices` slots."""
    lo, hi = box[0], box[1]
    corners = jnp.stack([lo, jnp.stack([hi[0], lo[1]]), hi, jnp.stack([lo[0], hi[1]])])
    vertices = jnp.zeros((max_vertices, 2), box.dtype).at[:4].set(corners)
    labels = jnp.full((max_vertices,), BOX_LABEL, jnp.int32)
    return vertices, labels, jnp.asarray(4, jnp.int32)


def clip(polygon, normal, offset, label):
    """A polygon is (vertices (P, 2), labels (P,) of the edge leaving each vertex, count ()).

    Sutherland-Hodgman clip of a convex polygon by {y : normal . y <= offset}; the new
    edge along the clip line gets `label`. Returns (polygon, overflowed)."""
    vertices, labels, count = polygon
    p = vertices.shape[0]
    index = jnp.arange(p, dtype=jnp.int32)
    live = index < count
    following = jnp.where(index + 1 < count, index + 1, 0)
    a, b = vertices, vertices[following]
    sa, sb = vertices @ normal - offset, b @ normal - offset
    inside_a, inside_b = sa <= 0, sb <= 0
    crossing = live & (inside_a != inside_b)
    t = jnp.where(crossing, sa / jnp.where(crossing, sa - sb, 1.0), 0.0)
    cut = a + t[:, None] * (b - a)
    # Per edge up to two output vertices: a (if inside), then the crossing point.
    keep_a = live & inside_a
    out_vertices = jnp.stack([a, cut], axis=1).reshape(2 * p, 2)
    out_labels = jnp.stack([labels, jnp.where(inside_a, label, labels)], axis=1).reshape(2 * p)
    emit = jnp.stack([keep_a, crossing], axis=1).reshape(2 * p)
    slot = jnp.cumsum(emit, dtype=jnp.int32) - 1
    new_count = jnp.sum(emit, dtype=jnp.int32)
    target = jnp.where(emit & (slot < p), slot, p)
    vertices = jnp.zeros_like(vertices).at[target].set(out_vertices, mode="drop")
    labels = jnp.full_like(labels, BOX_LABEL).at[target].set(out_labels, mode="drop")
    return (vertices, labels, jnp.minimum(new_count, p)), new_count > p


def voronoi_cell(x_i, candidates, candidate_ids, box, max_vertices: int):
    """Walker i's cell clipped by every candidate (nearest first; NaN rows are skipped).

    Returns (vertices, labels, count, certified, overflowed)."""

    def step(carry, cand):
        polygon, overflowed = carry
        x_j, j = cand
        valid = jnp.all(jnp.isfinite(x_j)) & (j >= 0)
        normal = jnp.where(valid, x_j - x_i, 0.0)
        offset = jnp.where(valid, 0.5 * (x_j @ x_j - x_i @ x_i), 1.0)  # invalid: 0 <= 1, a no-op
        clipped, over = clip(polygon, normal, offset, j)
        return (clipped, overflowed | over), None

    start = box_polygon(box, max_vertices)
    (polygon, overflowed), _ = jax.lax.scan(step, (start, jnp.asarray(False)), (candidates, candidate_ids))
    vertices, labels, count = polygon
    live = jnp.arange(max_vertices, dtype=jnp.int32) < count
    reach = jnp.max(jnp.where(live, jnp.sum((vertices - x_i) ** 2, axis=1), 0.0))
    farthest_candidate = jnp.sum((candidates[-1] - x_i) ** 2)
    certified = (4.0 * reach < farthest_candidate) | jnp.any(candidate_ids < 0)
    return vertices, labels, count, certified, overflowed


def polygon_area(vertices, count):
    """Shoelace area of the first `count` vertices (counter-clockwise: positive)."""
    index = jnp.arange(vertices.shape[0], dtype=jnp.int32)
    following = vertices[jnp.where(index + 1 < count, index + 1, 0)]
    cross = vertices[:, 0] * following[:, 1] - vertices[:, 1] * following[:, 0]
    return 0.5 * jnp.sum(jnp.where(index < count, cross, 0.0))


def voronoi_cells_2d(points: Float[Array, "N 2"], box: Float[Array, "2 2"], *, k: int = 48,
                     max_vertices: int = 32):
    """Box-clipped Voronoi cells of all walkers, jittable (candidates: brute-force k-NN).

    **Returns:** `(vertices (N, P, 2), labels (N, P), count (N,), area (N,), certified (N,),
    overflowed (N,))`; `labels` holds the neighbour across each edge, -1 for the box."""
    points = jnp.asarray(points)
    box = jnp.asarray(box, points.dtype)
    n = points.shape[0]
    ids = _brute_neighbors(points, min(k, n - 1), None)
    candidates = points.at[ids].get(mode="fill", fill_value=jnp.nan)
    ids = jnp.where(ids < n, ids, -1)
    cell = jax.vmap(voronoi_cell, in_axes=(0, 0, 0, None, None))
    vertices, labels, count, certified, overflowed = cell(points, candidates, ids, box, max_vertices)
    area = jax.vmap(polygon_area)(vertices, count)
    return vertices, labels, count, area, certified, overflowed
