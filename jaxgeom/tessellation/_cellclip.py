"""The Delaunay triangulation on the device, one walker's Voronoi cell at a time (2D).

After Ray, Sokolov, Lefebvre and Levy, "Meshless Voronoi on the GPU" (2018): walker i's
cell is a large square around x_i clipped by the bisector of each candidate j (from the
cell list of `_cellgrid`). The cell is kept as the cyclic list of the lines bounding it (homogeneous
3-vectors in the frame of x_i; the square's sides are labelled `FAR`), and every vertex
is the cross product of two consecutive lines, so a vertex near x_i is as precise as
the two bisectors that make it, however far the square's corners are. Every cell is
independent: one walker's kernel, vmapped.

A vertex between the bisectors of a and b is the circumcentre of the Delaunay triangle
(i, a, b), counter-clockwise. The triangles are *certified*, not trusted, by the
Delaunay lemma (a triangulation of the points whose every edge is locally Delaunay is
the Delaunay triangulation):

- every triangle is seen by the cells of all three of its vertices, in the same order
  (the cells form one consistent complex), and is positively oriented;
- every edge is locally Delaunay (the fourth vertex of the two triangles on it lies
  outside the circumcircle of the other three, to rounding);
- the boundary (cells reaching the square) is a convex polygon, turning once.

A candidate list that misses a Delaunay neighbour, a far Voronoi vertex outside the
square, a capacity exceeded or an unresolved degeneracy breaks one of these. The cells in
a failed condition are redone with more candidates (`triangulate`); what still fails is
flagged instead of returned wrong.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ..base._sharding import WALKER_AXIS, check_mesh, split_rows
from ._cellgrid import block_walkers, build_grid, grid_side, walker_reach, within
from ._delaunay import planar_tessellation
from ._graph import Tessellation, lower_bound_in_rows

FAR = -1  # label of the square's sides (the cell reaches "infinity": a hull walker)
SQUARE = 1e3  # half-side of the start square, in units of the swarm's extent
CLIP_ULPS = 64  # a vertex within this many units of rounding of a clipping line counts as on it


def bisector_lines(offsets: Float[Array, "k 2"]) -> Float[Array, "k 3"]:
    """Homogeneous lines (n, c) with the half-plane {p : n . p + c <= 0} closer to the
    origin (x_i) than to each offset d = x_j - x_i: n = d, c = -|d|^2 / 2."""
    return jnp.concatenate([offsets, -0.5 * jnp.sum(offsets * offsets, axis=1, keepdims=True)], axis=1)


def start_square(half: Float[Array, ""], max_edges: int):
    """The square [-half, half]^2 as a cell: (lines (P, 3), vertices (P, 3), labels (P,), count)."""
    one, zero = jnp.ones_like(half), jnp.zeros_like(half)
    sides = jnp.stack(
        [
            jnp.stack([zero, -one, -half]),
            jnp.stack([one, zero, -half]),
            jnp.stack([zero, one, -half]),
            jnp.stack([-one, zero, -half]),
        ]
    )
    lines = jnp.zeros((max_edges, 3), half.dtype).at[:4].set(sides)
    vertices = jnp.zeros((max_edges, 3), half.dtype).at[:4].set(jnp.cross(jnp.roll(sides, 1, axis=0), sides))
    return lines, vertices, jnp.full((max_edges,), FAR, jnp.int32), jnp.asarray(4, jnp.int32)


def clip(cell, line, label):
    """The cell cut by the half-plane {p : line . p <= 0}; returns (cell, overflowed).

    A cell is (lines, vertices, labels, count): edge m lies on `lines[m]` and runs from
    vertex m = lines[m - 1] x lines[m] (homogeneous, third entry > 0) to vertex m + 1. The
    vertices outside form one cyclic run; the edges between two outside vertices go, and
    the new line enters after the edge leaving the inside. The cycle is restarted at the
    edge entering the inside, so the update is one gather plus the two new vertices."""
    lines, vertices, labels, count = cell
    p = lines.shape[0]
    index = jnp.arange(p, dtype=jnp.int32)
    terms = vertices * line
    # A vertex on the line (to rounding) stays: a repeated line is then a no-op.
    tolerance = CLIP_ULPS * jnp.finfo(terms.dtype).eps
    outside = (index < count) & (jnp.sum(terms, axis=1) > tolerance * jnp.sum(jnp.abs(terms), axis=1))
    following = jnp.where(index + 1 < count, index + 1, 0)
    entry = jnp.argmax(outside & ~outside[following]).astype(jnp.int32)
    n_out = jnp.sum(outside, dtype=jnp.int32)
    new_count = count - n_out + 2
    source = jnp.mod(entry + index, jnp.maximum(count, 1))
    last = new_count - 1  # the new line's slot; slot last - 1 holds the edge leaving the inside
    new_lines = jnp.where((index == last)[:, None], line, lines[source])
    new_vertices = vertices[source]
    new_vertices = jnp.where((index == 0)[:, None], jnp.cross(line, lines[entry]), new_vertices)
    new_vertices = jnp.where(
        (index == last)[:, None], jnp.cross(new_lines[jnp.maximum(last - 1, 0)], line), new_vertices
    )
    new_labels = jnp.where(index == last, label, labels[source])
    cut = (n_out > 0) & (n_out < count)
    cell_after = (new_lines, new_vertices, new_labels, jnp.minimum(new_count, p))
    return jax.tree_util.tree_map(lambda a, b: jnp.where(cut, a, b), cell_after, cell), cut & (new_count > p)


def voronoi_cell(offsets, candidate_ids, half, max_edges: int):
    """Walker i's cell clipped by its candidates (`candidate_ids` < 0: padding, skipped; any
    order, nearest first keeps the intermediate cells small). Returns `(labels, count,
    overflowed, vertices)`, the vertices homogeneous in the frame of x_i."""

    def step(carry, candidate):
        cell, overflowed = carry
        line, j = candidate
        cell_after, over = clip(cell, line, j)
        cell = jax.tree_util.tree_map(lambda a, b: jnp.where(j >= 0, a, b), cell_after, cell)
        return (cell, overflowed | ((j >= 0) & over)), None

    start = start_square(half, max_edges)
    (cell, overflowed), _ = jax.lax.scan(step, (start, jnp.asarray(False)), (bisector_lines(offsets), candidate_ids))
    return cell[2], cell[3], overflowed, cell[1]


def voronoi_cycles(points: Float[Array, "N 2"], candidates: Int[Array, "M k"], rows=None, *, max_edges: int = 24):
    """The cells of walkers `rows` (default all) as cyclic lists of neighbour labels (`FAR`
    for the square's sides).

    **Arguments:**

    - `points`: (N, 2) walkers.
    - `candidates`: (M, k) candidate neighbours of each row's walker, padding N.
    - `rows`: (M,) walkers (padding N: an empty cell); default `arange(N)`.
    - `max_edges`: edge slots per cell (static).

    **Returns:** `(labels (M, P), count (M,), overflowed (M,), vertices (M, P, 3))`, the
    vertices homogeneous (x, y, w > 0) in the frame of each walker.
    """
    n = points.shape[0]
    rows = jnp.arange(n, dtype=jnp.int32) if rows is None else rows
    candidates = candidates.astype(jnp.int32)
    centre = points.at[rows].get(mode="fill", fill_value=0.0)
    offsets = points.at[candidates].get(mode="fill", fill_value=0.0) - centre[:, None, :]
    ids = jnp.where((candidates < n) & (candidates != rows[:, None]), candidates, -1).astype(jnp.int32)
    extent = jnp.max(jnp.abs(points - jnp.mean(points, axis=0)))
    half = SQUARE * jnp.maximum(extent, jnp.finfo(points.dtype).tiny)
    return jax.vmap(voronoi_cell, in_axes=(0, 0, None, None))(offsets, ids, half, max_edges)


def _cyclic(count, max_edges: int, shift: int):
    """Slot index m + shift (mod count) for every slot m < max_edges."""
    index = jnp.arange(max_edges, dtype=jnp.int32)
    return jnp.mod(index + shift, jnp.maximum(count, 1)[..., None])


def _label_search(sorted_labels, order, rows, values):
    """Slot (in the cycle of walker `rows`) of label `values`, or -1 if absent: binary search
    over each row's sorted labels (`order` maps sorted positions back to cycle slots)."""
    p = sorted_labels.shape[1]
    rows = jnp.clip(rows, 0, sorted_labels.shape[0] - 1)
    lo = lower_bound_in_rows(sorted_labels, rows, values)
    at = jnp.minimum(lo, p - 1)
    return jnp.where((lo < p) & (sorted_labels[rows, at] == values), order[rows, at], -1)


def _orient(a, b, c):
    """Twice the signed area of the triangles (a, b, c) (arrays (..., 2))."""
    return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])


def _incircle(a, b, c, q):
    """> 0 where q lies inside the circumcircle of the counter-clockwise triangle (a, b, c),
    relative to the scale |.|^4 of the offsets (so a tolerance is dimensionless)."""
    rows = [p - q for p in (a, b, c)]
    lift = [jnp.sum(r * r, axis=-1) for r in rows]
    det = (
        rows[0][..., 0] * (rows[1][..., 1] * lift[2] - lift[1] * rows[2][..., 1])
        - rows[0][..., 1] * (rows[1][..., 0] * lift[2] - lift[1] * rows[2][..., 0])
        + lift[0] * (rows[1][..., 0] * rows[2][..., 1] - rows[1][..., 1] * rows[2][..., 0])
    )
    scale = jnp.maximum(jnp.maximum(lift[0], lift[1]), lift[2])
    return det / jnp.where(scale > 0, scale * scale, 1.0)


class Cycles(NamedTuple):
    """Each walker's cell as a cycle of labels, with what the certificate needs of it."""

    labels: Int[Array, "N P"]  # neighbour across each edge, FAR for the square; N beyond count
    count: Int[Array, " N"]  # type: ignore[assignment]  # shadows tuple.count, which nothing calls
    before: Int[Array, "N P"]  # label of the previous edge (the vertex m is between before[m] and labels[m])
    after: Int[Array, "N P"]  # label of the next edge
    live: Bool[Array, "N P"]
    sorted_labels: Int[Array, "N P"]
    order: Int[Array, "N P"]


def _cycles(labels, count, n: int) -> Cycles:
    p = labels.shape[1]
    live = jnp.arange(p, dtype=jnp.int32) < count[:, None]
    labels = jnp.where(live, labels, n)
    before = jnp.take_along_axis(labels, _cyclic(count, p, -1), axis=1)
    after = jnp.take_along_axis(labels, _cyclic(count, p, 1), axis=1)
    order = jnp.argsort(labels, axis=1).astype(jnp.int32)
    return Cycles(labels, count, before, after, live, jnp.take_along_axis(labels, order, axis=1), order)


def _corner_points(points, *ids):
    """Coordinates of walkers `ids` (zeros at the sentinel and for FAR)."""
    n = points.shape[0]
    return [points.at[jnp.where((k >= 0) & (k < n), k, n)].get(mode="fill", fill_value=0.0) for k in ids]


class Certificate(NamedTuple):
    """Which part of the Delaunay lemma's conditions failed (all False: certified)."""

    inconsistent: Bool[Array, ""]  # a triangle not seen alike by its three cells
    inverted: Bool[Array, ""]  # a triangle not positively oriented
    not_delaunay: Bool[Array, ""]  # an edge not locally Delaunay
    bad_boundary: Bool[Array, ""]  # boundary not one convex cycle
    isolated: Bool[Array, ""]  # a walker in no triangle

    @property
    def failed(self):
        return self.inconsistent | self.inverted | self.not_delaunay | self.bad_boundary | self.isolated


def incircle_tolerance(dtype) -> float:
    """Largest normalised in-circle value taken as co-circular (a tie, either diagonal)."""
    return 256 * float(jnp.finfo(dtype).eps)


def _flag(n: int, failed, *walkers):
    """(N,) bool: the walkers named where `failed` (FAR and padding ids are dropped)."""
    marks = jnp.zeros((n + 1,), bool)
    for w in walkers:
        marks = marks.at[jnp.where(failed & (w >= 0), w, n)].set(True, mode="drop")
    return marks[:n]


class Checks(NamedTuple):
    """The certificate of a set of cycles, per cell vertex and per walker."""

    triangle: Bool[Array, "N P"]  # the vertex is a triangle (i, before, label)
    slot_in_a: Int[Array, "N P"]  # slot of this vertex in the cycle of `before`
    slot_in_b: Int[Array, "N P"]  # ... and of `label`
    hull: Bool[Array, " N"]
    suspect: Bool[Array, " N"]  # walkers in a failed condition: their cells are redone
    certificate: Certificate


def check_cycles(points, cy: Cycles) -> Checks:
    """The Delaunay lemma's conditions on the cycles (module docstring)."""
    n = points.shape[0]
    i = jnp.broadcast_to(jnp.arange(n, dtype=jnp.int32)[:, None], cy.labels.shape)
    a, b, c = cy.before, cy.labels, cy.after
    triangle = cy.live & (a >= 0) & (b >= 0)
    slot_in_a = _label_search(cy.sorted_labels, cy.order, jnp.where(triangle, a, 0), i)
    slot_in_b = _label_search(cy.sorted_labels, cy.order, jnp.where(triangle, b, 0), a)
    seen_by_a = (slot_in_a >= 0) & (cy.before[jnp.where(triangle, a, 0), jnp.maximum(slot_in_a, 0)] == b)
    seen_by_b = (slot_in_b >= 0) & (cy.before[jnp.where(triangle, b, 0), jnp.maximum(slot_in_b, 0)] == i)
    inconsistent = triangle & ~(seen_by_a & seen_by_b)
    xi, xa, xb, xc = _corner_points(points, i, a, b, c)
    inverted = triangle & ~(_orient(xi, xa, xb) > 0)
    not_delaunay = triangle & (c >= 0) & (c < n) & (_incircle(xi, xa, xb, xc) > incircle_tolerance(points.dtype))
    isolated = ~jnp.any(triangle, axis=1)
    hull, bad_chain, bad_turn, previous, following = boundary_checks(points, cy)
    suspect = (
        _flag(n, inconsistent | inverted | not_delaunay, i, a, b)
        | _flag(n, not_delaunay, c)
        | isolated
        | _flag(n, bad_chain, jnp.arange(n, dtype=jnp.int32), previous, following)
        | (bad_turn & hull)
    )
    certificate = Certificate(
        jnp.any(inconsistent),
        jnp.any(inverted),
        jnp.any(not_delaunay),
        jnp.any(bad_chain) | bad_turn,
        jnp.any(isolated),
    )
    return Checks(triangle, slot_in_a, slot_in_b, hull, suspect, certificate)


def boundary_checks(points, cy: Cycles):
    """The cells reaching the square must chain into one convex counter-clockwise cycle
    (previous hull walker = the label before the FAR run, next = the label after it; a
    straight turn allowed), turning once (2 pi). Returns `(hull, bad_chain (N,), bad_turn (), previous, following)`."""
    n = points.shape[0]
    enters = cy.live & (cy.labels == FAR) & (cy.before >= 0)
    leaves = cy.live & (cy.labels >= 0) & (cy.before == FAR)
    hull = jnp.any(enters, axis=1)
    entering = jnp.sum(enters, axis=1, dtype=jnp.int32)
    runs_ok = (entering == jnp.sum(leaves, axis=1, dtype=jnp.int32)) & (entering <= 1)
    previous = jnp.max(jnp.where(enters, cy.before, -1), axis=1)
    following = jnp.max(jnp.where(leaves, cy.labels, -1), axis=1)
    chained = previous.at[jnp.where(hull, following, n)].get(mode="fill", fill_value=-1) == jnp.arange(
        n, dtype=jnp.int32
    )
    xp, xi, xn = _corner_points(points, previous, jnp.arange(n, dtype=jnp.int32), following)
    turn = _orient(xp, xi, xn)
    dot = jnp.sum((xi - xp) * (xn - xi), axis=-1)
    total_turn = jnp.sum(jnp.where(hull, jnp.arctan2(turn, dot), 0.0))
    # Collinear walkers on the hull (a wall) turn by 0 to rounding: allowed.
    straight = (
        64 * jnp.finfo(points.dtype).eps * jnp.sqrt(jnp.sum((xi - xp) ** 2, axis=-1) * jnp.sum((xn - xi) ** 2, axis=-1))
    )
    bad_chain = ~runs_ok | (hull & ~(chained & (turn >= -straight)))
    return hull, bad_chain, jnp.abs(total_turn - 2 * jnp.pi) > 1.0, previous, following


def emit_triangles(cy: Cycles, checks: Checks, s_cap: int):
    """The triangles, each from the cell of its smallest vertex, and their adjacency.

    **Returns:** `(simplices (S, 3) counter-clockwise, padding N; adjacency (S, 3), the
    triangle opposite each corner, -1 on the hull; overflowed)`, `overflowed` when more
    than `s_cap` triangles were found."""
    n, p = cy.labels.shape
    i = jnp.arange(n, dtype=jnp.int32)[:, None]
    a, b = cy.before, cy.labels
    emit = checks.triangle & (i < a) & (i < b)
    ids = jnp.where(emit, jnp.cumsum(emit.ravel(), dtype=jnp.int32).reshape(n, p) - 1, -1)
    rows = jnp.where(emit & (ids < s_cap), ids, s_cap)
    simplices = (
        jnp.full((s_cap, 3), n, jnp.int32)
        .at[rows]
        .set(jnp.stack([jnp.broadcast_to(i, a.shape), a, b], axis=-1), mode="drop")
    )
    # Every cell vertex learns its triangle's id from the emitting cell.
    table = jnp.full((n + 1, p), -1, jnp.int32)
    table = table.at[jnp.where(emit, i, n), jnp.arange(p, dtype=jnp.int32)].set(ids, mode="drop")
    table = table.at[jnp.where(emit, a, n), jnp.maximum(checks.slot_in_a, 0)].set(ids, mode="drop")
    table = table.at[jnp.where(emit, b, n), jnp.maximum(checks.slot_in_b, 0)].set(ids, mode="drop")
    adjacency = _adjacency(cy, table, emit, rows, checks.slot_in_a, s_cap)
    return simplices, adjacency, jnp.sum(emit, dtype=jnp.int32) > s_cap


def _adjacency(cy: Cycles, table, emit, rows, slot_in_a, s_cap: int):
    """(S, 3) triangle across the edge opposite each corner of the emitted triangles (i, a, b)."""
    n, p = cy.labels.shape
    safe_a = jnp.where(emit, cy.before, 0)
    edge_ab = jnp.maximum(slot_in_a, 0) - 1  # in cell a, the vertex before (b, i) ends edge (a, b) too
    edge_ab = jnp.where(edge_ab < 0, cy.count[safe_a] - 1, edge_ab)
    across_ab = table[safe_a, edge_ab]
    across_ib = jnp.take_along_axis(table[:n], _cyclic(cy.count, p, 1), axis=1)
    across_ia = jnp.take_along_axis(table[:n], _cyclic(cy.count, p, -1), axis=1)
    adjacency = jnp.stack([across_ab, across_ib, across_ia], axis=-1)
    return jnp.full((s_cap, 3), -1, jnp.int32).at[rows].set(adjacency, mode="drop")


def repair_candidates(points, labels, rows, k: int, *, coarsening: int = 4, per_row: int = 16):
    """(R, k) candidates for the cells of walkers `rows` (padding N), nearest first, from the
    labels of their current cycle and of its cells (the 2-ring, which reaches the far
    neighbours of a sparse rim or of a cluster's edge) and the walkers of a block of a grid
    `coarsening` times coarser than the first pass's."""
    n, p = labels.shape
    r = rows.shape[0]
    centre = points.at[rows].get(mode="fill", fill_value=jnp.nan)
    grid = build_grid(points, max(4, grid_side(n) // coarsening))
    block, _, _, _ = block_walkers(points, grid, rows, walker_reach(grid, rows), per_row=per_row)
    ring1 = labels.at[rows].get(mode="fill", fill_value=n)
    ring1 = jnp.where(ring1 >= 0, ring1, n)
    ring2 = labels.at[ring1].get(mode="fill", fill_value=n).reshape(r, -1)
    ring2 = jnp.where(ring2 >= 0, ring2, n)
    union = jnp.sort(jnp.concatenate([ring1, ring2, block], axis=1), axis=1)  # sorted to drop repeats
    repeat = jnp.concatenate([jnp.zeros((r, 1), bool), union[:, 1:] == union[:, :-1]], axis=1)
    d2 = jnp.sum((points.at[union].get(mode="fill", fill_value=jnp.inf) - centre[:, None, :]) ** 2, axis=-1)
    d2 = jnp.where(repeat | (union == rows[:, None]) | (union >= n) | jnp.isnan(d2), jnp.inf, d2)
    neg, order = jax.lax.top_k(-d2, k)
    return jnp.where(jnp.isfinite(neg), jnp.take_along_axis(union, order, axis=1), n)


def cutter_candidates(points, labels, count, rows, *, active: int | None = None, block: int = 8):
    """(R, 2P) candidates for the cells of walkers `rows` by brute force over all walkers:
    their current labels and, for each vertex of their current cell whose circle through the
    walker holds another walker, the walker nearest to that vertex (its true owner: clipping
    by it removes the vertex). Every missing Delaunay neighbour lies in such a circle, so
    rounds of this converge. The last resort of a repair, for a few cells (cost R N P): only
    the first `active` rows are searched (the rest keep their labels and get no owners)."""
    n, p = labels.shape
    active = rows.shape[0] if active is None else min(active, rows.shape[0])
    current = labels.at[rows].get(mode="fill", fill_value=n)
    current = jnp.where(current >= 0, current, n)
    _, _, _, vertices = voronoi_cycles(points, current, rows, max_edges=p)
    live = jnp.arange(p, dtype=jnp.int32) < count.at[rows].get(mode="fill", fill_value=0)[:, None]
    r = active
    pad = -r % block

    def owners(chunk):
        ids, v, ok = chunk
        d = points[None, :, :] - points.at[ids].get(mode="fill", fill_value=jnp.nan)[:, None, :]  # (B, N, 2)
        w = jnp.where(ok, v[..., 2], 1.0)[:, None, :]
        centre = v[..., :2] / w[:, 0, :, None]  # (B, P, 2) vertex positions
        gap = jnp.sum((d[:, :, None, :] - centre[:, None, :, :]) ** 2, axis=-1)  # (B, N, P)
        gap = jnp.where(
            (jnp.arange(n, dtype=jnp.int32)[None, :, None] == ids[:, None, None]) | jnp.isnan(gap), jnp.inf, gap
        )
        nearest = jnp.argmin(gap, axis=1).astype(jnp.int32)  # (B, P)
        violated = ok & (jnp.min(gap, axis=1) < jnp.sum(centre * centre, axis=-1) * (1 - 1e-12))
        return jnp.where(violated, nearest, n)

    chunks = (
        jnp.pad(rows[:r], (0, pad), constant_values=n).reshape(-1, block),
        jnp.pad(vertices[:r], ((0, pad), (0, 0), (0, 0))).reshape(-1, block, p, 3),
        jnp.pad(live[:r], ((0, pad), (0, 0))).reshape(-1, block, p),
    )
    found = jax.lax.map(owners, chunks).reshape(-1, p)[:r]
    found = jnp.concatenate([found, jnp.full((rows.shape[0] - r, p), n, jnp.int32)], axis=0)
    return jnp.concatenate([current, found], axis=1)


class Triangulation(NamedTuple):
    """The device triangulation of `triangulate`, with its certificate."""

    simplices: Int[Array, "S 3"]
    adjacency: Int[Array, "S 3"]
    hull: Bool[Array, " N"]
    certified: Bool[Array, ""]  # the certificate holds and nothing overflowed
    certificate: Certificate
    n_repaired: Int[Array, ""]  # cells redone with more candidates
    rounds: Int[Array, ""]  # repair rounds taken


FIRST_PASS_CANDIDATES = 22  # walkers expected within the first pass's radius


def first_candidates(
    points: Float[Array, "N 2"], rows=None, *, expected: int = FIRST_PASS_CANDIDATES, width: int = 32, per_row: int = 16
):
    """The candidates of walkers `rows` (default all) for the first pass, in block order
    (padding N): the walkers of its grid block (`_cellgrid`) within the radius that holds about
    `expected` of them at the block's density (at most the radius the block
    covers), at most `width`. Returns `(candidates, covered2)`: every walker closer than
    sqrt(covered2) is a candidate (0 where the block or the list was cut short)."""
    n = points.shape[0]
    rows = jnp.arange(n, dtype=jnp.int32) if rows is None else rows
    grid = build_grid(points, grid_side(n))
    ids, d2, r2, complete = block_walkers(points, grid, rows, walker_reach(grid, rows), per_row=per_row)
    inside = jnp.sum(d2 < r2[:, None], axis=1, dtype=jnp.int32)
    radius2 = r2 * jnp.minimum(1.0, expected / jnp.maximum(inside, 1).astype(r2.dtype))
    candidates, fitted = within(ids, d2, jnp.zeros_like(r2), radius2, width, n)
    return candidates, jnp.where(complete & fitted, radius2, 0.0)


def cell_reach2(vertices, count):
    """Squared distance from the walker to its cell's farthest vertex (inf for a vertex at
    infinity)."""
    live = jnp.arange(vertices.shape[-2], dtype=jnp.int32) < count[..., None]
    w = vertices[..., 2]
    d2 = jnp.sum(vertices[..., :2] ** 2, axis=-1) / jnp.where(live & (w > 0), w * w, 1.0)
    return jnp.max(jnp.where(live, jnp.where(w > 0, d2, jnp.inf), 0.0), axis=-1)


def _take_suspects(suspect, capacity: int, rounds):
    """Up to `capacity` suspect walkers (padding N), starting at an offset that moves on each
    round, so that a long list is worked through instead of its head redone."""
    n = suspect.shape[0]
    offset = jnp.mod(rounds * capacity, n)
    rotated = jnp.roll(suspect, -offset)
    picked = jnp.nonzero(rotated, size=capacity, fill_value=n)[0].astype(jnp.int32)
    return jnp.where(picked < n, jnp.mod(picked + offset, n), n).astype(jnp.int32)


def _first_pass(points, rows, *, expected: int, max_edges: int):
    """(labels, count, overflowed, settled) of the cells of walkers `rows` clipped by their
    `first_candidates`; `settled`: Ray et al.'s security radius holds (a cell whose farthest
    vertex is closer than half the radius searched exhaustively is exact, whatever the
    certificate says of its neighbours)."""
    candidates, covered2 = first_candidates(points, rows, expected=expected)
    labels, count, overflowed, vertices = voronoi_cycles(points, candidates, rows, max_edges=max_edges)
    return labels, count, overflowed, (4 * cell_reach2(vertices, count) < covered2) & ~overflowed


def _redone_cells(points, labels, count, rows, local, *, max_edges: int, exact_capacity: int):
    """(labels, count, overflowed) of the cells of walkers `rows` clipped again, by
    `repair_candidates` (`local`) or `cutter_candidates` (the first `exact_capacity` rows)."""
    candidates = jax.lax.cond(
        local,
        lambda: repair_candidates(points, labels, rows, 2 * max_edges),
        lambda: cutter_candidates(points, labels, count, rows, active=exact_capacity),
    )
    return voronoi_cycles(points, candidates, rows, max_edges=max_edges)[:3]


def triangulate(
    points: Float[Array, "N 2"],
    *,
    s_cap: int,
    max_edges: int = 24,
    repair_capacity: int | None = None,
    local_rounds: int = 3,
    exact_capacity: int = 128,
    exact_rounds: int = 6,
    first_pass: int = FIRST_PASS_CANDIDATES,
    mesh=None,
) -> Triangulation:
    """The Delaunay triangulation of `points`, jittable: each cell clipped by its
    `first_candidates`, then repair rounds in which the cells of walkers in a failed
    condition of the certificate (and not settled by the security radius) are redone:
    `local_rounds` rounds with `repair_candidates` (at most `repair_capacity` cells each),
    then `exact_rounds` rounds with `cutter_candidates` (at most `exact_capacity` cells each). Never silently wrong:
    `certified` is False when the certificate still fails or a cell or the triangle list
    overflowed. `repair_capacity` defaults to N / 4 (at least 64); `first_pass` is the
    number of candidates the first pass aims for. `mesh`: a mesh with a "walkers" axis
    (`jaxgeom.walker_mesh`) splits the cells to clip over its devices (`split_rows`): each
    device clips its share of the cells from all the positions; same result."""
    n = points.shape[0]
    repair_capacity = max(64, n // 4) if repair_capacity is None else repair_capacity
    devices = 1 if mesh is None else mesh.shape[WALKER_AXIS]
    all_rows = jnp.arange(n, dtype=jnp.int32)
    labels, count, overflowed, settled = split_rows(
        lambda rows, p: _first_pass(p, rows, expected=first_pass, max_edges=max_edges), mesh, all_rows, n, points
    )
    exact_per_device = -(-exact_capacity // devices)

    def redo(rows, points, labels, count, local):
        return _redone_cells(points, labels, count, rows, local, max_edges=max_edges, exact_capacity=exact_per_device)

    def checks_of(labels, count, overflowed):
        checks = check_cycles(points, _cycles(labels, count, n))
        return checks._replace(suspect=(checks.suspect & ~settled) | overflowed)

    def repair(carry):
        labels, count, overflowed, checks, rounds, repaired = carry
        local = rounds < local_rounds
        rows = _take_suspects(checks.suspect, repair_capacity, rounds)
        rows = jnp.where(local | (jnp.arange(repair_capacity, dtype=jnp.int32) < exact_capacity), rows, n)
        new_labels, new_count, new_over = split_rows(redo, mesh, rows, n, points, labels, count, local)
        labels = labels.at[rows].set(new_labels, mode="drop")
        count = count.at[rows].set(new_count, mode="drop")
        overflowed = overflowed.at[rows].set(new_over, mode="drop")
        return (
            labels,
            count,
            overflowed,
            checks_of(labels, count, overflowed),
            rounds + 1,
            repaired + jnp.sum(rows < n, dtype=jnp.int32),
        )

    zero = jnp.asarray(0, jnp.int32)
    carry = (labels, count, overflowed, checks_of(labels, count, overflowed), zero, zero)
    carry = jax.lax.while_loop(lambda c: jnp.any(c[3].suspect) & (c[4] < local_rounds + exact_rounds), repair, carry)
    labels, count, overflowed, checks, rounds, repaired = carry
    simplices, adjacency, too_many_triangles = emit_triangles(_cycles(labels, count, n), checks, s_cap)
    certified = ~checks.certificate.failed & ~jnp.any(overflowed) & ~too_many_triangles
    return Triangulation(simplices, adjacency, checks.hull, certified, checks.certificate, repaired, rounds)


def rebuilds_on_device(tess: Tessellation) -> bool:
    """Whether `rebuild` builds this kind of graph: 2D, non-periodic, Delaunay."""
    return tess.simplices is not None and tess.dim == 2 and not tess.periodic


def describe_graph(tess: Tessellation) -> str:
    """'a k-NN graph', or the dimension and periodicity of a Delaunay graph, for messages."""
    return "a k-NN graph" if tess.simplices is None else f"{tess.dim}D{' periodic' if tess.periodic else ''}"


def rebuild(tess: Tessellation, points, *, mesh=None) -> Tessellation:
    """The Delaunay `Tessellation` of new positions, built on the device (jittable, vmappable).

    The jittable half of an allocate / update pair (after jax-md's neighbour lists):
    `tess = jaxgeom.delaunay(x0)` allocates on the host, `jaxgeom.rebuild(tess, x)` returns
    the graph of `x` with the same capacities, box and boundary rules, so a loop of rebuilds
    compiles once. Each walker's Voronoi cell is clipped from candidates found in a cell
    list (Ray, Sokolov, Lefebvre and Levy 2018), and the triangles read off the cells are
    certified by the Delaunay lemma (module docstring of `jaxgeom.tessellation._cellclip`). A rebuild
    that cannot be certified (candidates missing in a strongly clustered swarm, co-circular
    ties it cannot resolve, a capacity exceeded) sets `overflow`: then rebuild with
    `jaxgeom.delaunay` on the host (`simulate(rebuild="device")` does, and counts it).

    **Arguments:**

    - `tess`: a 2D, non-periodic Delaunay `Tessellation` (3D and periodic graphs: not yet).
    - `points`: (N, 2) new positions, the dtype of `tess.points`.
    - `mesh`: None, or a `jax.sharding.Mesh` with a "walkers" axis (`jaxgeom.walker_mesh()`):
      each of its devices clips its share of the cells (from all the positions); the same graph.

    **Returns:** the `Tessellation` of `points`; when `overflow` is set its arrays are not a
    valid Delaunay graph and must not be used.
    """
    if not isinstance(tess, Tessellation) or tess.simplices is None:
        raise TypeError(
            "jaxgeom.rebuild takes a Delaunay jaxgeom.Tessellation as `tess` (from jaxgeom.delaunay); "
            f"got {type(tess).__name__ if not isinstance(tess, Tessellation) else 'a k-NN graph'}."
        )
    if not rebuilds_on_device(tess):
        raise ValueError(
            f"jaxgeom.rebuild builds 2D, non-periodic graphs on the device so far; this graph is "
            f"{describe_graph(tess)}. Rebuild it with jaxgeom.delaunay."
        )
    points = jnp.asarray(points)
    if points.shape != tess.points.shape or points.dtype != tess.points.dtype:
        raise ValueError(
            f"`points` must have the shape and dtype of tess.points, {tess.points.shape} "
            f"{tess.points.dtype}; got {points.shape} {points.dtype}."
        )
    check_mesh(mesh, None, "", WALKER_AXIS)
    return rebuild_unchecked(tess, points, mesh)


@functools.partial(jax.jit, static_argnames="mesh")
def rebuild_unchecked(tess: Tessellation, points, mesh=None) -> Tessellation:
    """`rebuild` without the host checks (inside a trace)."""
    cap = tess.capacity
    result = triangulate(points, s_cap=cap.simplices, mesh=mesh)
    new = planar_tessellation(points, result.simplices, result.adjacency, tess.box, k_cap=cap.neighbors)
    return eqx.tree_at(lambda t: t.overflow, new, new.overflow | ~result.certified)
