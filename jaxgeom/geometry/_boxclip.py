"""2D Voronoi cells clipped to the box: exact areas of box ∩ cell (3D cells: `_dualclip`).

Walker i's cell is the polygon {y : n_f . (y - x_i) <= c_f} of its Delaunay neighbours'
bisectors (n = (x_j - x_i) / r, c = r / 2, r = |x_j - x_i|) and, for the box, of the 4
walls (n = +-e_k, c = the walker's distance to the wall). Any superset of the cell's
face-defining neighbours gives the same polygon, so the padded neighbour rows serve as they
are. Its area follows from the divergence theorem with signed distances from x_i:
area = 1/2 sum_f c_f L_f, L_f the length of line f inside every other half-plane (an
interval on the line), F^2 intervals per cell, F = K + 4. Only cells that reach the box
(tier 0) need clipping, so they are gathered in chunks and the chunks past their count are
skipped (`lax.cond` inside `lax.map`): the cost follows the number of boundary walkers.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..base._compact import flagged_ids
from ..tessellation._graph import (
    Tessellation,
    any_along_rows,
    maximum_along_rows,
    minimum_along_rows,
    neighbor_displacements,
)

CLIP_CHUNK = 64  # boundary cells clipped per chunk
PARALLEL = 1e-12  # |n_f x n_g| below this: the planes are parallel (no common line)
ROUNDING_ULPS = 64  # a slope, or a room over the cell's size, this many epsilons from 0 is 0


def _parallel(slope, room, size):
    """(rows parallel to the line, rows that contain it), to rounding: a lattice's cells have
    planes through their edges (zero-area faces) whose slope and room are ~eps, not 0, and
    room / slope is then an arbitrary bound."""
    eps = jnp.finfo(slope.dtype).eps
    parallel = jnp.abs(slope) <= ROUNDING_ULPS * eps
    return parallel, parallel & (jnp.abs(room) <= ROUNDING_ULPS * eps * size)


def _bounded_interval(point, direction, normals, offsets, usable, size):
    """(length of {point + t direction : normals . (...) <= offsets for the usable rows}, the
    rows whose plane contains the line); `size` the cell's length scale. A row parallel to the
    line (normal . direction = 0, to rounding) either holds on the whole line or empties it."""
    lower, upper, empty, _, contains = line_interval(point, direction, normals, offsets, usable, size)
    return jnp.where(empty, 0.0, jnp.maximum(upper - lower, 0.0)), contains


def line_interval(point, direction, normals, offsets, usable, size):
    """(lower, upper, empty, unbounded, contains): the interval of t, whether it is empty,
    whether an end is open (no usable row bounds it: an unbounded face), and the rows whose plane
    contains the line (`_bounded_interval`)."""
    slope = normals @ direction
    room = offsets - normals @ point
    parallel, contains = _parallel(slope, room, size)
    safe = jnp.where(parallel, 1.0, slope)
    bound = room / safe
    big = jnp.asarray(0.25 * jnp.finfo(point.dtype).max, point.dtype)  # upper - lower stays finite
    above, below = usable & ~parallel & (slope > 0), usable & ~parallel & (slope < 0)
    upper = over_planes("min", jnp.where(above, bound, big))
    lower = over_planes("max", jnp.where(below, bound, -big))
    outside = usable & parallel & (room < -ROUNDING_ULPS * jnp.finfo(point.dtype).eps * size)
    empty = over_planes("any", outside) | (upper <= lower)
    return lower, upper, empty, ~over_planes("any", above) | ~over_planes("any", below), contains


# XLA's CPU backend makes a reduction over more rows than this a reduce-window, slower than
# halving them (3D cells' K + 2d = 62 planes: boxed `voronoi_volumes` at 1e4 ~3% faster); at
# or below it jnp's own reduction is the faster (2D cells: ~10%)
REDUCE_WINDOW_ROWS = 32
_REDUCTIONS = {
    "min": (jnp.min, minimum_along_rows),
    "max": (jnp.max, maximum_along_rows),
    "any": (jnp.any, any_along_rows),
}


def over_planes(kind: str, values):
    """The `kind` ("min", "max", "any") of `values` over the last axis (a cell's planes), by
    halving where the axis is wide (`REDUCE_WINDOW_ROWS`); the same values either way."""
    reduce, halving = _REDUCTIONS[kind]
    return halving(values) if values.shape[-1] > REDUCE_WINDOW_ROWS else reduce(values, axis=-1)


def polygon_area(normals: Float[Array, "F 2"], offsets: Float[Array, " F"], active: Bool[Array, " F"]):
    """Area of {y : normals . y <= offsets (active rows)}, bounded and containing 0."""
    f = normals.shape[0]
    others = active[None, :] & ~jnp.eye(f, dtype=bool)

    def edge(n, c, usable):
        direction = jnp.stack([-n[1], n[0]])
        return _bounded_interval(c * n, direction, normals, offsets, usable, size)[0]

    size = jnp.max(jnp.where(active, offsets, 0.0))
    lengths = jnp.where(active, jax.vmap(edge)(normals, offsets, others), 0.0)  # padding rows: unbounded
    return 0.5 * jnp.sum(offsets * lengths)


def cell_planes(tess: Tessellation, rows):
    """The half-spaces of the cells of walkers `rows` (padding N) in their own frames:
    (normals (M, F, d), offsets (M, F), active (M, F)), the bisectors first, then the walls."""
    n, d = tess.points.shape
    box = tess.box.astype(tess.points.dtype)
    safe_rows = jnp.minimum(rows, n - 1)
    dx = neighbor_displacements(tess)[safe_rows]
    real = (tess.neighbors[safe_rows] < n) & (rows < n)[:, None]
    r = jnp.sqrt(jnp.sum(jnp.where(real[..., None], dx, 1.0) ** 2, axis=-1))
    normals = jnp.where(real[..., None], dx / r[..., None], 0.0)
    x = tess.points[safe_rows]
    eye = jnp.eye(d, dtype=x.dtype)
    walls = jnp.broadcast_to(jnp.concatenate([eye, -eye]), (len(rows), 2 * d, d))
    wall_offsets = jnp.concatenate([box[1] - x, x - box[0]], axis=1)
    wall_active = jnp.broadcast_to((rows < n)[:, None], wall_offsets.shape)
    return (
        jnp.concatenate([normals, walls], axis=1),
        jnp.concatenate([0.5 * r, wall_offsets], axis=1),
        jnp.concatenate([real, wall_active], axis=1),
    )


def map_flagged_rows(flags, size: int, fn, empty):
    """(rows, outputs): `fn(ids)` over the walkers where `flags` holds, `size` per chunk (rows
    padded with N), stacked along the rows; chunks past their count give `empty(ids)` without
    running `fn` (`lax.cond`, in groups: `map_live_chunks`), so the cost follows the flagged
    walkers."""
    n = flags.shape[0]
    n_chunks = -(-n // size)
    rows = flagged_ids(flags, n_chunks * size, n)
    out = map_live_chunks(fn, empty, rows.reshape(n_chunks, size), n)
    return rows, jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), out)


CHUNK_GROUPS = 16  # chunks are walked in this many groups, a group past the live ones skipped whole


def _in_groups(chunks, fill: int):
    """`chunks` (C, size) padded with `fill` to CHUNK_GROUPS groups: (groups, C', size)."""
    n_chunks = chunks.shape[0]
    groups = min(CHUNK_GROUPS, n_chunks)
    per = -(-n_chunks // groups)
    padded = jnp.pad(chunks, ((0, groups * per - n_chunks), (0, 0)), constant_values=fill)
    return padded.reshape(groups, per, chunks.shape[1])


def map_live_chunks(fn, empty, chunks, fill: int):
    """`lax.map` of `fn` over `chunks` (C, size) of ids compacted to the front and padded with
    `fill`, `empty(chunk)` for a chunk of padding. Every loop iteration has a cost of its own
    (on a GPU a launch), so the chunks go in CHUNK_GROUPS groups and a group of padding is
    skipped whole: a few live chunks cost about C / CHUNK_GROUPS iterations, not C (2D boxed
    `voronoi_volumes` on the CPU: 11.5 -> 6.0 ms at N = 1e5, 96 -> 71 ms at 1e6)."""
    one = lambda ids: jax.lax.cond(ids[0] < fill, fn, empty, ids)  # noqa: E731
    group = lambda g: jax.lax.cond(g[0, 0] < fill, lambda: jax.lax.map(one, g), lambda: jax.vmap(empty)(g))  # noqa: E731
    out = jax.lax.map(group, _in_groups(chunks, fill))
    n_chunks = chunks.shape[0]
    return jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:])[:n_chunks], out)


def scan_live_chunks(step, carry, chunks, fill: int):
    """`carry` after `step(carry, chunk)` over `chunks` (C, size) of ids compacted to the front
    and padded with `fill`, chunks of padding skipped (`map_live_chunks`' groups)."""
    one = lambda c, ids: (jax.lax.cond(ids[0] < fill, step, lambda c, _: c, c, ids), None)  # noqa: E731
    group = lambda c, g: (  # noqa: E731
        jax.lax.cond(g[0, 0] < fill, lambda c: jax.lax.scan(one, c, g)[0], lambda c: c, c),
        None,
    )
    return jax.lax.scan(group, carry, _in_groups(chunks, fill))[0]


def clip_to_box(tess: Tessellation, volumes: Float[Array, " N"]) -> Float[Array, " N"]:
    """`volumes` with every tier-0 walker's cell (unbounded or reaching the box) replaced by
    its area inside `tess.box` (2D, non-periodic; 3D cells are clipped by `_dualclip`)."""
    rows, clipped = map_flagged_rows(
        tess.tier == 0,
        CLIP_CHUNK,
        lambda ids: jax.vmap(polygon_area)(*cell_planes(tess, ids)),
        lambda ids: jnp.zeros(ids.shape, volumes.dtype),
    )
    return volumes.at[rows].set(clipped, mode="drop")
