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


def small_det(m):
    """Determinant of a k x k matrix (k <= 5) by explicit cofactor expansion."""
    k = m.shape[-1]
    if k == 1:
        return m[..., 0, 0]
    if k == 2:
        return m[..., 0, 0] * m[..., 1, 1] - m[..., 0, 1] * m[..., 1, 0]
    total = 0.0
    for j in range(k):
        total = total + (-1) ** j * m[..., 0, j] * small_det(_minor(m, 0, j))
    return total


def _minor(m, row: int, col: int):
    k = m.shape[-1]
    rows = [r for r in range(k) if r != row]
    cols = [c for c in range(k) if c != col]
    return m[..., np.array(rows), :][..., :, np.array(cols)]


def small_adjugate(m):
    """Adjugate (transposed cofactor matrix) of a k x k matrix, so that m @ adj = det * I."""
    k = m.shape[-1]
    if k == 1:
        return jnp.ones_like(m)
    rows = []
    for i in range(k):
        row = []
        for j in range(k):
            row.append((-1) ** (i + j) * small_det(_minor(m, j, i)))
        rows.append(jnp.stack(row, axis=-1))
    return jnp.stack(rows, axis=-2)


def circumcenter_offset(edges):
    """Circumcentre of a face relative to its first vertex.

    **Arguments:**

    - `edges`: (k, d) vectors from the face's first vertex to its other k vertices.

    **Returns:**

    `(offset, gram_det)`: the (d,) offset (zero where the face is degenerate) and
    det of the Gram matrix (zero for a degenerate face). Uses the adjugate, so the
    only division is guarded by a double `where` and gradients stay finite.
    """
    gram = edges @ edges.T
    half_sq = 0.5 * jnp.diagonal(gram)
    det = small_det(gram)
    scale = jnp.max(half_sq) ** edges.shape[0]
    ok = jnp.abs(det) > 10.0 * jnp.finfo(edges.dtype).eps * scale
    safe_det = jnp.where(ok, det, 1.0)
    lam = small_adjugate(gram) @ half_sq / safe_det
    return jnp.where(ok, lam @ edges, 0.0), jnp.where(ok, det, 0.0)


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

    **Arguments:**

    - `vertices`: (d + 1, d) coordinates.

    **Returns:**

    (d + 1,) pieces whose sum is the simplex volume; zero for a degenerate simplex.
    """
    d = vertices.shape[1]
    rel = vertices - vertices[0]
    centers, gram_det = {}, None
    for f in faces(d):
        offset, gram_det = circumcenter_offset(rel[np.array(f[1:])] - rel[f[0]])
        centers[f] = rel[f[0]] + offset
    orientation = small_det(rel[1:])  # the last face is the whole simplex: gram_det is its
    pieces = [0.0] * (d + 1)
    for i, flag, sign in chains(d):
        m = jnp.stack([centers[f] - rel[i] for f in flag])
        pieces[i] = pieces[i] + sign * small_det(m)
    pieces = jnp.stack(pieces) * jnp.sign(orientation) / math.factorial(d)
    return jnp.where(gram_det != 0.0, pieces, 0.0)


def simplex_circumcenter(vertices):
    """Circumcentre (d,) of one simplex (its first vertex where degenerate)."""
    offset, _ = circumcenter_offset(vertices[1:] - vertices[0])
    return vertices[0] + offset
