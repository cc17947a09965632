"""Geometry of one simplex: small determinants, face circumcentres, signed dual pieces.

Everything here acts on a single simplex and is vmapped by the public functions.
Python loops below run over the simplex's faces (a static, tiny set), never over data.
"""

from __future__ import annotations

import functools
import itertools
import math

import jax.numpy as jnp
import numpy as np


def dot(u, v):
    """Sum over the last axis of u * v, written out so XLA fuses it (no dot_general)."""
    return sum(u[..., k] * v[..., k] for k in range(u.shape[-1]))


def matvec(m, v):
    """m @ v over the last axes, written out (see `dot`)."""
    return jnp.stack([dot(m[..., i, :], v) for i in range(m.shape[-2])], axis=-1)


def vecmat(v, m):
    """v @ m over the last axes, written out (see `dot`)."""
    return sum(v[..., i, None] * m[..., i, :] for i in range(m.shape[-2]))


def cross(u, v):
    return jnp.stack([u[..., 1] * v[..., 2] - u[..., 2] * v[..., 1],
                      u[..., 2] * v[..., 0] - u[..., 0] * v[..., 2],
                      u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]], axis=-1)


def small_det(m):
    """Determinant of a k x k matrix (k <= 5) by cofactor expansion over scalar entries."""
    return _det_entries(_entries(m))


def small_adjugate(m):
    """Adjugate (transposed cofactor matrix) of a k x k matrix, so that m @ adj = det * I."""
    e = _entries(m)
    k = len(e)
    if k == 1:
        return jnp.ones_like(m)
    cof = [[(-1) ** (i + j) * _det_entries(_minor(e, j, i)) for j in range(k)] for i in range(k)]
    return jnp.stack([jnp.stack(row, axis=-1) for row in cof], axis=-2)


def _entries(m):
    k = m.shape[-1]
    return [[m[..., i, j] for j in range(k)] for i in range(k)]


def _minor(e, row: int, col: int):
    return [[v for c, v in enumerate(r) if c != col] for i, r in enumerate(e) if i != row]


def _det_entries(e):
    k = len(e)
    if k == 1:
        return e[0][0]
    if k == 2:
        return e[0][0] * e[1][1] - e[0][1] * e[1][0]
    return sum((-1) ** j * e[0][j] * _det_entries(_minor(e, 0, j)) for j in range(k))


def circumcenter_offset(edges):
    """Circumcentre of a face relative to its first vertex.

    **Arguments:**

    - `edges`: (k, d) vectors from the face's first vertex to its other k vertices.

    **Returns:**

    `(offset, ok)`: the (d,) offset (zero where the face is degenerate) and whether
    the face is non-degenerate. A full simplex (k = d) solves E u = |e|^2 / 2
    directly, which keeps the conditioning of E (the Gram form would square it);
    an edge gives its midpoint; other faces solve the Gram system. Solutions use
    the adjugate, and the one division is guarded by a double `where`.
    """
    k, d = edges.shape
    half_sq = 0.5 * dot(edges, edges)
    if k == 1:
        return 0.5 * edges[0], half_sq[0] > 0.0
    matrix = edges if k == d else jnp.stack([dot(edges[i], edges) for i in range(k)])
    det = small_det(matrix)
    scale = jnp.max(half_sq) ** (d / 2 if k == d else k)  # det(E) ~ length^d, det(Gram) ~ length^2k
    ok = jnp.abs(det) > 10.0 * jnp.finfo(edges.dtype).eps * scale
    solution = matvec(small_adjugate(matrix), half_sq) / jnp.where(ok, det, 1.0)
    offset = solution if k == d else vecmat(solution, edges)
    return jnp.where(ok, offset, 0.0), ok


@functools.lru_cache(maxsize=None)
def faces(d: int) -> tuple[tuple[int, ...], ...]:
    """All faces of a d-simplex with at least two vertices, as sorted vertex tuples."""
    return tuple(f for k in range(2, d + 2) for f in itertools.combinations(range(d + 1), k))


@functools.lru_cache(maxsize=None)
def chains(d: int) -> tuple[tuple[int, tuple[tuple[int, ...], ...], float], ...]:
    """Flags {i} < F_1 < ... < F_d = simplex, one per vertex i and order of the others.

    Each flag spans the orthoscheme (x_i, c(F_1), ..., c(F_d)). Its sign is fixed on a
    regular simplex, where every orthoscheme has positive height, so that for any
    positively oriented simplex the signed volumes of vertex i's flags add up to the
    part of i's Voronoi cell inside the simplex (negative pieces handle obtuse simplices).
    """
    ref = _regular_simplex(d)
    out = []
    for i in range(d + 1):
        others = [v for v in range(d + 1) if v != i]
        for order in itertools.permutations(others):
            flag = tuple(tuple(sorted((i,) + order[: k + 1])) for k in range(d))
            m = np.stack([_np_circumcenter(ref[list(f)]) - ref[i] for f in flag])
            out.append((i, flag, float(np.sign(np.linalg.det(m)))))
    return tuple(out)


def _regular_simplex(d: int) -> np.ndarray:
    basis = np.eye(d + 1) - 1.0 / (d + 1)
    q, _ = np.linalg.qr(basis[:, :d])
    pts = basis @ q
    if np.linalg.det(pts[1:] - pts[0]) < 0:
        pts[:, 0] *= -1.0
    return pts


def _np_circumcenter(p: np.ndarray) -> np.ndarray:
    e = p[1:] - p[0]
    g = e @ e.T
    return p[0] + np.linalg.solve(g, 0.5 * np.diag(g)) @ e


def dual_pieces(vertices):
    """Signed Voronoi-cell volume of each vertex inside one simplex.

    d = 2 and 3 use closed forms (`_dual_pieces_2d`, `_dual_pieces_3d`); other d
    the general flag decomposition `dual_pieces_flags`. All agree to rounding.
    """
    d = vertices.shape[1]
    if d == 2:
        return _dual_pieces_2d(vertices)
    if d == 3:
        return _dual_pieces_3d(vertices)
    return dual_pieces_flags(vertices)


def _cross2(u, v):
    return u[0] * v[1] - u[1] * v[0]


def _triangle_pieces(p):
    """8 |cross| times the signed cotangent pieces (L_ij cot_k + L_ik cot_j) / 8 of a triangle.

    cot_k = dot_k / |cross| with dot_k the dot product of the two edges leaving k,
    so the returned numerators are L_ij dot_k + L_ik dot_j; callers divide by the
    power of |cross| they need (no square root).
    """
    e = [p[(i + 1) % 3] - p[i] for i in range(3)]  # e_i from vertex i to i+1
    sq = [dot(v, v) for v in e]  # sq[i] = |p_{i+1} - p_i|^2
    dots = [-dot(e[i], e[(i + 2) % 3]) for i in range(3)]  # (p_{i+1}-p_i).(p_{i-1}-p_i)
    # edge (i, i+1) is opposite vertex i+2, edge (i+2, i) opposite vertex i+1
    return [sq[i] * dots[(i + 2) % 3] + sq[(i + 2) % 3] * dots[(i + 1) % 3] for i in range(3)]


def _dual_pieces_2d(vertices):
    rel = vertices - vertices[0]
    twice_area = _cross2(rel[1], rel[2])
    ok = jnp.abs(twice_area) > 10.0 * jnp.finfo(rel.dtype).eps * jnp.sum(rel[1:] ** 2)
    # piece_i = (L_ij cot_k + L_ik cot_j) / 8, cot = dot / |2A|.
    num = jnp.stack(_triangle_pieces(rel))
    return jnp.where(ok, num / (8.0 * jnp.abs(jnp.where(ok, twice_area, 1.0))), 0.0)


def _dual_pieces_3d(vertices):
    """V_i = (1/3) sum over faces f of i of H_f a_{f,i}: the circumcentre c cuts the tet
    into signed pyramids over its faces, and the bisector planes (which contain c)
    cut each pyramid like the face's own 2D circumcentric pieces a_{f,i}."""
    rel = vertices - vertices[0]
    offset, ok = circumcenter_offset(rel[1:])
    pieces = [0.0] * 4
    for opposite in range(4):
        f = [v for v in range(4) if v != opposite]
        p = [rel[v] for v in f]
        normal = cross(p[1] - p[0], p[2] - p[0])
        n_sq = dot(normal, normal)
        side = jnp.sign(dot(normal, rel[opposite] - p[0]))
        # H_f |n| = side * n.(c - p0); a_{f,i} * 8 |n| = num_i; so H_f a_i = side n.(c-p0) num_i / (8 |n|^2)
        height_num = side * dot(normal, offset - p[0])
        safe = jnp.where(n_sq > 0, n_sq, 1.0)
        for v, num in zip(f, _triangle_pieces(p)):
            pieces[v] = pieces[v] + height_num * num / (24.0 * safe)
    return jnp.where(ok, jnp.stack(pieces), 0.0)


def dual_pieces_flags(vertices):
    """Signed Voronoi-cell volume of each vertex inside one simplex, any d.

    **Arguments:**

    - `vertices`: (d + 1, d) coordinates.

    **Returns:**

    (d + 1,) pieces whose sum is the simplex volume; zero for a degenerate simplex.
    """
    d = vertices.shape[1]
    rel = vertices - vertices[0]
    centers, ok = {}, None
    for f in faces(d):
        offset, ok = circumcenter_offset(rel[np.array(f[1:])] - rel[f[0]])
        centers[f] = rel[f[0]] + offset
    orientation = small_det(rel[1:])  # the last face is the whole simplex: `ok` is its flag
    pieces = [0.0] * (d + 1)
    for i, flag, sign in chains(d):
        m = jnp.stack([centers[f] - rel[i] for f in flag])
        pieces[i] = pieces[i] + sign * small_det(m)
    pieces = jnp.stack(pieces) * jnp.sign(orientation) / math.factorial(d)
    return jnp.where(ok, pieces, 0.0)


def simplex_circumcenter(vertices):
    """Circumcentre (d,) of one simplex (its first vertex where degenerate)."""
    offset, _ = circumcenter_offset(vertices[1:] - vertices[0])
    return vertices[0] + offset
