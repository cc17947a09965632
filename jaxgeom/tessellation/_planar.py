"""Planar Delaunay adjacency in JAX, from Qhull's triangles and their edge neighbours.

Qhull (through scipy) gives counter-clockwise triangles and, for each triangle, the
triangle across the edge opposite each vertex (-1 on the hull). The triangles
around a vertex form a fan; walking it counter-clockwise visits the vertex's
Delaunay neighbours in angular order, one gather per neighbour, vectorised over
walkers. A hull vertex's fan is open: its walk starts at the clockwise end and
closes with the last triangle's other vertex. This replaces scipy's
`vertex_neighbor_vertices` plus numpy padding on the host (3-4x slower, bench/README.md),
and it is jittable, so a rebuild inside `jax.pure_callback`
returns Qhull's arrays alone.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Int

WALKING, CLOSING, DONE = 0, 1, 2


def fan_neighbors(
    simplices: Int[Array, "S 3"],
    adjacency: Int[Array, "S 3"],
    n_points: int,
    k_cap: int,
    degenerate: Bool[Array, "S 3"] | None = None,
) -> tuple[Int[Array, "N K"], Bool[Array, " N"], Bool[Array, " N"]]:
    """Neighbour rows of a planar triangulation by walking each vertex's fan.

    **Arguments:**

    - `simplices`: (S, 3) counter-clockwise triangles, padding rows = `n_points`.
    - `adjacency`: (S, 3) triangle across the edge opposite each vertex, -1 for none
      (padding rows: -1).
    - `n_points`, `k_cap`: N and the row capacity K (static).
    - `degenerate`: (S, 3) edges (t[a], t[a + 1]) to leave out of the rows (contacts of
      zero measure, `_contacts.planar_degenerate_corners`); they still take a walk step.

    **Returns:**

    `(neighbors, hull, complete)`: (N, K) rows in ascending index order (padding N),
    convex-hull flags, and whether each row fitted in K slots (False also for a
    walker in no triangle).
    """
    following = jnp.roll(simplices, -1, axis=1).ravel()  # corner (t, a) = 3 t + a -> vertex t[a + 1]
    if degenerate is not None:
        following = jnp.where(degenerate.ravel(), n_points, following)
    preceding = jnp.roll(simplices, -2, axis=1).ravel()  # -> vertex t[a + 2]
    turn = _counterclockwise_corners(simplices, adjacency)
    first, hull, isolated = _fan_starts(simplices, adjacency, n_points)
    phase = jnp.where(isolated, -1, WALKING)  # -1: in no triangle, never complete

    def walking(carry):
        k, _, phase, _ = carry
        return (k < k_cap) & jnp.any((phase == WALKING) | (phase == CLOSING))

    def step(carry):  # emit one neighbour per walker, then turn counter-clockwise
        k, c, phase, columns = carry
        column = jnp.where(phase == WALKING, following[c], jnp.where(phase == CLOSING, preceding[c], n_points))
        after = turn[c]
        phase = jnp.where(
            phase == WALKING,
            jnp.where(after < 0, CLOSING, jnp.where(after == first, DONE, WALKING)),
            jnp.where(phase == CLOSING, DONE, phase),
        )
        return k + 1, jnp.where(after >= 0, after, c), phase, columns.at[k].set(column)

    # A while loop stops at the largest degree (14-17 in a swarm), not at the capacity (24).
    columns = jnp.full((k_cap, n_points), n_points, jnp.int32)
    _, _, phase, columns = jax.lax.while_loop(walking, step, (0, first, phase, columns))
    return sort_rows(columns), hull, phase == DONE


def _fan_starts(simplices, adjacency, n_points: int):
    """(first corner, hull, isolated) per vertex: any corner of an interior vertex, the
    clockwise end of a hull vertex's open fan (no triangle across edge t[a], t[a + 1])."""
    corners = 3 * simplices.shape[0]
    corner = jnp.arange(corners, dtype=jnp.int32)
    open_end = (jnp.roll(adjacency, -2, axis=1) < 0).ravel()
    start = jax.ops.segment_max(jnp.where(open_end, corner + corners, corner), simplices.ravel(), num_segments=n_points)
    isolated = start < 0  # the segment maximum of nothing is the smallest int
    hull = start >= corners
    return jnp.where(isolated, 0, jnp.where(hull, start - corners, start)), hull & ~isolated, isolated


def _counterclockwise_corners(simplices, adjacency):
    """For corner (t, a) with vertex i = t[a], the corner of i in the next triangle
    counter-clockwise around i (across edge t[a], t[a + 2]); -1 on the hull."""
    across = jnp.roll(adjacency, -1, axis=1)  # triangle opposite t[a + 1]
    there = simplices.at[across].get(mode="fill", fill_value=-1)  # (S, 3, 3)
    position = jnp.argmax(there == simplices[:, :, None], axis=-1).astype(jnp.int32)
    return jnp.where(across >= 0, 3 * across + position, -1).ravel()


# Rows up to this width are sorted by the merge network; wider rows (a walker ringed by many
# others) by XLA's sort, whose cost and compile time stay flat in the width (the network's
# comparator count grows like K log^2 K, and each comparator is an op XLA compiles).
MERGE_NETWORK_MAX_WIDTH = 32
# Fewer rows than this are sorted by XLA's sort: there the network saves 0.1-1.5 ms a call on a
# CPU and costs 0.5-1.5 s more compilation (K = 16-24; bench/README.md, "Sorting the neighbour
# rows"), which a run repays only after hundreds (near 4096) to thousands (1000) of rebuilds.
MERGE_NETWORK_MIN_ROWS = 4096


def sort_rows(columns, *, network: bool | None = None) -> Int[Array, "N K"]:
    """Stack K columns (a list of (N,) arrays, or a (K, N) array) into rows sorted ascending:
    Batcher's odd-even merge network (elementwise min/max that XLA fuses; its CPU sort is
    ~4-10x slower on short rows) for K <= `MERGE_NETWORK_MAX_WIDTH` and N >=
    `MERGE_NETWORK_MIN_ROWS`, `jnp.sort` otherwise. `network` forces the choice (the network
    still only up to `MERGE_NETWORK_MAX_WIDTH`)."""
    width = len(columns)
    rows = columns[0].shape[0]
    if network is None:
        network = rows >= MERGE_NETWORK_MIN_ROWS
    if not network or width > MERGE_NETWORK_MAX_WIDTH:
        return jnp.sort(jnp.stack(list(columns), axis=1) if isinstance(columns, list) else columns.T, axis=1)
    columns = list(columns)
    for i, j in _merge_network(width):
        columns[i], columns[j] = jnp.minimum(columns[i], columns[j]), jnp.maximum(columns[i], columns[j])
    return jnp.stack(columns, axis=1)


@functools.cache
def _merge_network(k: int) -> tuple[tuple[int, int], ...]:
    """Comparators (i, j), i < j < k, of Batcher's odd-even merge sort on the next power of
    two; comparators reaching past k are dropped (those slots would hold +inf)."""
    size = 1 << max(0, (k - 1).bit_length())
    pairs, p = [], 1
    while p < size:
        step = p
        while step >= 1:
            for j in range(step % p, size - step, 2 * step):
                for i in range(min(step, size - j - step)):
                    if (i + j) // (2 * p) == (i + j + step) // (2 * p) and i + j + step < k:
                        pairs.append((i + j, i + j + step))
            step //= 2
        p *= 2
    return tuple(pairs)
