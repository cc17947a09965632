"""Voronoi faces from the Delaunay dual, in O(simplices): 3D facet areas, cell volumes,
centroids and vertex counts without building a polytope per cell.

Every simplex s is cut into signed orthoschemes (x_a, m_ab, c_T, C_s), one per flag
(vertex a, edge ab, triangle T ⊃ ab, s), with m_ab the edge's midpoint, c_T the triangle's
circumcentre and C_s the simplex's. Their legs are orthogonal: r_ab / 2 along the edge, the
signed height h = (c_T - m_ab) . w (w: in T's plane, across ab, towards T's third vertex) and
the signed piece p = (C_s - c_T) . u (u: T's normal, towards s's fourth vertex). So

- the Voronoi edge dual to T has length p_s + p_t, summed over T's two simplices;
- the face shared by a and b (on their bisector plane) has area 1/2 sum_T h L_T, a signed
  decomposition about m_ab that needs no cyclic order of its vertices;
- the cell of a has volume sum r h p / 12 over its flags and first moment sum over the
  orthoschemes of their volume times their centroid (the mean of their four vertices).

A triangle with one simplex lies on the hull: its Voronoi edge, and every face around it, is
unbounded. Open 3D graphs find those by sorting the faces' vertex ids (`hull_faces`); 2D
graphs at the hull walkers' extreme neighbours. In a (non-periodic) box the pieces that reach
a wall, and the hull's unbounded ones, are cut to it (`_dualclip`) and the walls' faces follow
from their edges; vertex counts then add the clipped cells' vertices on the walls.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base._compact import flagged_ids
from ..base._simplex import dot
from ..tessellation._graph import (
    Tessellation,
    lower_bound_in_rows,
    neighbor_distances,
    simplex_vertices,
    take_or_zero,
)
from ._boxclip import ROUNDING_ULPS, map_flagged_rows, scan_live_chunks
from ._dualclip import (
    CORNER_WALLS,
    EDGE_WALLS,
    FACES_3D,
    box_edge_faces,
    cells_near_box_edges,
    clipped_sums,
    dual_centres,
    near_walls,
    order_in_rows,
    triangle_circumcentre,
)


def simplex_flags_3d(p, centre, ok, face_centres, face_ok, heights, lengths, normals):
    """The flags of one tetrahedron p (4, 3), coordinates relative to its first vertex, with
    its circumcentre and its faces' (4, 3) in that frame, whether each is not flat, and its
    faces' heights h, edge lengths and unit normals (`dual_centres`).

    Returns per face f (opposite vertex f) and its edge e (FACES_3D order, edge e opposite the
    face's e-th vertex): `piece` (4,) p_(s,T), `volume` (4, 3) r h p / 12 (each
    of the edge's two ends gets it), `weighted` (4, 3, 3) the volume times m_ab + c_T + C (the
    orthoscheme at end x has its centroid at (x + m_ab + c_T + C) / 4: `_sums_at_vertices`
    takes the moments about the ends from it). The faces' normals are oriented towards the
    opposite vertex (`_outer_normal` orients the hull's the same way)."""
    pieces, volumes, weighted = [], [], []
    for o, face in enumerate(FACES_3D):
        c_t, tri_ok = face_centres[o], face_ok[o]
        normal = towards_vertex(normals[o], p, o, face[0])
        piece = jnp.where(ok & tri_ok, dot(centre - c_t, normal), 0.0)
        pieces.append(piece)
        v_row, w_row = [], []
        for e in range(3):  # edge opposite the face's e-th vertex: (face[e+1], face[e+2])
            middle = 0.5 * (p[face[(e + 1) % 3]] + p[face[(e + 2) % 3]])
            volume = lengths[o, e] * heights[o, e] * piece / 12.0
            v_row.append(volume)
            w_row.append(volume * (middle + c_t + centre))
        volumes.append(jnp.stack(v_row))
        weighted.append(jnp.stack(w_row))
    return jnp.stack(pieces), jnp.stack(volumes), jnp.stack(weighted)


def towards_vertex(normal, p, o, corner):
    """`normal` of the face opposite vertex `o` of the tetrahedron p (4, 3), turned towards
    that vertex (`corner`: a vertex of the face)."""
    return jnp.where(dot(normal, p[o] - p[corner]) < 0, -normal, normal)


FACE_VERTS = jnp.asarray(FACES_3D, jnp.int32)  # (4, 3)
# edge e of face f joins FACE_VERTS[f, (e + 1) % 3] and FACE_VERTS[f, (e + 2) % 3]
EDGE_ENDS = jnp.asarray(
    [[[FACES_3D[f][(e + 1) % 3], FACES_3D[f][(e + 2) % 3]] for e in range(3)] for f in range(4)], jnp.int32
)  # (4, 3, 2)


def _face_keys(tess: Tessellation):
    """(4S, 3) int32 keys identifying each simplex face of an open or boxed graph (its sorted
    vertex ids; `hull_faces` is not asked on a torus, which has no hull); padding faces get key N."""
    ids = tess.simplices[:, FACE_VERTS]  # (S, 4, 3)
    a, b, c = ids[..., 0], ids[..., 1], ids[..., 2]
    low, high = jnp.minimum(jnp.minimum(a, b), c), jnp.maximum(jnp.maximum(a, b), c)
    keys = jnp.stack([low, a + b + c - low - high, high], axis=-1)  # sorted (argsort: 20x the time)
    return jnp.where(tess.simplex_mask[:, None, None], keys, tess.n_points).reshape(-1, 3)


# the hull's candidate faces are sorted alone when at most 1/HULL_SHARE of all faces, or at
# most FEW_AT_LEAST (a uniform sample's: 516 of 295k faces at N = 1e4, 754 of 2.9M at 1e5;
# from 1/16 to 1/256, interleaved, float32: boxed `voronoi_facets` 1e5 1908 -> 1812 ms,
# clipped `voronoi_volumes` 556 -> 486 ms, 1e4 248 -> 235 and 113 -> 105 ms)
HULL_SHARE = 256
FEW_AT_LEAST = 1024


def hull_faces(tess: Tessellation, proper=None):
    """(S, 4) whether each simplex face lies on the hull: the only simplex with its key
    (`_face_keys`) in a sort of all of them. With `proper` (S,) (the simplices that are not
    flat), a flat simplex lying on the hull (co-planar hull walkers, a lattice's) is dropped:
    its faces are not on the hull, and those of the proper simplices it covers are.

    Only faces of three hull walkers (`tess.hull`, the vertices of the faces with one simplex)
    can be either, so when they are few (a uniform sample: a few hundred) they are sorted
    alone; otherwise (a lattice's flat outer layer) all faces are."""
    keys = _face_keys(tess)
    total = keys.shape[0]
    walker_on_hull = jnp.concatenate([tess.hull, jnp.zeros(1, bool)])
    candidate = jnp.all(walker_on_hull[keys], axis=1)

    def few(ids):
        some = jnp.where((ids < total)[:, None], keys[jnp.minimum(ids, total - 1)], tess.n_points)
        return _scatter_back(_unpaired(some, tess.n_points), ids, total)

    alone, partner = _few_or_all(candidate, few, lambda: _unpaired(keys, tess.n_points))
    raw = alone.reshape(-1, 4)
    if proper is None:
        return raw
    partner = partner.reshape(-1, 4)
    flat_on_hull = ~proper & tess.simplex_mask & jnp.any(raw, axis=1)
    covered = (partner >= 0) & flat_on_hull[jnp.maximum(partner, 0) // 4]
    return proper[:, None] & (raw | covered)


def _few_or_all(marked, few, every, share: int | None = None):
    """`few(ids)` of the `marked` (M,) entries' ids (padded with M) when they are at most
    1/`share` of them (default HULL_SHARE) or FEW_AT_LEAST, else `every()`: the hull's faces
    are a few hundred of millions in a uniform sample, and most of them on a lattice's flat
    outer layer."""
    total = marked.size
    size = max(FEW_AT_LEAST, total // (HULL_SHARE if share is None else share))
    ids = flagged_ids(marked.ravel(), size, total)
    return jax.lax.cond(jnp.sum(marked, dtype=jnp.int32) <= size, lambda: few(ids), every)


def _unpaired(keys, n: int):
    """(alone, partner) of face keys (F, m) (padding: first key n): whether each is the only one
    with its key, and the other face with its key (-1 if none)."""
    order = jnp.lexsort(tuple(keys[:, k] for k in reversed(range(keys.shape[1]))))
    sorted_keys = keys[order]
    same = jnp.all(sorted_keys[1:] == sorted_keys[:-1], axis=1)
    after, before = jnp.concatenate([same, jnp.zeros(1, bool)]), jnp.concatenate([jnp.zeros(1, bool), same])
    alone = ~(after | before) & (sorted_keys[:, 0] < n)
    partner_sorted = jnp.where(after, jnp.roll(order, -1), jnp.where(before, jnp.roll(order, 1), -1))
    unsort = lambda a, fill: jnp.full(a.shape, fill, a.dtype).at[order].set(a)  # noqa: E731
    return unsort(alone, False), unsort(partner_sorted.astype(jnp.int32), -1)


def _scatter_back(found, ids, total: int):
    """`_unpaired` of the faces `ids` (padding: total) as arrays over all `total` faces."""
    alone, partner = found
    partner = jnp.where(partner >= 0, ids[jnp.maximum(partner, 0)], -1)
    return (
        jnp.zeros(total, bool).at[ids].set(alone, mode="drop"),
        jnp.full(total, -1, jnp.int32).at[ids].set(partner, mode="drop"),
    )


SHIFT_CODES = 5  # a relative periodic shift's components lie in -2..2 (images one box away, seen from either end)


def _row_keys(neighbors, shifts):
    """int32 keys of neighbour `neighbors` at relative periodic `shifts` (or None): the index,
    and on a torus the image, in one number (padding N sorts last)."""
    if shifts is None:
        return neighbors
    code = jnp.zeros(neighbors.shape, jnp.int32)
    for axis in range(shifts.shape[-1]):
        code = code * SHIFT_CODES + (shifts[..., axis].astype(jnp.int32) + SHIFT_CODES // 2)
    return neighbors * SHIFT_CODES ** shifts.shape[-1] + code


def _sorted_rows(tess: Tessellation):
    """Every neighbour row's keys (`_row_keys`) in ascending order and the slot each came from,
    flat (N K,), and whether the rows came sorted (each slot its own), for `_find_slots`'s
    binary searches."""
    n, k = tess.neighbors.shape
    row_keys = _row_keys(tess.neighbors, tess.neighbor_shifts)
    slots = jnp.broadcast_to(jnp.arange(k, dtype=jnp.int32), (n, k))
    # `delaunay`'s rows come sorted; a graph whose rows were edited is sorted here
    came_sorted = jnp.all(row_keys[:, 1:] >= row_keys[:, :-1])
    sorted_keys, sorted_slots = jax.lax.cond(
        came_sorted,
        lambda: (row_keys, slots),
        lambda: jax.lax.sort((row_keys, slots), dimension=1, num_keys=1),
    )
    return sorted_keys.ravel(), sorted_slots.ravel(), came_sorted


def _find_slots(tess: Tessellation, rows, ends, shifts):
    """(first, second), each (...,): the flat slot (row * K + slot) of every edge `ends` (..., 2)
    seen from its first end and from its second; N * K where the other end is not a neighbour
    (a zero-measure contact) or on padding. `shifts` (..., 2, d): the ends' periodic images, or
    None; `rows`: `_sorted_rows(tess)`.

    Every edge finds its slot by a binary search of its row's sorted keys: log2 K gathers per
    edge instead of comparing it with all K."""
    n, k = tess.neighbors.shape
    sorted_keys, sorted_slots, came_sorted = rows
    index = []
    for side in (0, 1):
        rows, targets = ends[..., side], ends[..., 1 - side]
        rel = None if shifts is None else shifts[..., 1 - side, :] - shifts[..., side, :]
        wanted = _row_keys(targets, rel)
        rows_in = jnp.minimum(rows, n - 1)
        base = rows_in * k
        at = base + jnp.minimum(lower_bound_in_rows(sorted_keys.reshape(n, k), rows_in, wanted), k - 1)
        found = (sorted_keys[at] == wanted) & (rows < n) & (targets < n)
        # rows that came sorted hold each slot in its own place: no gather of the slots
        slot = jax.lax.cond(came_sorted, lambda at=at, base=base: at - base, lambda at=at: sorted_slots[at])
        index.append(jnp.where(found, base + slot, n * k))
    return tuple(index)


EDGES_3D = tuple((a, b) for a in range(4) for b in range(a + 1, 4))  # a simplex's 6 edges
# each flag's edge (EDGE_ENDS) among EDGES_3D, and whether its ends are in the other order
FLAG_EDGE = np.asarray([EDGES_3D.index(tuple(sorted(e))) for e in EDGE_ENDS.reshape(-1, 2).tolist()], np.int32)
FLAG_REVERSED = jnp.asarray([e[0] > e[1] for e in EDGE_ENDS.reshape(-1, 2).tolist()], bool)


def edge_slot_index(tess: Tessellation, rows):
    """(first, second), each (S, 6): the flat slot (`_find_slots`) of every simplex edge
    (EDGES_3D order) seen from its first end and from its second; `rows`: `_sorted_rows(tess)`."""
    pairs = jnp.asarray(EDGES_3D, jnp.int32)
    shifts = None if tess.simplex_shifts is None else tess.simplex_shifts[:, pairs]
    return _find_slots(tess, rows, tess.simplices[:, pairs], shifts)


def face_flag_slots(edge_index, simplex, opposite):
    """(2, F, 3) the slots of the three flags (EDGE_ENDS order) of each face (F,), the one
    `opposite` a vertex of `simplex`, seen from its edge's first end (EDGE_ENDS), then from its
    second, from `edge_slot_index` (one gather of each simplex's six edges per side)."""
    first, second = (side[simplex] for side in edge_index)  # (F, 6)
    edge = jnp.asarray(FLAG_EDGE.reshape(4, 3))[opposite]  # (F, 3)
    reversed_ = FLAG_REVERSED.reshape(4, 3)[opposite]
    forward, backward = (jnp.take_along_axis(rows, edge, axis=1) for rows in (first, second))
    return jnp.stack([jnp.where(reversed_, backward, forward), jnp.where(reversed_, forward, backward)])


# the two flags (places in EDGE_ENDS order) of each simplex edge (EDGES_3D order)
EDGE_FLAGS = tuple(tuple(f for f in range(12) if FLAG_EDGE[f] == e) for e in range(6))


def _per_edge(values, combine):
    """(S, 6) the flag `values` (S, 4, 3) of each simplex edge's two flags, combined."""
    flat = values.reshape(values.shape[0], 12)
    return jnp.stack([combine(flat[:, a], flat[:, b]) for a, b in EDGE_FLAGS], axis=1)


def _sum_into_slots(values, index, n: int, k: int):
    """(N, K) sums of `values` (the same for both ends of each edge) at `_find_slots`'s `index`
    (two arrays of values' shape)."""
    return _add_into_slots(jnp.zeros(n * k + 1, values.dtype), values, index)[:-1].reshape(n, k)


def _add_into_slots(sums, values, index):
    """`sums` (N K + 1,), the last for edges without a slot, plus `values` at both of
    `_find_slots`'s `index`."""
    for side in index:
        sums = sums.at[side.ravel()].add(values.ravel())
    return sums


def _sums_at_vertices(local_ends, values, weighted, points):
    """Per simplex and vertex: the sum of `values` (S, ...), one per edge `local_ends` (..., 2)
    of each simplex (its vertices' positions in the row), counted at both ends, and the first
    moments about the vertex of the orthoschemes (d-simplices of volume `values`, centroid
    (end + q) / (d + 1)) from `weighted` (S, ..., d) = values * q: sum (weighted - d value end)
    / (d + 1), `points` (S, m, d) the simplices' vertices in the frame of `weighted`.
    Returns (S, m) and (S, m, d)."""
    s, m, d = points.shape
    pairs = np.asarray(local_ends).reshape(-1, 2)  # static: the same for every simplex
    values = values.reshape(s, -1)
    weighted = jnp.where((values != 0)[..., None], weighted.reshape(s, -1, d), 0.0)  # flat ones: 0, not 0 * inf
    at_ends = [[f for f, pair in enumerate(pairs.tolist()) if v in pair] for v in range(m)]
    at = lambda a, flags: sum(a[:, f] for f in flags)  # noqa: E731  # sums of static slices fuse into one loop
    totals = jnp.stack([at(values, at_ends[v]) for v in range(m)], axis=1)
    moments = (jnp.stack([at(weighted, at_ends[v]) for v in range(m)], axis=1) - d * totals[..., None] * points) / (
        d + 1
    )
    return totals, moments


def _scatter_at_vertices(simplices, totals, moments, n: int):
    """(N,) and (N, d): the per-simplex-vertex `totals` (S, m) and `moments` (S, m, d) summed
    per walker; the scatter takes one entry per simplex vertex (4 in 3D, not 24 flags)."""
    zeros = (jnp.zeros(n + 1, totals.dtype), jnp.zeros((n + 1, moments.shape[-1]), moments.dtype))
    volumes, first_moments = _add_at_vertices(zeros, simplices, totals, moments)
    return volumes[:n], first_moments[:n]


def _add_at_vertices(sums, simplices, totals, moments):
    """`sums` ((N + 1,), (N + 1, d)), the last for padding, plus the per-simplex-vertex
    `totals` (S, m) and `moments` (S, m, d) at their walkers (`_scatter_at_vertices`)."""
    volumes, first_moments = sums
    ids = simplices.ravel()
    return volumes.at[ids].add(totals.ravel()), first_moments.at[ids].add(moments.reshape(-1, moments.shape[-1]))


def _sum_at_ends(simplices, local_ends, values, weighted, points, n: int):
    """Per walker: `_sums_at_vertices` scattered to the simplices' walkers, (N,) and (N, d)."""
    totals, moments = _sums_at_vertices(local_ends, values, weighted, points)
    return _scatter_at_vertices(simplices, totals, moments, n)


# simplices per block of the 3D dual's per-simplex stage: a block's temporaries stay in cache
# (periodic `voronoi_facets`, float32: 1e5 1.20 -> 1.05 s and 1e6 16.4 -> 14.4 s from 2^15 to
# 2^13; from 2^13 to 2^12 at 1e5, interleaved: float64 periodic 638 -> 568 ms, boxed 1222 ->
# 1184 ms, float32 periodic 495 -> 487 ms; the same at 1e4)
SIMPLEX_BLOCK = 1 << 12


def block_layout(s: int, most: int) -> tuple[int, int]:
    """(blocks, size): the fewest blocks of at most `most` of `s` items, as even as they can be
    (S on the capacity ladder then pads little: 73,728 in three blocks of 24,576)."""
    blocks = -(-s // most)
    return blocks, -(-s // blocks)


def _in_blocks(tess: Tessellation, per_simplex, sums):
    """`per_simplex(sub, sums)` -> (out, sums) over all simplices, at most SIMPLEX_BLOCK at a
    time (`lax.scan`): `out` a dict of (S_b, ...) arrays of the simplices of `sub` (`tess` cut
    to a block of them), stacked, and `sums` a pytree of arrays added to block after block
    (in place: what is summed per walker or slot is never stacked per simplex). A block's
    temporaries, ~1.7 kB per simplex when unblocked (11 GiB at N = 1e6 in 3D), take one
    block's room."""
    s = tess.simplices.shape[0]
    if s <= SIMPLEX_BLOCK:
        return per_simplex(tess, sums)
    blocks, size = block_layout(s, SIMPLEX_BLOCK)
    pad = blocks * size - s
    cut = (
        lambda a, fill: jnp.pad(a, [(0, pad)] + [(0, 0)] * (a.ndim - 1), constant_values=fill).reshape(  # noqa: E731
            blocks, size, *a.shape[1:]
        )
    )
    simplices = cut(tess.simplices, tess.n_points)
    shifts = None if tess.simplex_shifts is None else cut(tess.simplex_shifts, 0)

    def block(acc, parts):
        ids, moved = parts
        sub = eqx.tree_at(lambda t: (t.simplices, t.simplex_shifts), tess, (ids, moved), is_leaf=lambda x: x is None)
        out, acc = per_simplex(sub, acc)
        return acc, out

    def empty(acc, parts):
        shapes = jax.eval_shape(block, acc, parts)[1]
        return acc, jax.tree.map(functools.partial(_padding_like, no_slot=tess.neighbors.size), shapes)

    def live_block(acc, parts):  # a block of padding alone (past a compacted graph's simplices) is skipped
        return jax.lax.cond(jnp.any(parts[0][:, 0] < tess.n_points), block, empty, acc, parts)

    sums, out = jax.lax.scan(live_block, sums, (simplices, shifts))
    return jax.tree.map(lambda a: a.reshape(blocks * size, *a.shape[2:])[:s], out), sums


def _padding_like(shape, no_slot: int):
    """A padding block's stage output of this shape: False or zero, and for the slot indices
    (int32) `_find_slots`' "no slot" N K, as padding simplices get from it."""
    return jnp.full(shape.shape, no_slot if shape.dtype == jnp.int32 else 0, shape.dtype)


def _simplex_stage_3d(tess: Tessellation, sums, rows):
    """Per simplex, everything `dual_faces_3d` needs of its geometry (module docstring): the
    areas its flags add to its 6 edges' faces (S, 6), the volumes and first moments its
    orthoschemes add to its 4 walkers' cells (S, 4), (S, 4, 3), its circumcentre (S, 3), whether
    it is not flat and counted as a vertex (S,); in a box also its faces' centres, their
    flatness and whether their pieces reach a wall (clipped by `_clip_to_box`, not summed
    here; the hull's normals are computed there again, `_outer_normal`); and the neighbour
    slots of its edges
    (`edge_slot_index`, `rows`: `_sorted_rows` of the whole graph; not on a torus, where only
    the areas need them). The areas, volumes and moments are added to `sums` (flat slots
    (N K + 1,), per walker (N + 1,) and (N + 1, 3)) instead. One block of `_in_blocks`."""
    verts = simplex_vertices(tess)  # (S, 4, 3), images applied
    centres, ok, proper, face_centres, face_ok, measures = dual_centres(verts)
    origin = verts[:, :1]
    heights = measures[0]
    pieces, volumes, weighted = jax.vmap(simplex_flags_3d)(
        verts - origin, centres - origin[:, 0], ok, face_centres - origin, face_ok, *measures
    )
    mask = tess.simplex_mask
    edge_index = edge_slot_index(tess, rows)
    out = {"centres": centres, "ok": ok, "proper": proper}
    if tess.simplex_shifts is None:
        out["edge_index"] = edge_index
    keep = mask[:, None]
    if tess.box is not None and tess.simplex_shifts is None:
        box = tess.box.astype(verts.dtype)
        # pieces reaching a wall are clipped: those leaving the box, and those with a point on a
        # wall (a walker on it), whose edges there bound the cell's wall face
        reaches = lambda y: jnp.any(near_walls(y, box), axis=-1)  # noqa: E731
        centre_out = reaches(centres)
        on_wall = jnp.any(reaches(verts[:, FACE_VERTS]), axis=-1)  # (S, 4) a face with a walker on a wall
        outside = mask[:, None] & (centre_out[:, None] | reaches(face_centres) | on_wall)  # (S, 4)
        keep = mask[:, None] & ~outside
        out.update(face_centres=face_centres, face_ok=face_ok, outside=outside)
    keep = jnp.broadcast_to(keep, pieces.shape)[:, :, None]
    # face areas: each simplex adds its own share 1/2 h p_s of every flag's edge (no pairing),
    # summed over the edge's two flags first
    areas = _add_into_slots(
        sums[0], _per_edge(jnp.where(keep, 0.5 * heights * pieces[:, :, None], 0.0), jnp.add), edge_index
    )
    # volumes and first moments: every flag's orthoscheme belongs to both ends of its edge
    totals, moments = _sums_at_vertices(EDGE_ENDS, jnp.where(keep, volumes, 0.0), weighted, verts - origin)
    return out, (areas, *_add_at_vertices(sums[1:], tess.simplices, totals, moments))


def dual_faces_3d(tess: Tessellation, *, counts: bool = True):
    """Per walker and neighbour slot: (areas (N, K), unbounded (N, K)); per walker: volumes
    (N,), first moments about the walker (N, 3), Voronoi vertex counts (N, -1 where a count's
    table overflowed: `_vertex_counts`, boxed `packed_slots`; zeros without `counts`), (N,)
    False (3D keeps flat simplices: they add nothing) and the faces on the box walls (N, 6),
    from the Delaunay dual (module docstring).
    With a (non-periodic) box every cell is clipped to it (`_dualclip`); otherwise hull cells'
    volumes, moments and counts are meaningless (callers mask them with `tess.hull`)."""
    tess = with_sorted_simplices(tess)
    n, k = tess.neighbors.shape
    mask = tess.simplex_mask
    boxed = tess.box is not None and tess.simplex_shifts is None
    dtype = tess.points.dtype
    sums = (jnp.zeros(n * k + 1, dtype), jnp.zeros(n + 1, dtype), jnp.zeros((n + 1, 3), dtype))
    stage, (slot_areas, walker_volumes, walker_moments) = _in_blocks(
        tess, functools.partial(_simplex_stage_3d, rows=_sorted_rows(tess)), sums
    )
    centres, proper = stage["centres"], stage["proper"]
    # open and boxed: the hull's faces bound the unbounded cells (a torus has none)
    if tess.simplex_shifts is not None:
        hull_face = jnp.zeros(tess.simplices.shape, bool)
    else:
        hull_face = hull_faces(tess, proper & mask if boxed else None)
    edge_index = stage.get("edge_index")
    areas, cell_volume, moments = slot_areas[:-1].reshape(n, k), walker_volumes[:n], walker_moments[:n]
    wall_areas = jnp.zeros((n, 6), areas.dtype)
    if boxed:
        areas, cell_volume, moments, wall_areas, wall_lengths, edges = _clip_to_box(
            tess,
            (centres, stage["face_centres"], stage["ok"], stage["face_ok"]),
            hull_face,
            stage["outside"],
            edge_index,
            areas,
            cell_volume,
            moments,
        )
        unbounded = jnp.zeros((n, k), bool)
    elif tess.simplex_shifts is not None:  # a torus: every cell is bounded
        unbounded = jnp.zeros((n, k), bool)
    else:
        per_flag = jnp.broadcast_to(hull_face[:, :, None], (*hull_face.shape, 3))
        ray = _per_edge(per_flag, jnp.logical_or).astype(jnp.int32)
        unbounded = jnp.zeros(n * k + 1, jnp.int32)
        for side in edge_index:
            unbounded = unbounded.at[side.ravel()].max(ray.ravel())
        unbounded = unbounded[:-1].reshape(n, k) > 0
    vertices = jnp.zeros(n, jnp.int32)
    if counts:
        counted = jnp.broadcast_to((mask & proper)[:, None], tess.simplices.shape)
        if boxed:
            counted = counted & _counted_in_box(tess, centres, wall_areas)
        vertices = _vertex_counts(tess, centres[:, None, :] - simplex_vertices(tess), counted)
        if boxed:
            vertices = jnp.where(
                vertices < 0, vertices, vertices + _wall_vertices(tess, wall_areas, wall_lengths, edges)
            )
            _, first, width = wall_lengths
            vertices = jnp.where(first + width > len(wall_lengths[0]), -1, vertices)  # past the packed table
    return areas, unbounded, cell_volume, moments, vertices, jnp.zeros(n, bool), wall_areas


def with_sorted_simplices(tess: Tessellation):
    """`tess` with each simplex's walkers in ascending order (their periodic images with them):
    every face then lists its walkers in one order in both its simplices (`dual_centres`)."""
    order = order_in_rows(tess.simplices)
    take = lambda a: jnp.take_along_axis(a, order if a.ndim == 2 else order[..., None], axis=1)  # noqa: E731
    shifts = None if tess.simplex_shifts is None else take(tess.simplex_shifts)
    return eqx.tree_at(
        lambda t: (t.simplices, t.simplex_shifts), tess, (take(tess.simplices), shifts), is_leaf=lambda x: x is None
    )


# the simplices with a tier-0 walker are computed alone when at most this share of all (a
# uniform sample: 35% at N = 1e4, 18% at 1e5, 13% at 3e5; most of a few hundred walkers')
BOUNDARY_SHARE = 2


def tier0_volumes_3d(tess: Tessellation):
    """(N,) the volumes of the tier-0 cells of a boxed 3D graph clipped to the box (others:
    meaningless), from `dual_faces_3d` of the simplices with a tier-0 walker alone: they hold
    every flag of those cells, the hull's faces and every piece that reaches a wall on their
    behalf. Cut to 1/BOUNDARY_SHARE of the capacity when they fit, the blocks of padding
    skipped (`_in_blocks`): uniform walkers, float32, 1.19 -> 0.66 s at N = 1e5 and 153 ->
    108 ms at 1e4 (the cut and the fallback compile as one program: ~1.4x the time)."""
    volumes = lambda t: dual_faces_3d(t, counts=False)[2]  # noqa: E731
    if tess.simplices.shape[0] // BOUNDARY_SHARE < 2 * SIMPLEX_BLOCK:  # small graphs: all of them
        return volumes(tess)
    tier0 = (tess.tier == 0).at[tess.simplices].get(mode="fill", fill_value=False)  # (S, 4)
    cut = lambda ids: eqx.tree_at(  # noqa: E731
        lambda t: t.simplices, tess, tess.simplices.at[ids].get(mode="fill", fill_value=tess.n_points)
    )
    return _few_or_all(
        tess.simplex_mask & jnp.any(tier0, axis=1), lambda ids: volumes(cut(ids)), lambda: volumes(tess), BOUNDARY_SHARE
    )


def _clip_to_box(tess: Tessellation, centres, hull_face, outside, edge_index, areas, cell_volume, moments):
    """Add the clipped pieces (`_dualclip`) to the areas, volumes and moments of the pieces
    inside the box, and the walls' faces: (areas, volumes, moments, wall areas (N, 6), the
    segments' lengths on each wall per slot (packed: `packed_slots`'s table (size, 6), each
    walker's first place and row width (N,)), and what `box_edge_faces` counts).
    `edge_index` (first, second) (S, 6): `edge_slot_index`."""
    n, k = tess.neighbors.shape
    packing = packed_slots(tess)
    area_add, wall_lengths, volume_add, moment_add, wall_area, wall_moment = clipped_sums(
        tess,
        centres,
        hull_face,
        outside,
        _hull_normal_sums(tess, hull_face, edge_index, n * k),
        functools.partial(face_flag_slots, edge_index),
        packing[:2],
    )
    areas = areas + area_add.reshape(n, k)
    edge_area, edge_moment, real, inner, corners = box_edge_faces(
        tess, cells_near_box_edges(tess, centres[0], centres[2])
    )
    wall_area, wall_moment = wall_area + edge_area, wall_moment + edge_moment
    box = tess.box.astype(tess.points.dtype)
    distance = jnp.concatenate([box[1] - tess.points, tess.points - box[0]], axis=1)  # (N, 6)
    cell_volume = cell_volume + volume_add + jnp.sum(distance * wall_area, axis=1) / 3.0
    moments = moments + moment_add + jnp.sum(distance[:, :, None] * wall_moment, axis=1) / 4.0
    return areas, cell_volume, moments, wall_area, (wall_lengths, *packing[2:]), (real, inner, corners)


def packed_slots(tess: Tessellation):
    """(pack, size, first, width): a table per neighbour slot packed to the rows' used widths
    (`width` (N,): up to the last neighbour; `first` (N,): each walker's first place) in `size`
    places, 2 (2 N + S) where less than N K: a bound of the directed edges of a 3D
    triangulation of N walkers in S simplices (Euler: E = N - 1 + S + H / 2, with H <= 2 N - 4
    hull triangles), so Delaunay rows fit (uniform, N = 1e5: 33% of N K, the rows' common
    width being the widest's). `pack(slots)`: the places of flat slots (size for N K, padding,
    and for a slot past `size`: the walkers with first + width > size, which `dual_faces_3d`
    reports)."""
    n, k = tess.neighbors.shape
    size = min(n * k, 2 * (2 * n + tess.simplices.shape[0]))
    width = jnp.max(jnp.where(tess.neighbors < n, jnp.arange(1, k + 1, dtype=jnp.int32), 0), axis=1)
    first = jnp.cumsum(width, dtype=jnp.int32) - width

    def pack(slots):
        place = first.at[slots // k].get(mode="fill", fill_value=size) + slots % k
        return jnp.where((slots < n * k) & (place < size), place, size)

    return pack, size, first, width


def _outer_normal(verts, opposite):
    """(3,) the unit normal of the face `opposite` a vertex of one simplex (`verts` (4, 3)),
    away from that vertex: the stage's (`dual_centres`, oriented as in `simplex_flags_3d`, bit
    for bit), computed for the faces that need it (the hull's) instead of kept for all."""
    face = FACE_VERTS[opposite]
    corners = verts[face]
    normal = triangle_circumcentre(corners[0], corners[1], corners[2])[-1]
    return -towards_vertex(normal, verts - verts[0], opposite, face[0])


def _hull_normal_sums(tess: Tessellation, hull_face, edge_index, slots: int):
    """(slots + 1, 3) per neighbour slot the sum of the outer normals of the hull triangles at
    its edge (a hull edge has two), over the hull's faces alone when they are few (`_few_or_all`)."""
    total = hull_face.size
    dtype = tess.points.dtype

    def add(faces):  # faces (M,): the sum over their flags, each at the slot seen from both ends
        real = faces < total
        face = jnp.minimum(faces, total - 1)
        slot = face_flag_slots(edge_index, face // 4, face % 4).reshape(2 * len(faces), 3)
        slot = jnp.where(jnp.concatenate([real, real])[:, None], slot, slots)
        verts = simplex_vertices(eqx.tree_at(lambda t: t.simplices, tess, tess.simplices[face // 4]))
        outer = jnp.where(real[:, None], jax.vmap(_outer_normal)(verts, face % 4), 0.0)
        values = jnp.broadcast_to(outer[:, None, :], (len(faces), 3, 3))
        values = jnp.concatenate([values, values])
        return jnp.zeros((slots + 1, 3), dtype).at[slot.ravel()].add(values.reshape(-1, 3))

    def every():  # all faces in their (S, 4) layout: each flag's slots are its edge's (no gather of ids)
        faces = jnp.arange(4, dtype=jnp.int32)
        normals = jax.vmap(lambda v: jax.vmap(_outer_normal, (None, 0))(v, faces))(simplex_vertices(tess))  # (S, 4, 3)
        outer = jnp.where(hull_face[..., None], normals, 0.0).reshape(-1, 3)
        values = jnp.broadcast_to(outer.reshape(*hull_face.shape, 1, 3), (*hull_face.shape, 3, 3)).reshape(-1, 3)
        sums = jnp.zeros((slots + 1, 3), dtype)
        for side in edge_index:  # both ends of each edge get the normal: their order does not matter
            sums = sums.at[side[:, FLAG_EDGE].ravel()].add(values)
        return sums

    return _few_or_all(hull_face, add, every)


def _counted_in_box(tess: Tessellation, centres, wall_areas):
    """(S, 4) whether each simplex's circumcentre counts as a vertex of each of its walkers'
    clipped cells apart from their wall faces' (`_wall_vertices`): inside the box, or on a wall
    (to rounding) where the cell has no face (it touches the wall at that vertex)."""
    box = tess.box.astype(centres.dtype)
    margin = ROUNDING_ULPS * jnp.finfo(centres.dtype).eps * jnp.max(jnp.abs(box))
    inside = jnp.all((centres > box[0] + margin) & (centres < box[1] - margin), axis=-1)
    on = jnp.concatenate([jnp.abs(centres - box[1]) <= margin, jnp.abs(centres - box[0]) <= margin], axis=-1)  # (S, 6)
    in_box = jnp.all((centres >= box[0] - margin) & (centres <= box[1] + margin), axis=-1)
    eps = jnp.finfo(wall_areas.dtype).eps
    faces = wall_areas > ROUNDING_ULPS * eps * jnp.max(box[1] - box[0]) ** 2  # (N, 6)
    walkers_face = faces.at[tess.simplices].get(mode="fill", fill_value=False)  # (S, 4, 6)
    touching = in_box[:, None] & ~jnp.any(on[:, None, :] & walkers_face, axis=-1)
    return inside[:, None] | touching


def _wall_vertices(tess: Tessellation, wall_areas, wall_lengths, edges):
    """(N,) the vertices of the clipped cells on the box. Each wall face has as many as edges
    (the faces' segments on it and the box's edges inside the cell); a vertex on j walls with
    a face there (inside a box edge, or a box corner) is counted j times, so j - 1 less."""
    real, inner, corners = edges
    lengths, first, width = wall_lengths  # `packed_slots`' table (size, 6), first places, widths (N,)
    k = tess.neighbors.shape[1]
    eps = jnp.finfo(wall_areas.dtype).eps
    scale = jnp.max(tess.box[1] - tess.box[0])
    faces = wall_areas > ROUNDING_ULPS * eps * scale**2  # (N, 6)
    hits = lengths > ROUNDING_ULPS * eps * scale
    place = jnp.arange(k, dtype=jnp.int32)
    places = jnp.where(place < width[:, None], first[:, None] + place, len(lengths))  # (N, K); past the table: none
    segments = jnp.sum(hits.at[places].get(mode="fill", fill_value=False), axis=1, dtype=jnp.int32)  # (N, 6)
    box_edges = jnp.zeros_like(segments).at[:, EDGE_WALLS].add(real[:, :, None].astype(jnp.int32))
    counted = jnp.sum(jnp.where(faces, segments + box_edges, 0), axis=1, dtype=jnp.int32)
    on_edge = jnp.sum(faces[:, EDGE_WALLS], axis=2, dtype=jnp.int32)  # (N, 12) walls j of an edge's vertices
    on_corner = jnp.sum(faces[:, CORNER_WALLS], axis=2, dtype=jnp.int32)  # (N, 8)
    return (
        counted
        - jnp.sum(inner * (on_edge - 1), axis=1, dtype=jnp.int32)
        - jnp.sum(jnp.where(corners, on_corner - 1, 0), axis=1, dtype=jnp.int32)
    )


# circumcentres of co-spherical walkers' simplices closer than this many epsilons of the cell's
# size are one vertex: a thin simplex's centre carries rounding of ~1/its flatness (measured:
# up to ~1e-13 of the cell on a cubic lattice), far below a 1e-9 jitter's split vertices
MERGE_ULPS = 4096
VERTEX_CHUNK = 256  # cells per chunk of the pairwise count (cells whose window did not suffice)
VERTEX_WINDOW = 4  # each centre is compared with the next this many along the projection
# sorted entries per chunk of those with a neighbour in the window that near (`_vertex_counts`;
# a uniform sample's: ~2% in float32, ~0.01% in float64), chunks past their count skipped
NEAR_CHUNK = 4096
# weights of the projection that orders a cell's centres: irrational ratios, so a lattice's
# distinct vertices (equal in some coordinates) do not tie
PROJECTION = (1.0, 0.7548776662466927, 0.5698402909980532)


def _vertex_counts(tess: Tessellation, offsets, proper):
    """(N,) the distinct Voronoi vertices of every cell. A vertex is the circumcentre of an
    incident simplex where `proper` holds ((S,), or (S, 4) per walker of the simplex: not flat,
    and in a box counted there, `_counted_in_box`; `offsets` (S, 4, 3): circumcentre minus each
    vertex, images applied), and co-spherical walkers (a lattice's) share one among several
    simplices: a centre within rounding of the cell's size (Chebyshev, MERGE_ULPS) of an earlier
    one (in simplex order) is not counted again.

    Every (cell, centre) is sorted by cell and a projection of the centre quantized to the
    cell's range (`_order_by_cell_and_projection`). Two centres within the tolerance have
    quanta at most `apart` apart (one number for every cell: the tolerance and the quantum both
    scale with the cell's range), so they lie within VERTEX_WINDOW places of each other unless
    more than that many crowd within those quanta. The window is read on the sorted cells and
    quanta first: only the entries with a neighbour there that near (a uniform sample: ~2% in
    float32) gather their centres and compare them, NEAR_CHUNK at a time (`_window_repeats`),
    so the cost follows their count. Crowded cells (none in uniform samples) are
    compared pair by pair (`_pairwise_counts`), -1 where a walker has more incident simplices
    than that table holds (2 K + 8)."""
    n, k = tess.neighbors.shape
    d = offsets.shape[-1]
    cells = jnp.where(proper if proper.ndim == 2 else proper[:, None], tess.simplices, n).ravel()
    flat = offsets.reshape(-1, d)
    m = flat.shape[0]
    valid = cells < n
    extent = jax.ops.segment_max(
        jnp.where(valid, jnp.max(jnp.abs(flat), axis=-1), 0.0), cells, num_segments=n + 1
    )  # (N + 1,) each cell's centres lie within this of its walker
    tolerance = MERGE_ULPS * jnp.finfo(offsets.dtype).eps * extent
    weights = jnp.asarray(PROJECTION[:d], offsets.dtype)
    projection = jnp.where(valid, dot(flat, weights), 0.0)
    order, _, _, sorted_cells, sorted_quanta, bits = _order_by_cell_and_projection(
        cells, projection, extent[cells] * sum(PROJECTION), n
    )
    # within the tolerance t: projections within sum(PROJECTION) t, quanta within that over the
    # quantum 2 sum(PROJECTION) extent / 2^bits, plus one, plus one for rounding (and one spare)
    apart = int(np.ceil(MERGE_ULPS * float(jnp.finfo(offsets.dtype).eps) * 2.0 ** (bits - 1))) + 3
    near = [
        jnp.concatenate(
            [
                (sorted_cells[w:] == sorted_cells[:-w]) & (sorted_quanta[w:] - sorted_quanta[:-w] <= apart),
                jnp.zeros(w, bool),
            ]
        )
        for w in range(1, VERTEX_WINDOW + 1)
    ]  # (M,) each: the entry w places on is of the same cell, its quantum that near
    chunks = -(-m // NEAR_CHUNK)
    places = flagged_ids(functools.reduce(jnp.logical_or, near) & (sorted_cells < n), chunks * NEAR_CHUNK, m)
    places = places.reshape(chunks, NEAR_CHUNK)
    step = functools.partial(_window_repeats, sorted_cells, order, flat, tolerance[sorted_cells], near[-1])
    repeated, crowded = scan_live_chunks(step, (jnp.zeros(m + 1, bool), jnp.zeros(n + 1, bool)), places, m)
    repeated, crowded = repeated[:m], crowded[:n]
    per_cell = jax.ops.segment_sum(
        jnp.stack([valid, valid & ~repeated], axis=1).astype(jnp.int32), cells, num_segments=n + 1
    )
    incident, counts = per_cell[:, 0], per_cell[:n, 1]
    rows_at, pairwise = _pairwise_counts(order, flat, tolerance, incident, crowded, cap=2 * k + 8)
    return counts.at[rows_at].set(pairwise, mode="drop")


def _window_repeats(cells, order, flat, limit, crowding, marked, places):
    """`marked` (repeated (M + 1,), crowded (N + 1,)) with, of the sorted entries at `places`
    (padding M) and the next VERTEX_WINDOW, the later in simplex order (`order` (M,): each
    sorted entry's) of every pair of one cell (`cells` (M,) sorted) whose centres (`flat` (M,
    d), by entry) lie within the tolerance (`limit` (M,) sorted), marked by entry; and the
    cells of the places whose entry VERTEX_WINDOW on is as near (`crowding` (M,)), where the
    window may not suffice."""
    m = order.shape[0]
    repeated, crowded = marked
    real = places < m
    at = jnp.minimum(places, m - 1)
    first, cell = order[at], cells[at]
    centre = flat[first]
    marks = []
    for w in range(1, VERTEX_WINDOW + 1):
        on = jnp.minimum(at + w, m - 1)
        other = order[on]
        apart = jnp.max(jnp.abs(flat[other] - centre), axis=-1)
        close = real & (at + w < m) & (cells[on] == cell) & (apart <= limit[at])
        marks.append(jnp.where(close, jnp.maximum(first, other), m))
    n = crowded.shape[0] - 1
    return (
        repeated.at[jnp.concatenate(marks)].set(True),
        crowded.at[jnp.where(real & crowding[at], cell, n)].set(True),
    )


QUANTUM_BITS = (10, 20)  # the fewest and most bits of a cell's quantized projection in the key


def _order_by_cell_and_projection(cells, projection, reach, n: int):
    """(order, quanta, quantum, sorted cells, sorted quanta, bits): the permutation (M,) int32
    that sorts the entries by (cell, quantum of projection, entry), with each projection in
    [-reach, reach] (its cell's) cut into 2^bits quanta (`quanta` (M,) int32, `quantum` (M,)
    their width), and the cells and quanta (M,) int32 in that order. Off the CPU the key (cell,
    quantum) fits 32 bits; it is sorted by least-significant-digit radix passes, each a sort of
    one uint32 holding the key's next digit above the entry's current position (so ties keep
    their order: each pass is stable). One operand sorts ~9x faster than the (cell,
    projection, entry) triple in XLA (bench/README.md); on a GPU one-operand sorts are CUB's
    radix sorts. On the CPU numpy sorts the cell, the quantum and the entry packed in one
    uint64 instead (`_order_by_key`), with as many quanta as 64 bits leave (up to
    QUANTUM_BITS[1]): fewer near pairs for `_vertex_counts` to compare."""
    m = cells.shape[0]
    position_bits = max(1, (m - 1).bit_length())
    digit_bits = 32 - position_bits
    if digit_bits < 1:
        raise ValueError(f"{m} (cell, centre) entries exceed the 2^31 a vertex count can sort.")
    cell_bits = max(1, n.bit_length())  # cells 0..n, n the padding
    cpu = jax.default_backend() == "cpu"
    passes = -(-(cell_bits + QUANTUM_BITS[0]) // digit_bits)
    room = 64 - position_bits if cpu else min(passes * digit_bits, 32)
    bits = max(1, min(room - cell_bits, QUANTUM_BITS[1]))
    safe = jnp.where(reach > 0, reach, 1.0)
    quantum = 2.0 * safe / 2.0**bits
    quanta = jnp.clip(jnp.floor((projection + safe) / quantum), 0, 2**bits - 1).astype(jnp.int32)
    if cpu:
        order, sorted_cells, sorted_quanta = _order_by_key(cells, quanta, bits)
        return order, quanta, quantum, sorted_cells, sorted_quanta, bits
    key = (cells.astype(jnp.uint32) << bits) | quanta.astype(jnp.uint32)
    position = jnp.arange(m, dtype=jnp.uint32)
    order = jnp.arange(m, dtype=jnp.int32)
    for shift in range(0, cell_bits + bits, digit_bits):
        digit = (key[order] >> shift) & np.uint32((1 << digit_bits) - 1)
        packed = jax.lax.sort((digit << position_bits) | position)
        order = order[(packed & np.uint32((1 << position_bits) - 1)).astype(jnp.int32)]
    in_order = key[order]
    return (
        order,
        quanta,
        quantum,
        (in_order >> bits).astype(jnp.int32),
        (in_order & ((1 << bits) - 1)).astype(jnp.int32),
        bits,
    )


def _order_by_key(cells, quanta, bits: int):
    """(order, sorted cells, sorted quanta): the stable order (M,) int32 of the entries by
    (cell, quantum) (`cells`, `quanta` (M,) int32, quanta below 2^bits) and both in that order,
    on the CPU backend: numpy sorts the cell, the quantum and the entry packed in one uint64,
    one pass instead of the radix passes' two or three, each a callback and gathers (3D vertex
    counts, uniform, float32, interleaved, when it returned the order alone: N = 1e5 340 -> 293
    ms, 1e4 23.9 -> 21.7 ms)."""

    def order(cells, quanta):
        cells, quanta = np.asarray(cells), np.asarray(quanta)  # the callback may get jax.Arrays
        position_bits = np.uint64(max(1, (cells.shape[-1] - 1).bit_length()))
        packed = cells.astype(np.uint64)  # in place from here: each pass over M uint64 counts
        packed <<= np.uint64(bits)
        packed |= quanta.astype(np.uint64)
        packed <<= position_bits
        packed |= np.arange(cells.shape[-1], dtype=np.uint64)
        packed.sort(axis=-1)
        positions = (packed & ((np.uint64(1) << position_bits) - np.uint64(1))).astype(np.int32)
        packed >>= position_bits
        sorted_quanta = (packed & np.uint64((1 << bits) - 1)).astype(np.int32)
        packed >>= np.uint64(bits)
        return positions, packed.astype(np.int32), sorted_quanta

    shape = jax.ShapeDtypeStruct(cells.shape, jnp.int32)
    return jax.pure_callback(order, (shape, shape, shape), cells, quanta, vmap_method="expand_dims")


def _pairwise_counts(order, flat, tolerance, incident, flagged, *, cap: int):
    """(rows, counts): the `flagged` cells' distinct centres compared pair by pair, chunk by
    chunk, -1 where a cell has more than `cap` entries; `order` (M,) the entries sorted by cell
    (`incident` (N + 1,) per cell), `flat` (M, d) their centres and `tolerance` (N + 1,) per cell
    (`_vertex_counts`)."""
    starts = jnp.cumsum(incident, dtype=jnp.int32) - incident  # the cells come sorted

    def count(ids):
        at = starts[ids][:, None] + jnp.arange(cap, dtype=jnp.int32)[None, :]
        inside = jnp.arange(cap, dtype=jnp.int32)[None, :] < incident[ids][:, None]
        entry = order[jnp.where(inside, at, 0)]
        centres, entry = flat[entry], jnp.where(inside, entry, -1)
        close = (
            jnp.max(jnp.abs(centres[:, :, None, :] - centres[:, None, :, :]), axis=-1) <= tolerance[ids][:, None, None]
        )
        earlier = entry[:, None, :] < entry[:, :, None]
        repeated = jnp.any(close & earlier & inside[:, None, :], axis=2)
        distinct = jnp.sum(inside & ~repeated, axis=1, dtype=jnp.int32)
        return jnp.where(incident[ids] > cap, -1, distinct)

    return map_flagged_rows(flagged, VERTEX_CHUNK, count, lambda ids: jnp.zeros(ids.shape, jnp.int32))


# --- 2D ----------------------------------------------------------------------------------

EDGES_2D = ((1, 2, 0), (2, 0, 1), (0, 1, 2))  # (a, b, the third vertex k) of each triangle edge


def triangle_flags_2d(p):
    """The flags of one triangle p (3, 2), coordinates relative to its first vertex: per edge
    (EDGES_2D order) the signed distance s = (c - m_ab) . w from the edge's midpoint to the
    circumcentre c (w across the edge towards the third vertex), the orthoschemes' area r s / 4
    (each end of the edge gets one), the area times m_ab + c (`_sums_at_vertices`); the
    circumcentre and whether the triangle is not flat."""
    e1, e2 = p[1] - p[0], p[2] - p[0]
    cross = e1[0] * e2[1] - e1[1] * e2[0]
    scale = jnp.maximum(jnp.sum(e1 * e1), jnp.sum(e2 * e2))
    ok = jnp.abs(cross) > 10.0 * jnp.finfo(p.dtype).eps * scale
    safe = jnp.where(ok, cross, 1.0)
    offset = jnp.stack(
        [e2[1] * jnp.sum(e1 * e1) - e1[1] * jnp.sum(e2 * e2), e1[0] * jnp.sum(e2 * e2) - e2[0] * jnp.sum(e1 * e1)]
    ) / (2.0 * safe)
    centre = p[0] + jnp.where(ok, offset, 0.0)
    heights, areas, weighted = [], [], []
    for a, b, k in EDGES_2D:
        edge = p[b] - p[a]
        length = jnp.sqrt(jnp.sum(edge * edge))
        # |ab| cot(angle at k) / 2: the circumcentre lies across ab from k where that angle is obtuse
        height = jnp.where(ok, length * dot(p[a] - p[k], p[b] - p[k]) / (2.0 * jnp.abs(safe)), 0.0)
        middle = 0.5 * (p[a] + p[b])
        area = length * height / 4.0
        heights.append(height)
        areas.append(area)
        weighted.append(area * (middle + centre))
    return jnp.stack(heights), jnp.stack(areas), jnp.stack(weighted), centre, ok


RAY_CHUNK = 64  # hull walkers per chunk of the ray test (chunks past their count are skipped)


def _unbounded_slots_2d(tess: Tessellation):
    """(N, K) the faces that are rays: a hull walker's two extreme neighbours, those with every
    other neighbour on one side of them (the outside lies beyond), share a ray with it. Only
    the hull walkers are tested (`map_flagged_rows`): the cost follows them (their neighbour
    displacements too: the graph has no box, so no images)."""
    n, k = tess.neighbors.shape

    def extreme(ids):
        safe = jnp.minimum(ids, n - 1)
        mask = tess.neighbor_mask[safe]
        rows = jnp.where(
            mask[..., None], take_or_zero(tess.points, tess.neighbors[safe]) - tess.points[safe][:, None], 0.0
        )
        cross = rows[:, :, None, 0] * rows[:, None, :, 1] - rows[:, :, None, 1] * rows[:, None, :, 0]
        scale = jnp.max(jnp.sum(rows * rows, axis=-1), axis=1)[:, None, None]
        tol = ROUNDING_ULPS * jnp.finfo(rows.dtype).eps * scale
        others = mask[:, None, :]
        left = jnp.all(~others | (cross >= -tol), axis=2)
        right = jnp.all(~others | (cross <= tol), axis=2)
        return mask & (left | right) & (ids < n)[:, None]

    rows, rays = map_flagged_rows(tess.hull, RAY_CHUNK, extreme, lambda ids: jnp.zeros((len(ids), k), bool))
    return jnp.zeros((n, k), bool).at[rows].set(rays, mode="drop")


def dual_faces_2d(tess: Tessellation):
    """`dual_faces_3d` in 2D: per walker and slot the face lengths and whether they are
    unbounded; per walker areas, first moments, vertex counts, and whether the
    walker is beside a triangle within rounding of flat (its cell's sign is not decided)."""
    n, k = tess.neighbors.shape
    verts = simplex_vertices(tess)  # (S, 3, 2)
    local = verts - verts[:, :1]
    heights, areas, weighted, _, proper = jax.vmap(triangle_flags_2d)(local)
    mask = tess.simplex_mask
    pairs = np.asarray([[a, b] for a, b, _ in EDGES_2D], np.int32)
    ends = tess.simplices[:, pairs]  # (S, 3, 2)
    shifts = None if tess.simplex_shifts is None else tess.simplex_shifts[:, pairs]
    index = _find_slots(tess, _sorted_rows(tess), ends, shifts)
    faces = _sum_into_slots(jnp.where(mask[:, None], heights, 0.0), index, n, k)
    unbounded = _unbounded_slots_2d(tess) if tess.box is None else jnp.zeros((n, k), bool)
    cell_area, moments = _sum_at_ends(tess.simplices, pairs, jnp.where(mask[:, None], areas, 0.0), weighted, local, n)
    # a polygon has as many vertices as edges: the faces of positive length
    r = neighbor_distances(tess)
    vertices = jnp.sum(faces > ROUNDING_ULPS * jnp.finfo(verts.dtype).eps * r, axis=1, dtype=jnp.int32)
    flat = jnp.repeat(mask & ~proper, 3).astype(jnp.int32)
    beside_flat = jax.ops.segment_max(flat, tess.simplices.ravel(), num_segments=n + 1)[:n] > 0
    return faces, unbounded, cell_area, moments, vertices, beside_flat
