"""The cheap check of a 2D triangulation, jitted, for a backend whose triangles stay on the device
(CuPy's gDel2D): the same conditions as the host's `check_triangulation`, on device arrays.

- every index in range and every walker a vertex (a walker left out is a failed build);
- every triangle positively oriented (twice its signed area above the rounding of its terms);
- Euler's formula for a triangulation of the convex hull: S = 2N - b - 2, b the boundary edges
  (edges of exactly one triangle), and no edge in more than two triangles.

The edges are counted by one sort of their (min, max) keys: O(S log S) on the device, no host
sync but the status read by the caller. `planar_summary` adds what the graph build needs from the
same triangles (their adjacency, the largest degree) and what the host's input checks need from the
positions (bounding box, largest |x|), so that one read of a few scalars is the only transfer.

Triangles may be padded to a fixed row count with rows of the sentinel N (all three entries).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

OK, OUT_OF_RANGE, LEFT_OUT, FLAT, EULER = 0, 1, 2, 3, 4
REASONS = {
    OUT_OF_RANGE: "a vertex index out of range",
    LEFT_OUT: "a walker left out",
    FLAT: "triangles flat or negatively oriented",
    EULER: "Euler's formula fails (or an edge has three triangles)",
}


@jax.jit
def planar_triangulation_status(points, simplices):
    """(status, flat triangles): `OK` (0) when `simplices` (S, 3) int is a positively oriented
    triangulation of the convex hull of `points` (N, 2), else the first failed condition's code
    (`REASONS`). Rows of the sentinel N are padding. Float64 arithmetic for the orientation where
    JAX has it."""
    n = points.shape[0]
    s, padding, safe = _padded(simplices, n)
    x = points.astype(jnp.float64 if jax.config.jax_enable_x64 else points.dtype)
    corners = jnp.minimum(safe, n - 1)
    a, b, c = x[corners[:, 0]], x[corners[:, 1]], x[corners[:, 2]]
    ab, ac = b - a, c - a
    twice_area = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    size = jnp.abs(ab[:, 0] * ac[:, 1]) + jnp.abs(ab[:, 1] * ac[:, 0])
    flat = jnp.sum(~padding & (twice_area <= 8 * jnp.finfo(x.dtype).eps * size), dtype=jnp.int32)
    return _status(s, padding, safe, n, n, flat), flat


def _padded(simplices, sentinel: int):
    """The triangles as int32, which rows are padding (every entry the `sentinel`), and the
    triangles with every index clipped into range (padding rows: the sentinel)."""
    s = simplices.astype(jnp.int32)
    padding = jnp.all(s == sentinel, axis=1)
    return s, padding, jnp.where(padding[:, None], sentinel, jnp.clip(s, 0, sentinel - 1))


def _status(s, padding, safe, n_walkers, sentinel: int, flat, edges=None):
    """The check's code (`REASONS`) of triangles `s` (`_padded`) of the first
    `n_walkers` (may be traced) of `sentinel` walkers, `flat` of them flat or negatively oriented;
    `edges`: their `_sorted_edges`, if already sorted."""
    n_walkers = jnp.asarray(n_walkers, jnp.int32)
    in_range = jnp.all(padding[:, None] | ((s >= 0) & (s < n_walkers)))
    used = jnp.zeros(sentinel, bool).at[safe.ravel()].set(True, mode="drop")
    used |= jnp.arange(sentinel, dtype=jnp.int32) >= n_walkers
    _, pair, n_edges = _sorted_edges(safe, sentinel) if edges is None else edges
    crowded = jnp.any(pair[1:] & pair[:-1])  # three equal keys in a row: an edge in three triangles
    boundary = n_edges - 2 * jnp.sum(pair, dtype=jnp.int32)  # edges in one triangle (none crowded)
    euler = (jnp.sum(~padding, dtype=jnp.int32) == 2 * n_walkers - boundary - 2) & ~crowded
    status = jnp.where(
        ~in_range,
        OUT_OF_RANGE,
        jnp.where(~jnp.all(used), LEFT_OUT, jnp.where(flat > 0, FLAT, jnp.where(~euler, EULER, OK))),
    )
    return status.astype(jnp.int32)


def _sorted_edges(s, sentinel: int):
    """`(corner, pair, n_edges)`: the corners of the triangles `s` (corner k of triangle t is
    3 t + k) sorted by the (min, max) key of the edge opposite them (one sort, no 64-bit keys),
    whether each shares its key with the next (both real, not padding rows of the `sentinel`),
    and the number of real edges counted with multiplicity."""
    a, b = jnp.roll(s, -1, axis=1).ravel(), jnp.roll(s, -2, axis=1).ravel()  # edge opposite corner k
    lo, hi, corner = jax.lax.platform_dependent(
        jnp.minimum(a, b), jnp.maximum(a, b), cpu=sort_by_two_keys, default=sort_in_two_radix_passes
    )
    pair = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1]) & (lo[1:] < sentinel)
    return corner, pair, jnp.sum(lo < sentinel, dtype=jnp.int32)


def sort_by_two_keys(lo, hi):
    """`(lo, hi, position)` sorted by (lo, hi): one sort with two keys (on the CPU 1.4x faster
    than two passes, bench/README.md)."""
    return jax.lax.sort((lo, hi, jnp.arange(lo.shape[0], dtype=jnp.int32)), num_keys=2)


def sort_in_two_radix_passes(lo, hi):
    """`sort_by_two_keys` as two stable one-key sorts with an index payload, the less significant
    key first. On a GPU XLA hands such sorts to CUB's radix sort; a sort of three operands is not
    CUB-compatible there (XLA's `sort_rewriter`: one or two operands) and runs as XLA's own
    comparison sort."""
    index = jnp.arange(lo.shape[0], dtype=jnp.int32)
    hi, by_hi = jax.lax.sort((hi, index), num_keys=1, is_stable=True)
    lo, then_by_lo = jax.lax.sort((lo[by_hi], index), num_keys=1, is_stable=True)
    return lo, hi[then_by_lo], by_hi[then_by_lo]


def triangle_adjacency(edges, shape):
    """(S, 3) = `shape`: the triangle across the edge opposite each vertex (-1 on the hull and in
    padding rows), from the triangles' `_sorted_edges`, for a triangulation that passed the check
    (an edge in at most two triangles)."""
    corner, pair, _ = edges
    nowhere = corner.shape[0]  # dropped by the scatters
    across = jnp.full(corner.shape[0], -1, jnp.int32)
    across = across.at[jnp.where(pair, corner[:-1], nowhere)].set(corner[1:] // 3, mode="drop")
    across = across.at[jnp.where(pair, corner[1:], nowhere)].set(corner[:-1] // 3, mode="drop")
    return across.reshape(shape)


def largest_degree(simplices, adjacency, sentinel: int):
    """The largest vertex degree of the triangulation: its triangles at a vertex, plus one on
    the hull (an open fan); the device twin of `_delaunay._planar_max_degree`."""
    triangles_at = jnp.zeros(sentinel, jnp.int32).at[simplices.ravel()].add(1, mode="drop")
    hull_start = jnp.where(adjacency < 0, jnp.roll(simplices, -1, axis=1), sentinel).ravel()  # t[a + 1] opposite a
    hull = jnp.zeros(sentinel, jnp.int32).at[hull_start].set(1, mode="drop")
    return jnp.max(triangles_at + hull)


@jax.jit
def planar_summary(points, simplices, flat, n_walkers):
    """`(scalars, adjacency)` of triangles `simplices` of the first `n_walkers` (traced) of
    `points` (M, 2; the rest padding, in no triangle), padded with rows of the sentinel M, of which
    `flat` were found flat or negatively oriented (by the backend's module in float64, which JAX
    lacks by default): scalars = (status (`REASONS`), number of triangles, largest degree) as int32,
    and (lower corner, upper corner, largest |x|) of the walkers in their dtype: one read for all."""
    m = points.shape[0]
    s, padding, safe = _padded(simplices, m)
    edges = _sorted_edges(safe, m)
    adjacency = triangle_adjacency(edges, s.shape)
    counts = jnp.stack(
        [
            _status(s, padding, safe, n_walkers, m, flat, edges),
            jnp.sum(~padding, dtype=jnp.int32),
            largest_degree(s, adjacency, m).astype(jnp.int32),
        ]
    )
    real = (jnp.arange(m, dtype=jnp.int32) < n_walkers)[:, None]
    lower = jnp.min(jnp.where(real, points, jnp.inf), axis=0)
    upper = jnp.max(jnp.where(real, points, -jnp.inf), axis=0)
    largest = jnp.max(jnp.where(real, jnp.abs(points), 0))
    return (counts, jnp.concatenate([lower, upper, largest[None]])), adjacency
