"""3D cells of a (non-periodic) box from the Delaunay dual: each face piece clipped to the box.

`_dual` cuts every cell into signed orthoschemes (x_a, m_ab, c_T, C_s), whose face (m_ab, c_T,
C_s) is a signed piece of the face ab. The signed pieces decompose the cell as indicator
functions (a cone from a point over a polytope's facets, with signs, covers the polytope once
and every other point zero times), so they decompose box ∩ cell as well: a face's area inside
the box is the signed sum of its pieces clipped to the box. A hull triangle T has one simplex;
its Voronoi edge is a ray from C_s along T's outer normal u, and the faces around it gain the
half-strip (m_ab, c_T) + t u, t >= 0 (the second simplex's piece, at infinity), and the wedge
m_ab + cone(u, g), g the direction of the sum of the outer normals of the two hull triangles
at edge ab: the two wedges of a hull edge make its face's recession cone, which a cone from
m_ab over the face's edges leaves out. Only pieces that reach a wall are clipped
(Sutherland-Hodgman against the six walls, the buffer growing by a vertex per wall), so the
cost follows the simplices at the boundary.

Each cell's faces on the walls follow from the same pieces: a clipped piece's edges on wall w
are signed pieces of the segment where its face meets w, and a wall face's area is 1/2 sum h L
over its edges (h: the edge's signed distance from the walker's foot on the wall), the edges
being those segments and the box's edges inside the cell (an interval on each of the 12 box
edges, per cell at the boundary). Volumes and first moments follow from the faces by the
divergence theorem (cones from the walker), as in `_dual`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..base._compact import flagged_ids
from ..base._simplex import dot  # not `@`: under vmap that is a batched dot_general, 0.55 s of 5.2 s here at N = 1e5
from ..tessellation._graph import Tessellation
from ._boxclip import ROUNDING_ULPS, cell_planes, line_interval, map_flagged_rows, over_planes, scan_live_chunks

FACE_CHUNK = 256  # simplex faces per chunk of clipped pieces (3 or 6 pieces each)
EDGE_CHUNK = 64  # boundary cells per chunk of the box-edge intervals
FACES_3D = ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2))  # face opposite vertex 0, 1, 2, 3
# flag (face o, edge e) as in `_dual.simplex_flags_3d`: its edge ends x, y and the face's third
# vertex k, as corners of the face (FACES_3D[o] order); the fourth point is the vertex o
FLAG_CORNERS = jnp.asarray([[(e + 1) % 3, (e + 2) % 3, e] for e in range(3)], jnp.int32)  # (3, 3)
FIRST_END_FLAG = jnp.asarray([2, 0, 1], jnp.int32)  # corner c is the first end of flag (c - 1) % 3
SECOND_END_FLAG = jnp.asarray([1, 2, 0], jnp.int32)  # and the second end of flag (c + 1) % 3


# A tetrahedron whose |det(edges)| is below this many epsilons of the product of its edges'
# lengths (the rounding bound of the determinant, Hadamard's) is flat: co-spherical walkers'
# coplanar quadruples (a lattice's) have |det| below one epsilon of it, and their computed
# centres are anywhere. The product, not the longest edge cubed: a needle from a cluster of
# walkers 1e-4 apart to one 100 away has |det| ~ 1e-12 of the longest edge cubed, and is no
# more flat than its cluster (measured: the 1e4x-clustered swarm of test_triangulators).
FLAT_ULPS = 256.0


def unit_vector(v):
    norm_sq = jnp.sum(v * v)
    ok = norm_sq > 0
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, norm_sq, 1.0)), 0.0), ok


# per vertex of a tetrahedron, the other three
OTHER_VERTICES = jnp.asarray([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]], jnp.int32)
OTHER_CORNERS = jnp.asarray([[1, 2], [0, 2], [0, 1]], jnp.int32)  # the same for a triangle


def circumcentre_3d(p):
    """Circumcentre of a tetrahedron (rows p; in their frame), whether it is not flat (to
    rounding), and whether it is a vertex of its own (`FLAT_ULPS`). Solved from the vertex
    whose three edges have the least product of lengths (the determinant's rounding bound):
    from the far end of a needle, a cluster's 1e-4 spacing costs the centre 1e-2 of its digits
    (the choice does not depend on the vertices' order)."""
    edges = p[OTHER_VERTICES] - p[:, None, :]  # (4, 3, 3) from each vertex
    products = jnp.prod(jnp.sqrt(jnp.sum(edges * edges, axis=-1)), axis=-1)
    best = jnp.argmin(products)
    e = edges[best]
    # Cramer's rule for e u = |e|^2 / 2 (rows e_k): u = sum_k |e_k|^2 e_k+1 x e_k+2 / (2 det e)
    crossed = jnp.cross(e[jnp.asarray([1, 2, 0])], e[jnp.asarray([2, 0, 1])])
    det = dot(e[0], crossed[0])
    bound = jnp.finfo(p.dtype).eps * products[best]
    ok = jnp.abs(det) > 10.0 * bound
    centre = jnp.sum(jnp.sum(e * e, axis=1)[:, None] * crossed, axis=0) / (2.0 * jnp.where(ok, det, 1.0))
    return jnp.where(ok, p[best] + centre, p[0]), ok, jnp.abs(det) > FLAT_ULPS * bound


def triangle_circumcentre(a, b, c):
    """Circumcentre of triangle abc in 3D and whether it is not flat, solved from the vertex
    opposite the longest edge (the cross product's rounding bound is least there; ties go to
    the first, so callers pass the vertices in a canonical order). Also, per corner j (input
    order), the edge opposite it: its signed distance from its midpoint to the circumcentre
    (towards j: |edge| cot(angle at j) / 2 = |edge| (a - j) . (b - j) / (2 |(a - j) x (b - j)|),
    a and b the edge's ends; 0 where flat) and its length; and the unit normal (0 where the cross product is 0), each
    computed from the corners alone, so the two simplices of a face get them bit for bit."""
    p = jnp.stack([a, b, c])
    edges = p[OTHER_CORNERS] - p[:, None, :]  # (3, 2, 3): from each vertex to the other two
    lengths_sq = jnp.sum(edges * edges, axis=-1)
    best = jnp.argmin(jnp.prod(lengths_sq, axis=-1))
    u, v = edges[best]
    n = jnp.cross(u, v)
    n_sq = jnp.sum(n * n)
    scale = jnp.maximum(jnp.sum(u * u), jnp.sum(v * v)) ** 2
    ok = n_sq > 100.0 * jnp.finfo(a.dtype).eps ** 2 * scale
    safe = jnp.where(ok, n_sq, 1.0)
    offset = (jnp.sum(u * u) * jnp.cross(v, n) + jnp.sum(v * v) * jnp.cross(n, u)) / (2.0 * safe)
    opposite = jnp.sqrt(jnp.stack([lengths_sq[1, 1], lengths_sq[0, 1], lengths_sq[0, 0]]))
    cosines = jnp.sum(edges[:, 0] * edges[:, 1], axis=-1)  # (3,) |ja| |jb| cos(angle at j)
    heights = jnp.where(ok, opposite * cosines / (2.0 * jnp.sqrt(safe)), 0.0)
    some = n_sq > 0
    normal = jnp.where(some, n / jnp.sqrt(jnp.where(some, n_sq, 1.0)), 0.0)
    return jnp.where(ok, p[best] + offset, a), ok, heights, opposite, normal


def order_in_rows(ids):
    """`jnp.argsort(ids, axis=-1, stable=True)` of (..., m) ids by comparisons (XLA's sort on
    the CPU costs ~20x as much for rows of three or four): each entry's rank, ties by position."""
    m = ids.shape[-1]
    i, j = jnp.arange(m, dtype=jnp.int32)[:, None], jnp.arange(m, dtype=jnp.int32)[None, :]
    before = (ids[..., None, :] < ids[..., :, None]) | ((ids[..., None, :] == ids[..., :, None]) & (j < i))
    rank = jnp.sum(before, axis=-1, dtype=jnp.int32)  # (..., m) a permutation of 0 .. m - 1
    return jnp.sum(jnp.where(rank[..., :, None] == j, i, 0), axis=-2, dtype=jnp.int32)


def dual_centres(verts):
    """The circumcentres of the simplices `verts` (S, 4, 3) and of their faces (S, 4, 3), in the
    frame of `verts`, each computed once: a face's two simplices, and every flag of a
    simplex, must share its centre bit for bit, or the signed pieces around an edge stop
    cancelling (a needle's centre carries ~1e-5 of rounding from its inputs). Returns (centres
    (S, 3), not flat (S,), counted as a vertex (S,), face centres (S, 4, 3), faces not flat
    (S, 4), and per face (S, 4, 3) (`triangle_circumcentre`'s, edge e opposite the face's e-th
    vertex in FACES_3D order) the heights h and lengths of its edges, and (S, 4, 3) its unit
    normals, either way round). The simplices' vertices come in the order of their walker ids
    (`_dual.with_sorted_simplices`), so each face's (FACES_3D keeps it) is the same in both its
    simplices."""
    centres, ok, counted = jax.vmap(circumcentre_3d)(verts)
    corners = verts[:, jnp.asarray(FACES_3D, jnp.int32)]  # (S, 4, 3 corners, 3)
    face_centres, face_ok, heights, lengths, normals = jax.vmap(jax.vmap(triangle_circumcentre))(
        corners[..., 0, :], corners[..., 1, :], corners[..., 2, :]
    )
    return centres, ok, counted, face_centres, face_ok, (heights, lengths, normals)


def wall_bounds(lower, upper):
    """(2d,) the walls' axis, bound and outward sign, walls ordered as `VoronoiFacets.wall_areas`."""
    d = lower.shape[0]
    axes = jnp.concatenate([jnp.arange(d), jnp.arange(d)])
    return axes, jnp.concatenate([upper, lower]), jnp.concatenate([jnp.ones(d), -jnp.ones(d)]).astype(lower.dtype)


def clip_polygon(verts, count, lower, upper, tol, wall=None):
    """A convex polygon (`count` of the rows of `verts` (P, 3), in order) cut to the box
    [lower, upper]: (vertices (P + 6, 3), count, on (P + 6, 6): the vertex lies on wall j).
    Each wall adds at most one vertex, so the buffer grows by one row per wall. With `wall`
    (an index, traced), the cut against that wall alone: (P + 1) rows, and `on` (P + 1, 1) for
    that wall; the same polygon where every vertex lies inside the other walls by more than
    `tol` (`walls_reached`), so on none of them."""
    axes, bounds, signs = _walls(lower, upper, wall)
    on = jnp.abs(verts[:, axes] - bounds) <= tol
    for j in range(len(axes)):
        verts, count, on = _clip_to_wall(verts, count, on, axes[j], bounds[j], signs[j], jnp.arange(len(axes)) == j)
    return verts, count, on


def _walls(lower, upper, wall=None):
    """`wall_bounds`, or that of the one `wall` (an index) as arrays of one."""
    axes, bounds, signs = wall_bounds(lower, upper)
    if wall is None:
        return axes, bounds, signs
    return axes[wall][None], bounds[wall][None], signs[wall][None]


def _clip_to_wall(verts, count, on, k, bound, sign, is_wall):
    """One Sutherland-Hodgman pass: the polygon cut by the wall x_k = `bound` (`sign` > 0: the
    box lies below it), `is_wall` (2d,) marking the wall among the flags `on`."""
    d, size = verts.shape[-1], verts.shape[0] + 1
    idx = jnp.arange(size - 1)
    s = sign * (verts[:, k] - bound)  # > 0 outside
    valid = idx < count
    nxt = jnp.where(idx + 1 < count, idx + 1, 0)
    inside, inside_next = s <= 0, s[nxt] <= 0
    cross = valid & (inside != inside_next)
    t = s / jnp.where(cross, s - s[nxt], 1.0)
    point = jnp.where(jnp.arange(d) == k, bound, verts + t[:, None] * (verts[nxt] - verts))
    keep = jnp.stack([valid & inside, cross], axis=1).reshape(-1)
    candidates = jnp.stack([verts, point], axis=1).reshape(-1, d)
    candidates_on = jnp.stack([on, (on & on[nxt]) | is_wall], axis=1).reshape(-1, on.shape[-1])
    position = jnp.where(keep, running_count(keep) - 1, size)
    verts = jnp.zeros((size, d), verts.dtype).at[position].set(candidates, mode="drop")
    on = jnp.zeros((size, on.shape[-1]), bool).at[position].set(candidates_on, mode="drop")
    return verts, jnp.sum(keep), on


def running_count(flags):
    """`jnp.cumsum(flags)` (int32) of a short row by additions: XLA's CPU backend makes a
    cumulative sum a reduce-window, which over a polygon's few candidates costs more than the
    clipping around it."""
    total, counts = jnp.zeros((), jnp.int32), []
    for flag in flags.astype(jnp.int32):
        total = total + flag
        counts.append(total)
    return jnp.stack(counts) if counts else jnp.zeros((0,), jnp.int32)


def walls_reached(verts, count, lower, upper, tol):
    """(2d,) bool: the walls some vertex of the polygon lies beyond, on, or within `tol` of;
    cutting by any other wall leaves it as it is (`clip_polygon`)."""
    axes, bounds, signs = wall_bounds(lower, upper)
    near = signs * (verts[:, axes] - bounds) > -tol  # (P, 2d)
    return jnp.any(near & (jnp.arange(verts.shape[0]) < count)[:, None], axis=0)


def polygon_measures(verts, count, on, axis):
    """(area oriented about `axis`, its first moment, per wall the length of the polygon's
    edges on it (2d,) and their first moments (2d, 3))."""
    idx = jnp.arange(verts.shape[0])
    a, b = verts[1:-1] - verts[0], verts[2:] - verts[0]
    fan = jnp.where(idx[1:-1] + 1 < count, 0.5 * dot(jnp.cross(a, b), axis), 0.0)
    moment = jnp.sum(fan[:, None] * (3.0 * verts[0] + a + b) / 3.0, axis=0)
    nxt = jnp.where(idx + 1 < count, idx + 1, 0)
    edge = verts[nxt] - verts
    length = jnp.where(idx < count, jnp.sqrt(jnp.sum(edge * edge, axis=-1)), 0.0)
    on_wall = jnp.where(on & on[nxt], length[:, None], 0.0)  # (P, 2d)
    return (
        jnp.sum(fan),
        moment,
        jnp.sum(on_wall, axis=0),
        jnp.sum(on_wall[:, :, None] * (0.5 * (verts + verts[nxt]))[:, None, :], axis=0),
    )


def _triangle_piece(q, centres):
    """Flag (x, y, k, v) = q (rows relative to x, so q[0] = 0), `centres` its simplex's and face
    xyk's circumcentres (relative to x) and whether each is not flat (`dual_centres`): the signed
    triangle (m, c_T, C) of face xy it adds, as (sign, the triangle's orientation about the face
    normal, the triangle (3 rows), its count 3, the face's unit normal x -> y). Its sign is that
    of the height (c_T - m) . w times that of the piece (C - c_T) . u (`_dual`'s orthoscheme
    legs; w across xy towards k, u the normal of xyk towards v), from vectors along w and u
    not normalised (products of two lengths at most: float32 keeps their signs down to
    lengths of ~1e-19)."""
    centre, c_t, ok, tri_ok = centres
    direction, _ = unit_vector(q[1])
    middle = 0.5 * q[1]
    across = q[2] - dot(q[2], direction) * direction  # |across| w
    normal = jnp.cross(direction, q[2])  # |normal| (+-u): no power of the lengths above two
    height, piece = dot(c_t - middle, across), dot(centre - c_t, normal)
    sign = jnp.where(ok & tri_ok, jnp.sign(height) * jnp.sign(piece) * jnp.sign(dot(q[3], normal)), 0.0)
    orient = jnp.sign(dot(jnp.cross(c_t - middle, centre - middle), direction))
    return sign, orient, jnp.stack([middle, c_t, centre]), jnp.asarray(3), direction


def _hull_piece(q, centres, hull, lower, upper, kind, toward):
    """Flag (x, y, k, v) = q (rows relative to x) of a triangle T = xyk on the hull, `centres`
    as `_triangle_piece`'s: the signed piece of face xy beyond T's Voronoi ray, as (sign, the
    polygon's orientation about the face normal, polygon (4 rows), count, the face's unit
    normal x -> y). `kind` 1: the half-strip beyond c_T along T's outer normal u; 2: the wedge
    m + cone(u, g), `toward` the sum of the outer normals of the two hull triangles at edge xy
    (g its direction: the two wedges of a hull edge make its face's recession cone
    m + cone(u_1, u_2))."""
    _, c_t, _, tri_ok = centres
    normal, _ = unit_vector(jnp.cross(q[1] - q[0], q[2] - q[0]))
    normal = jnp.where(dot(normal, q[3] - q[0]) < 0, -normal, normal)
    direction, _ = unit_vector(q[1] - q[0])
    across = q[2] - dot(q[2], direction) * direction
    w, _ = unit_vector(across)
    middle = 0.5 * q[1]
    height = dot(c_t - middle, w)
    out = -normal
    diagonal = jnp.sqrt(jnp.sum((upper - lower) ** 2))

    def beyond_box(point, axis):  # a distance along `axis` from `point` that leaves the box
        return jnp.maximum(jnp.sum(jnp.maximum(lower * axis, upper * axis)) - dot(point, axis), 0.0) + diagonal

    reach = beyond_box(c_t, out)
    strip = jnp.stack([middle, c_t, c_t + reach * out, middle + reach * out])
    g, g_ok = unit_vector(toward)
    bisector, b_ok = unit_vector(g + out)
    cos = jnp.where(b_ok, dot(g, bisector), 1.0)
    far = beyond_box(middle, bisector) / jnp.maximum(cos, 0.5)
    wedge = jnp.stack([middle, middle + far * g, middle + far * out, middle + far * out])
    corners = jnp.where(kind == 1, strip, wedge)
    sign = jnp.where(
        kind == 1, jnp.where(hull & tri_ok, jnp.sign(height), 0.0), jnp.where(hull & g_ok & b_ok, 1.0, 0.0)
    )
    orient = jnp.sign(dot(jnp.cross(corners[1] - corners[0], corners[2] - corners[0]), direction))
    return sign, orient, corners, jnp.where(kind == 1, 4, 3), direction


def clip_tolerance(lower, upper):
    """The rounding room of the walls, the box relative to a walker."""
    return ROUNDING_ULPS * jnp.finfo(lower.dtype).eps * jnp.max(jnp.abs(jnp.stack([lower, upper])))


def clipped_piece(q, piece, lower, upper, wall=None):
    """One flag's piece (`_triangle_piece`, `_hull_piece`) clipped to the box (frame of x = q[0],
    box relative to it; `wall`: the only wall it reaches, `clip_polygon`): (signed area, the
    walls' signed segment lengths (6,), and per end x, y: the volume and first moment of the
    cone over the piece (about that end), the wall faces' area (6,) and moment (6, 3) (about
    that end) added by the segments). With `wall`, the walls' quantities are those of that
    wall alone, (1,) and (1, 3) (the others are zero)."""
    sign, orient, polygon, count, direction = piece
    tol = clip_tolerance(lower, upper)
    clipped = clip_polygon(polygon, count, lower, upper, tol, wall)
    area, moment, lengths, length_moments = polygon_measures(*clipped, direction)  # type: ignore[call-arg]  # (verts, count, on)
    area, moment = sign * orient * area, sign * orient * moment
    axes, bounds, signs = _walls(lower, upper, wall)
    # a piece outside a wall that its face meets there (a walker on the wall, its hull
    # triangle's strip) keeps only its edge on the wall: no measure inside, no segment
    depth = signs[None, :] * (bounds[None, :] - clipped[0][:, axes])  # (P, W) distance inside
    inside = jnp.max(jnp.where((jnp.arange(len(depth)) < clipped[1])[:, None], depth, 0.0), axis=0) > tol
    lengths = jnp.where(inside, lengths, 0.0)
    walls = signs[:, None] * jnp.eye(3, dtype=q.dtype)[axes]  # (W, 3) outward normals
    r = jnp.sqrt(jnp.sum(q[1] * q[1]))
    safe = jnp.where(lengths > 0, lengths, 1.0)
    middles = length_moments / safe[:, None]
    per_end = []
    for end, outward in ((q[0], direction), (q[1], -direction)):
        # in wall j, the segment's outward direction is the face normal projected on the wall
        u = outward - dot(walls, outward)[:, None] * walls
        u_norm = jnp.sqrt(jnp.sum(u * u, axis=-1))
        u = u / jnp.where(u_norm > 0, u_norm, 1.0)[:, None]
        h = jnp.sum((middles - end) * u, axis=-1)
        foot = end + (bounds - end[axes])[:, None] * jnp.eye(3, dtype=q.dtype)[axes]
        wall_area = sign * 0.5 * h * lengths
        wall_moment = wall_area[:, None] * ((foot - end) + 2.0 * (middles - end)) / 3.0
        per_end.append((r / 6.0 * area, r / 8.0 * (moment - area * end), wall_area, wall_moment))
    return area, sign * lengths, per_end


def clipped_sums(tess: Tessellation, centres, hull_face, outside, toward, slots_of, walls_of):
    """Every flag piece that reaches a wall, clipped (`clipped_piece`) and summed: the
    triangles of the flags of the faces marked `outside` (S, 4), and the half-strips and
    wedges of the hull triangles (`hull_face` (S, 4); `toward` (N * K + 1, 3) per neighbour
    slot the sum of the outer normals of the hull triangles at its edge).
    `slots_of(simplex, opposite)`: (2, F, 3) the neighbour slots of the three flags of faces
    (F,) seen from either end of their edges (N * K where none; `_dual.face_flag_slots`);
    `walls_of` = (pack, size): the places of those slots in the wall segments' table (`pack`:
    slots -> 0 ... size - 1, size where none; `_dual.packed_slots`).
    `centres`: (the simplices' circumcentres (S, 3), their faces' (S, 4, 3), whether each is
    not flat (S,), (S, 4)), as `dual_centres` gives them.

    Returns the sums per slot of the areas (N * K,) and of the segments on each wall (size, 6)
    (by `walls_of`),
    and per walker of the cones' volumes (N,), first moments (N, 3), and the wall faces' areas
    (N, 6) and first moments (N, 6, 3). The faces are compacted and their pieces summed chunk
    by chunk (`lax.scan`; chunks past their count are skipped by `lax.cond`), so the cost
    follows the boundary's pieces, not the simplices."""
    n, k = tess.neighbors.shape
    dtype = tess.points.dtype
    sums = (
        jnp.zeros(n * k + 1, dtype),
        jnp.zeros((walls_of[1] + 1, 6), dtype),
        jnp.zeros(n + 1, dtype),
        jnp.zeros((n + 1, 3), dtype),
        jnp.zeros((n + 1, 6), dtype),
        jnp.zeros((n + 1, 6, 3), dtype),
    )
    for faces, kinds in ((outside, (0,)), (hull_face, (1, 2))):
        sums = _sum_pieces(
            tess, sums, faces & tess.simplex_mask[:, None], kinds, centres, hull_face, toward, slots_of, walls_of[0]
        )
    return tuple(a[:-1] for a in sums)


def _sum_pieces(tess: Tessellation, sums, faces, kinds, centres, hull_face, toward, slots_of, pack):
    """`clipped_sums` for the flags of the marked `faces` (S, 4), pieces of the given kinds.
    Each face's inputs are gathered once for its three flags, and each walker of a face gets
    the sum of its two flags' shares (one update per corner, not per flag end)."""
    n, k = tess.neighbors.shape
    s_cap = tess.simplices.shape[0]
    box = tess.box.astype(tess.points.dtype)
    total = s_cap * 4
    n_chunks = -(-total // FACE_CHUNK)
    triangles = kinds == (0,)
    first = _near_one_wall(centres, box) if triangles else jnp.ones_like(faces)
    rows = _compacted(faces.ravel(), first.ravel(), n_chunks * FACE_CHUNK)
    per_flag = (
        lambda a: jnp.broadcast_to(  # noqa: E731  (F, 3, ...) per face and flag -> (F * kinds * 3, ...)
            a[:, None], (a.shape[0], len(kinds), *a.shape[1:])
        ).reshape(-1, *a.shape[2:])
    )

    def chunk_inputs(face):  # inside the `cond`: a skipped chunk gathers nothing
        real = face < total
        simplex, opposite = jnp.minimum(face, total - 1) // 4, face % 4
        corner_ids, corners, apex = _face_corners(tess.simplices[simplex], tess.points, opposite)
        q = jnp.concatenate(  # (F, 3, 4, 3) per flag (x, y, k, v) in the frame of x
            [corners[:, FLAG_CORNERS], jnp.broadcast_to(apex[:, None, None], (len(face), 3, 1, 3))], axis=2
        )
        origin = q[:, :, 0]
        q = per_flag(q - origin[:, :, None])
        flag_centres = (
            per_flag(centres[0][simplex][:, None] - origin),
            per_flag(centres[1][simplex, opposite][:, None] - origin),
            per_flag(jnp.broadcast_to(centres[2][simplex][:, None], (len(face), 3))),
            per_flag(jnp.broadcast_to(centres[3][simplex, opposite][:, None], (len(face), 3))),
        )
        slots = slots_of(simplex, opposite)  # (2, F, 3)
        slot = jnp.where(real[None, :, None], slots, n * k)
        walker = jnp.where(real[:, None], corner_ids, n)  # (F, 3)
        origin = per_flag(origin)
        lower, upper = box[0] - origin, box[1] - origin
        if triangles:
            return slot, walker, q, lower, upper, jax.vmap(_triangle_piece)(q, flag_centres)
        kind = jnp.broadcast_to(jnp.asarray(kinds, jnp.int32)[None, :, None], (len(face), len(kinds), 3)).ravel()
        pieces = jax.vmap(_hull_piece)(
            q,
            flag_centres,
            per_flag(jnp.broadcast_to(hull_face[simplex, opposite][:, None], (len(face), 3))),
            lower,
            upper,
            kind,
            per_flag(toward[slots[0]]),
        )
        return slot, walker, q, lower, upper, pieces

    def add(sums, face):
        slot, walker, q, lower, upper, piece = chunk_inputs(face)
        if triangles:  # triangles that reach one wall each are cut by it alone
            reached = jax.vmap(walls_reached)(piece[2], piece[3], lower, upper, jax.vmap(clip_tolerance)(lower, upper))
            area, lengths, per_end = jax.lax.cond(
                jnp.all(jnp.sum(reached, axis=1) <= 1),
                lambda: _clipped_by_one_wall(q, piece, lower, upper, jnp.argmax(reached, axis=1)),
                lambda: jax.vmap(clipped_piece)(q, piece, lower, upper),
            )
        else:  # the hull's pieces (a uniform sample's few hundred) by every wall: one program less to compile
            area, lengths, per_end = jax.vmap(clipped_piece)(q, piece, lower, upper)
        by_flag = lambda v: jnp.sum(v.reshape(len(face), len(kinds), 3, *v.shape[1:]), axis=1)  # noqa: E731
        # corner c is the first end of flag c - 1 and the second end of flag c + 1 (FLAG_CORNERS)
        by_corner = (
            lambda i: (  # noqa: E731
                by_flag(per_end[0][i])[:, FIRST_END_FLAG] + by_flag(per_end[1][i])[:, SECOND_END_FLAG]
            ).reshape(3 * len(face), *per_end[0][i].shape[1:])
        )
        area, lengths = by_flag(area), by_flag(lengths)
        both = lambda v: jnp.broadcast_to(v, (2, *v.shape)).reshape(-1, *v.shape[2:])  # noqa: E731
        areas, walls, volumes, moments, wall_areas, wall_moments = sums
        walker = walker.ravel()
        return (
            areas.at[slot.ravel()].add(both(area).ravel()),
            walls.at[pack(slot.ravel())].add(both(lengths)),
            volumes.at[walker].add(by_corner(0)),
            moments.at[walker].add(by_corner(1)),
            wall_areas.at[walker].add(by_corner(2)),
            wall_moments.at[walker].add(by_corner(3)),
        )

    return scan_live_chunks(add, sums, rows.reshape(n_chunks, FACE_CHUNK), total)


def _face_corners(simplices, points, opposite):
    """Per face (the rows of `simplices` (F, 4) and the vertex `opposite` each face, (F,)): its
    corners' ids (F, 3) and points (F, 3, 3) in FACES_3D order (the other three in ascending
    place: corner c is place c, or c + 1 from the opposite vertex on), and the opposite
    vertex's point (F, 3). Selected, not gathered, from the simplex's four points."""
    verts = points[simplices]  # (F, 4, 3)
    shifted = jnp.arange(3, dtype=jnp.int32)[None, :] >= opposite[:, None]  # (F, 3) corner c at place c + 1
    ids = jnp.where(shifted, simplices[:, 1:], simplices[:, :3])
    corners = jnp.where(shifted[..., None], verts[:, 1:], verts[:, :3])
    apex = jnp.sum(
        jnp.where((jnp.arange(4, dtype=jnp.int32)[None, :] == opposite[:, None])[..., None], verts, 0), axis=1
    )
    return ids, corners, apex


def _clipped_by_one_wall(q, piece, lower, upper, wall):
    """`clipped_piece` of pieces (M,) that each reach one `wall` (M,) alone: measured on that
    wall, its values put at its entry of the six walls'."""
    area, lengths, per_end = jax.vmap(clipped_piece)(q, piece, lower, upper, wall)
    at_wall = jnp.arange(6) == wall[:, None]  # (M, 6)
    spread = lambda v: jnp.where(at_wall.reshape(*at_wall.shape, *(1,) * (v.ndim - 2)), v, 0.0)  # noqa: E731  (M, 1, ...) -> (M, 6, ...)
    return area, spread(lengths), [(vol, mom, spread(wa), spread(wm)) for vol, mom, wa, wm in per_end]


def near_walls(y, box):
    """(..., 2d) bool: per wall (`wall_bounds`' order), whether the points y (..., d) lie
    beyond it, on it, or within `clip_tolerance` of it."""
    margin = clip_tolerance(box[0], box[1])
    return jnp.concatenate([y >= box[1] - margin, y <= box[0] + margin], axis=-1)


def _near_one_wall(centres, box):
    """(S, 4) bool: faces whose simplex's and own circumcentres are near (`near_walls`) one
    wall at most: their triangles mostly reach that wall alone."""
    return jnp.sum(near_walls(centres[0], box)[:, None, :] | near_walls(centres[1], box), axis=-1) <= 1


def _compacted(flags, first, size: int):
    """The ids where `flags` (M,) holds, those where `first` holds before the others (each in
    order), padded with M to `size`: chunks of pieces that reach one wall each, then the rest."""
    return flagged_ids(flags, size, flags.shape[0], first)


def _box_edges():
    """The 12 box edges as (axis, wall 1, wall 2) and the 8 corners as their 3 walls (walls
    ordered as `VoronoiFacets.wall_areas`: x_k = hi_k is k, x_k = lo_k is d + k)."""
    edges = [
        (k, w1, w2) for k in range(3) for w1 in ((k + 1) % 3, (k + 1) % 3 + 3) for w2 in ((k + 2) % 3, (k + 2) % 3 + 3)
    ]
    corners = [(wx, wy, wz) for wx in (0, 3) for wy in (1, 4) for wz in (2, 5)]
    return edges, corners


BOX_EDGES, BOX_CORNERS = _box_edges()
EDGE_WALLS = jnp.asarray([[w1, w2] for _, w1, w2 in BOX_EDGES], jnp.int32)  # (12, 2)
EDGE_AXES = jnp.asarray([k for k, _, _ in BOX_EDGES], jnp.int32)  # (12,) each edge's direction
CORNER_WALLS = jnp.asarray(BOX_CORNERS, jnp.int32)  # (8, 3)


def cells_near_box_edges(tess: Tessellation, centres, ok):
    """(N,) the walkers at the boundary (tier 0) whose cells may hold a point of a box edge: a
    bounded cell is the hull of its simplices' circumcentres (`centres` (S, 3); `ok` (S,): not
    flat), so its bounding box must reach both walls of the edge. Hull walkers' (unbounded)
    cells, and those beside a flat simplex, always. A cell taken in vain costs time only."""
    n = tess.n_points
    box = tess.box.astype(tess.points.dtype)
    usable = ok[:, None]  # a flat simplex's centre is anywhere: its cells reach every wall
    high = jax.ops.segment_max(
        jnp.repeat(jnp.where(usable, centres, jnp.inf), 4, axis=0), tess.simplices.ravel(), num_segments=n + 1
    )[:n]
    low = jax.ops.segment_min(
        jnp.repeat(jnp.where(usable, centres, -jnp.inf), 4, axis=0), tess.simplices.ravel(), num_segments=n + 1
    )[:n]
    d = centres.shape[-1]  # the upper walls reached by the highest centres, the lower by the lowest
    reached = jnp.concatenate([near_walls(high, box)[:, :d], near_walls(low, box)[:, d:]], axis=1)  # (N, 2d)
    edges = jnp.any(jnp.all(reached[:, EDGE_WALLS], axis=-1), axis=-1)
    return (tess.tier == 0) & (tess.hull | edges)


def box_edge_faces(tess: Tessellation, cells):
    """Per walker at the boundary (tier 0): the 12 box edges' parts inside its cell, as their
    share of the wall faces' areas (N, 6) and first moments about the walker (N, 6, 3); whether
    each has a positive length (N, 12) and how many of its ends lie inside the box edge (N, 12)
    (vertices of the cell on two walls); and whether each box corner lies in the cell (N, 8).
    Measured for the walkers `cells` (N,) marks (`cells_near_box_edges`), zero for the others."""
    n, d = tess.points.shape
    box = tess.box.astype(tess.points.dtype)
    axes, bounds, signs = wall_bounds(box[0], box[1])
    eye = jnp.eye(3, dtype=box.dtype)

    def measured(ids):
        normals, offsets, active = cell_planes(tess, ids)
        x = tess.points[jnp.minimum(ids, n - 1)]

        def cell(x_i, nrm, off, act):  # the 12 edges at once: one program, not 12 copies
            size = over_planes("max", jnp.where(act, off, 0.0))
            tol = ROUNDING_ULPS * jnp.finfo(off.dtype).eps * jnp.maximum(size, jnp.max(box[1] - box[0]))
            walls = EDGE_WALLS  # (12, 2): each edge's two walls
            place = bounds[walls] - x_i[axes[walls]]  # (12, 2) the walls' offsets from the walker
            point = jnp.zeros((12, 3), off.dtype)
            for side in (0, 1):
                point = point.at[jnp.arange(12), axes[walls[:, side]]].set(place[:, side])
            direction = eye[EDGE_AXES]
            lo, hi, empty, _, _ = jax.vmap(line_interval, in_axes=(0, 0, None, None, None, None))(
                point, direction, nrm, off, act, size
            )
            length = jnp.where(empty, 0.0, jnp.maximum(hi - lo, 0.0))
            middle = point + 0.5 * (lo + hi)[:, None] * direction
            # per edge, its share of wall w1's face (h: the distance from w2), then of w2's
            h = signs[walls[:, ::-1]] * place[:, ::-1]  # (12, 2)
            foot = place[:, :, None] * eye[axes[walls]]  # (12, 2, 3)
            piece = 0.5 * h * length[:, None]
            shares = piece[:, :, None] * (foot + 2.0 * middle[:, None, :]) / 3.0
            area = jnp.zeros(6, off.dtype).at[walls.ravel()].add(piece.ravel())
            moment = jnp.zeros((6, 3), off.dtype).at[walls.ravel()].add(shares.reshape(-1, 3))
            real = length > tol
            ends = (lo > box[0, EDGE_AXES] - x_i[EDGE_AXES] + tol).astype(jnp.int32) + (
                hi < box[1, EDGE_AXES] - x_i[EDGE_AXES] - tol
            ).astype(jnp.int32)
            corner = bounds[CORNER_WALLS] - x_i  # (8, 3): each corner's walls are x, y and z in order
            in_cell = jnp.all(~act[None, :] | (corner @ nrm.T <= off[None, :] + tol), axis=1)
            return area, moment, real, jnp.where(real, ends, 0), in_cell

        return jax.vmap(cell)(x, normals, offsets, active)

    def empty(ids):
        m = len(ids)
        dt = tess.points.dtype
        return (
            jnp.zeros((m, 6), dt),
            jnp.zeros((m, 6, 3), dt),
            jnp.zeros((m, 12), bool),
            jnp.zeros((m, 12), jnp.int32),
            jnp.zeros((m, 8), bool),
        )

    rows, out = map_flagged_rows(cells, EDGE_CHUNK, measured, empty)
    return jax.tree_util.tree_map(lambda a: jnp.zeros((n,) + a.shape[1:], a.dtype).at[rows].set(a, mode="drop"), out)
