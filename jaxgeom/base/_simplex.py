"""Geometry of one simplex: small determinants, face circumcentres, signed dual pieces.

Everything here acts on a single simplex and is vmapped by the public functions.
A simplex arrives coordinate-major: a tuple of d arrays, coordinate k of its d + 1
vertices (`Tessellation` gathers one coordinate at a time). Inside, vectors are Python
lists of scalars, so XLA sees only elementwise arithmetic on contiguous (S,) arrays
and fuses it: on CPU this is several times faster than slicing (S, d + 1, d) arrays.
Python loops below run over a simplex's vertices and faces (static), never over data.
"""

from __future__ import annotations

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np

# Small per-walker tensors are written out entry by entry up to this dimension (XLA fuses
# each entry's products and sums; batched small matmuls are several times slower on CPU);
# above it they are einsums: one op per entry is d^2 to d^4 ops to compile (a d = 30 k-NN
# graph's Hessian fit took over 10 minutes, its emergent metric 45 s).
WRITTEN_OUT_MAX_DIM = 3
HIGHEST = jax.lax.Precision.HIGHEST  # einsums in full float32 on GPUs too (no TF32)


def safe_sqrt(x):
    """sqrt for x > 0 and 0 elsewhere (padding, flat simplices), with finite gradients."""
    pos = x > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, x, 1.0)), 0.0)


def dot(u, v):
    """Sum over the last axis of u * v, written out so XLA fuses it (no dot_general)."""
    return sum(u[..., k] * v[..., k] for k in range(u.shape[-1]))


def _sub(u, v):
    return [a - b for a, b in zip(u, v, strict=True)]


def _vdot(u, v):
    return sum(a * b for a, b in zip(u, v, strict=True))


def _cross3(u, v):
    return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]


def _minor(e, row: int, col: int):
    return [[v for c, v in enumerate(r) if c != col] for i, r in enumerate(e) if i != row]


def det_entries(e):
    """Determinant of a k x k matrix given as nested lists of scalars (cofactor expansion)."""
    k = len(e)
    if k == 1:
        return e[0][0]
    if k == 2:
        return e[0][0] * e[1][1] - e[0][1] * e[1][0]
    return sum((-1) ** j * e[0][j] * det_entries(_minor(e, 0, j)) for j in range(k))


def _adjugate_entries(e):
    k = len(e)
    if k == 1:
        return [[1.0]]
    return [[(-1) ** (i + j) * det_entries(_minor(e, j, i)) for j in range(k)] for i in range(k)]


def _entries(m):
    k = m.shape[-1]
    return [[m[..., i, j] for j in range(k)] for i in range(k)]


def small_det(m):
    """Determinant of (..., k, k) arrays (k <= 5) by explicit cofactor expansion."""
    return det_entries(_entries(m))


def small_adjugate(m):
    """Adjugate of (..., k, k) arrays, so that m @ adj = det * I."""
    adj = _adjugate_entries(_entries(m))
    if m.shape[-1] == 1:
        return jnp.ones_like(m)
    return jnp.stack([jnp.stack(row, axis=-1) for row in adj], axis=-2)


def _vertices(coords):
    """Vertex v of a coordinate-major simplex as a list of d scalars."""
    return [[c[v] for c in coords] for v in range(coords[0].shape[0])]


def circumcenter_offset(edges):
    """Circumcentre of a face relative to its first vertex.

    **Arguments:**

    - `edges`: k vectors (lists of d scalars) from the face's first vertex to the others.

    **Returns:**

    `(offset, ok)`: the offset (list of d scalars, zero where the face is degenerate)
    and whether the face is non-degenerate. A full simplex (k = d) solves
    E u = |e|^2 / 2 directly, keeping the conditioning of E (the Gram form would
    square it); an edge gives its midpoint; other faces solve the Gram system.
    Solutions use the adjugate, and the one division is guarded by a double `where`.
    """
    k, d = len(edges), len(edges[0])
    half_sq = [0.5 * _vdot(e, e) for e in edges]
    if k == 1:
        return [0.5 * x for x in edges[0]], half_sq[0] > 0.0
    matrix = edges if k == d else [[_vdot(a, b) for b in edges] for a in edges]
    det = det_entries(matrix)
    scale = max_scalar(half_sq) ** (d / 2 if k == d else k)  # det(E) ~ length^d, det(Gram) ~ length^2k
    ok = jnp.abs(det) > 10.0 * jnp.finfo(jnp.result_type(det)).eps * scale
    safe = jnp.where(ok, det, 1.0)
    adj = _adjugate_entries(matrix)
    solution = [sum(adj[i][j] * half_sq[j] for j in range(k)) / safe for i in range(k)]
    offset = solution if k == d else [sum(solution[i] * edges[i][c] for i in range(k)) for c in range(d)]
    return [jnp.where(ok, o, 0.0) for o in offset], ok


def max_scalar(values):
    return functools.reduce(jnp.maximum, values)


@functools.cache
def faces(d: int) -> tuple[tuple[int, ...], ...]:
    """All faces of a d-simplex with at least two vertices, as sorted vertex tuples."""
    return tuple(f for k in range(2, d + 2) for f in itertools.combinations(range(d + 1), k))


@functools.cache
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


def dual_pieces(coords):
    """Signed Voronoi-cell volume of each vertex inside one simplex.

    **Arguments:**

    - `coords`: tuple of d arrays (d + 1,), coordinate k of each vertex.

    **Returns:**

    (d + 1,) pieces whose sum is the simplex volume; zero for a degenerate simplex.
    d = 2 and 3 use closed forms; other d the flag decomposition `dual_pieces_flags`.
    All agree to rounding.
    """
    d = len(coords)
    rel = [_sub(p, _vertices(coords)[0]) for p in _vertices(coords)]
    if d == 2:
        return _dual_pieces_2d(rel)
    if d == 3:
        return _dual_pieces_3d(rel)
    return _dual_pieces_flags(rel)


def _triangle_pieces(p):
    """8 |cross| times the signed cotangent pieces (L_ij cot_k + L_ik cot_j) / 8 of a triangle.

    cot_k = dot_k / |cross| with dot_k the dot product of the two edges leaving k,
    so the returned numerators are L_ij dot_k + L_ik dot_j; callers divide by the
    power of |cross| they need (no square root).
    """
    e = [_sub(p[(i + 1) % 3], p[i]) for i in range(3)]  # e_i from vertex i to i+1
    sq = [_vdot(v, v) for v in e]  # sq[i] = |p_{i+1} - p_i|^2
    dots = [-_vdot(e[i], e[(i + 2) % 3]) for i in range(3)]  # (p_{i+1}-p_i).(p_{i-1}-p_i)
    # edge (i, i+1) is opposite vertex i+2, edge (i+2, i) opposite vertex i+1
    return [sq[i] * dots[(i + 2) % 3] + sq[(i + 2) % 3] * dots[(i + 1) % 3] for i in range(3)]


def _dual_pieces_2d(rel):
    twice_area = rel[1][0] * rel[2][1] - rel[1][1] * rel[2][0]
    ok = jnp.abs(twice_area) > 10.0 * jnp.finfo(jnp.result_type(twice_area)).eps * (
        _vdot(rel[1], rel[1]) + _vdot(rel[2], rel[2])
    )
    denom = 8.0 * jnp.abs(jnp.where(ok, twice_area, 1.0))
    return jnp.stack([jnp.where(ok, num / denom, 0.0) for num in _triangle_pieces(rel)])


def _dual_pieces_3d(rel):
    """V_i = (1/3) sum over faces f of i of H_f a_{f,i}: the circumcentre c cuts the tet
    into signed pyramids over its faces, and the bisector planes (which contain c)
    cut each pyramid like the face's own 2D circumcentric pieces a_{f,i}."""
    offset, ok = circumcenter_offset(rel[1:])
    pieces = [0.0] * 4
    for opposite in range(4):
        f = [v for v in range(4) if v != opposite]
        p = [rel[v] for v in f]
        normal = _cross3(_sub(p[1], p[0]), _sub(p[2], p[0]))
        n_sq = _vdot(normal, normal)
        side = jnp.sign(_vdot(normal, _sub(rel[opposite], p[0])))
        # H_f |n| = side n.(c - p0) and a_{f,i} 8 |n| = num_i, so H_f a_i = side n.(c - p0) num_i / (8 |n|^2)
        height = side * _vdot(normal, _sub(offset, p[0])) / (24.0 * jnp.where(n_sq > 0, n_sq, 1.0))
        for v, num in zip(f, _triangle_pieces(p), strict=True):
            pieces[v] = pieces[v] + height * num
    return jnp.stack([jnp.where(ok, piece, 0.0) for piece in pieces])


def dual_pieces_flags(coords):
    """`dual_pieces` by the general flag decomposition (any d; the reference for d = 2, 3)."""
    return _dual_pieces_flags([_sub(p, _vertices(coords)[0]) for p in _vertices(coords)])


def _dual_pieces_flags(rel):
    d = len(rel[0])
    centers, ok = {}, None
    for f in faces(d):
        offset, ok = circumcenter_offset([_sub(rel[v], rel[f[0]]) for v in f[1:]])
        centers[f] = [a + b for a, b in zip(rel[f[0]], offset, strict=True)]
    orientation = det_entries(rel[1:])  # the last face is the whole simplex: `ok` is its flag
    pieces = [0.0] * (d + 1)
    for i, flag, sign in chains(d):
        pieces[i] = pieces[i] + sign * det_entries([_sub(centers[f], rel[i]) for f in flag])
    scale = jnp.sign(orientation) / math.factorial(d)
    return jnp.stack([jnp.where(ok, p * scale, 0.0) for p in pieces])


def _first_vertex_and_offset(coords):
    """(first vertex, circumcentre - first vertex) of one coordinate-major simplex."""
    verts = _vertices(coords)
    offset, _ = circumcenter_offset([_sub(p, verts[0]) for p in verts[1:]])
    return verts[0], offset


def simplex_circumcenter(coords):
    """Circumcentre (d,) of one coordinate-major simplex (its first vertex where degenerate)."""
    return simplex_circumcenter_and_flat(coords)[0]


def simplex_circumcenter_and_flat(coords):
    """(circumcentre (d,), flat): `simplex_circumcenter` and whether the simplex is degenerate."""
    verts = _vertices(coords)
    offset, ok = circumcenter_offset([_sub(p, verts[0]) for p in verts[1:]])
    return jnp.stack([a + b for a, b in zip(verts[0], offset, strict=True)]), ~ok


def simplex_circumradius(coords):
    """Circumradius of one coordinate-major simplex (0 where degenerate)."""
    _, offset = _first_vertex_and_offset(coords)
    return safe_sqrt(_vdot(offset, offset))


# Cyclic Jacobi sweeps that take a symmetric d x d matrix to machine-precision diagonal form
# (quadratic convergence; d = 2 is exact after one rotation).
JACOBI_SWEEPS = {1: 0, 2: 1, 3: 6, 4: 8}


def small_eigh(m):
    """Eigenvalues (ascending) and eigenvectors (columns) of symmetric (..., d, d) arrays,
    d <= 4, by cyclic Jacobi rotations in plain elementwise arithmetic.

    XLA fuses each sweep (batched LAPACK `syevd` is slower, bench/small_eigh.py), and it
    makes no LAPACK call: two batched LAPACK calls running at once on XLA's CPU thread
    pool deadlocked (jaxlib 0.10, 2 cores), which hung `ricci_scalar` with a Hessian
    metric. The sweeps run in a `fori_loop`, so one sweep is traced and compiled, not
    `JACOBI_SWEEPS[d]` copies of it.
    """
    d = m.shape[-1]
    a = _entries(m)
    zero, one = jnp.zeros_like(a[0][0]), jnp.ones_like(a[0][0])
    v = [[one if i == j else zero for j in range(d)] for i in range(d)]

    def sweep(_, av):
        for p, q in itertools.combinations(range(d), 2):
            av = _jacobi_rotation(*av, p, q)
        return av

    return eigenpairs_ascending(*jax.lax.fori_loop(0, JACOBI_SWEEPS[d], sweep, (a, v)))


def eigenpairs_ascending(a, v):
    """(eigenvalues ascending, eigenvectors as columns) from the entries `a` of a matrix the
    Jacobi rotations diagonalised and the entries `v` of their accumulated product."""
    d = len(a)
    values = jnp.stack([a[i][i] for i in range(d)], axis=-1)
    vectors = jnp.stack([jnp.stack(row, axis=-1) for row in v], axis=-2)
    order = jnp.argsort(values, axis=-1)
    return jnp.take_along_axis(values, order, axis=-1), jnp.take_along_axis(vectors, order[..., None, :], axis=-1)


def _jacobi_rotation(a, v, p: int, q: int):
    """Rotate rows/columns p, q of the symmetric entries `a` so that a[p][q] = 0; accumulate
    the rotation in the eigenvector entries `v` (Golub & Van Loan, Algorithm 8.5.1)."""
    apq = a[p][q]
    t = _jacobi_tangent(a[q][q] - a[p][p], apq)
    c = 1.0 / jnp.sqrt(t * t + 1.0)
    s = t * c
    a = [row[:] for row in a]
    for k in range(len(a)):
        if k not in (p, q):
            akp, akq = a[k][p], a[k][q]
            a[k][p] = a[p][k] = c * akp - s * akq
            a[k][q] = a[q][k] = s * akp + c * akq
    a[p][p], a[q][q] = a[p][p] - t * apq, a[q][q] + t * apq
    a[p][q] = a[q][p] = jnp.zeros_like(apq)
    v = [row[:] for row in v]
    for k in range(len(v)):
        vkp, vkq = v[k][p], v[k][q]
        v[k][p], v[k][q] = c * vkp - s * vkq, s * vkp + c * vkq
    return a, v


def _jacobi_tangent(delta, apq):
    """tan of the Jacobi angle that zeroes a_pq, with delta = a_qq - a_pp.

    Golub & Van Loan's t = sign(theta) / (|theta| + sqrt(theta^2 + 1)), theta = delta / (2 a_pq),
    multiplied through by |2 a_pq| / m with m = max(|delta|, |2 a_pq|):
    t = s (2 a_pq / m) / (|delta| / m + hypot(delta / m, 2 a_pq / m)), s = sign(delta) (+1 at 0).
    No division by a_pq: after convergence a_pq is tiny, theta overflowed, and the derivative
    of theta (~1 / a_pq^2) times the derivative of its tangent (~0) was inf x 0 = NaN.
    """
    off = apq != 0
    m = jnp.maximum(jnp.abs(delta), 2.0 * jnp.abs(apq))
    m = jnp.where(off, m, 1.0)
    u, w = 2.0 * apq / m, delta / m
    sign = jnp.where(delta >= 0, 1.0, -1.0)
    return jnp.where(off, sign * u / (jnp.abs(w) + jnp.sqrt(w * w + u * u)), 0.0)


def small_cholesky(m):
    """Lower Cholesky factor of symmetric positive definite (..., d, d) arrays, written out
    (no batched LAPACK call; see `small_eigh`). NaN where m is not positive definite."""
    d = m.shape[-1]
    a = _entries(m)
    low = [[jnp.zeros_like(a[0][0]) for _ in range(d)] for _ in range(d)]
    for j in range(d):
        pivot = a[j][j] - sum(low[j][k] ** 2 for k in range(j))
        low[j][j] = jnp.sqrt(pivot)  # NaN for a non-positive pivot
        for i in range(j + 1, d):
            low[i][j] = (a[i][j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    return jnp.stack([jnp.stack(row, axis=-1) for row in low], axis=-2)


def small_positive_definite(m):
    """Whether symmetric (..., d, d) arrays are positive definite: every pivot of their
    Cholesky elimination is > 0 (Sylvester). A positive determinant alone is not enough
    from d = 3 on (two negative eigenvalues)."""
    low = small_cholesky(m)
    pivots = jnp.diagonal(low, axis1=-2, axis2=-1)
    return jnp.all(pivots > 0, axis=-1)  # NaN pivots compare False


def spectral_function(fn, eigh, h, p):
    """F(h) = Q diag(fn(lambda, p)) Q^T for a symmetric (d, d) `h` = Q diag(lambda) Q^T, with
    derivatives of every order that stay finite and right at repeated eigenvalues.

    **Arguments:**

    - `fn`: elementwise scalar function (lambda, p) -> value, differentiable in both.
    - `eigh`: the eigensolver, (d, d) -> (eigenvalues, eigenvectors as columns).
    - `h`: the symmetric matrix.
    - `p`: the scalar parameter of `fn` (may be traced).

    Derivatives never go through `eigh`. The k-th derivative in directions E_1..E_k is
    Q M Q^T with M_ij = sum over orders s of the E's and indices m of
    fn[lambda_i, lambda_m1, ..., lambda_m(k-1), lambda_j] (E^_s1)_{i m1} ... (E^_sk)_{m(k-1) j},
    E^ = Q^T E Q and fn[...] the divided differences of fn (Daleckii and Krein for k = 1);
    a derivative in p replaces fn by its p-derivative. Each derivative is itself a custom JVP
    whose tangent is the next order, so `jax.hessian` of a metric, and its gradient, are
    exact too. Differentiating the eigenvectors instead is 0/0 at a repeated eigenvalue: an
    exact repeat gave a derivative that missed the off-diagonal part of the direction, a
    near repeat cancelling ~1/gap terms, and second derivatives NaN.
    """
    return _spectral_derivative(fn, eigh, 0, 0, h, jnp.asarray(p, h.dtype), (), ())


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2, 3))
def _spectral_derivative(fn, eigh, n_p: int, n_h: int, h, p, dps: tuple, dhs: tuple):
    """The derivative of `spectral_function` of order `n_p` in p (directions `dps`) and
    `n_h` in h (directions `dhs`)."""
    lam, q = eigh(h)
    value_of = _lambda_derivatives(fn, n_p, p)
    qt = jnp.swapaxes(q, -1, -2)
    scale = functools.reduce(lambda a, b: a * b, dps, jnp.ones((), h.dtype))
    if n_h == 0:
        return (q * (value_of(0)(lam) * scale)) @ qt
    table = _divided_difference_table(value_of, lam, n_h)
    hats = [qt @ e @ q for e in dhs]
    letters = "abcdefgh"[: n_h - 1]
    indices = ["i"] + list(letters) + ["j"]
    spec = "".join(indices) + "," + ",".join(indices[t] + indices[t + 1] for t in range(n_h)) + "->ij"
    inner = sum(jnp.einsum(spec, table, *[hats[s] for s in order]) for order in itertools.permutations(range(n_h)))
    return q @ (inner * scale) @ qt


@_spectral_derivative.defjvp
def _spectral_derivative_jvp(fn, eigh, n_p, n_h, primals, tangents):
    h, p, dps, dhs = primals
    t_h, t_p, t_dps, t_dhs = tangents
    out = _spectral_derivative(fn, eigh, n_p, n_h, h, p, dps, dhs)
    # multilinear in dps and dhs, so a tangent of one direction replaces it
    tangent = _spectral_derivative(fn, eigh, n_p, n_h + 1, h, p, dps, dhs + (t_h,)) + _spectral_derivative(
        fn, eigh, n_p + 1, n_h, h, p, dps + (t_p,), dhs
    )
    for i in range(n_p):
        tangent = tangent + _spectral_derivative(fn, eigh, n_p, n_h, h, p, dps[:i] + (t_dps[i],) + dps[i + 1 :], dhs)
    for i in range(n_h):
        tangent = tangent + _spectral_derivative(fn, eigh, n_p, n_h, h, p, dps, dhs[:i] + (t_dhs[i],) + dhs[i + 1 :])
    return out, tangent


def _lambda_derivatives(fn, n_p: int, p):
    """j -> the elementwise function lambda -> d^j/dlambda^j d^n_p/dp^n_p fn(lambda, p)."""

    def in_p(lam, p_, order):
        if order == 0:
            return fn(lam, p_)
        return jax.jvp(lambda y: in_p(lam, y, order - 1), (p_,), (jnp.ones_like(p_),))[1]

    def in_lambda(lam, order):
        if order == 0:
            return in_p(lam, p, n_p)
        return jax.jvp(lambda x: in_lambda(x, order - 1), (lam,), (jnp.ones_like(lam),))[1]

    return lambda order: lambda lam: in_lambda(lam, order)


def _divided_difference_table(value_of, lam, k: int):
    """fn[lambda_i0, ..., lambda_ik] for every index tuple: a (d,) * (k + 1) array.

    The points are sorted (divided differences are symmetric), so a tuple's spread is its
    last minus its first point. Where the spread is below eps^(1 / (k + 2)) of the spectrum's
    scale, the Taylor value fn^(k)(centroid) / k! (error O(spread^2)) replaces the recursion
    (error O(eps / spread^k))."""
    d = lam.shape[-1]
    axes = [jnp.reshape(lam, [d if a == t else 1 for a in range(k + 1)]) for t in range(k + 1)]
    points = jnp.sort(jnp.stack(jnp.broadcast_arrays(*axes)), axis=0)
    scale = jnp.max(jnp.abs(lam))
    eps = jnp.finfo(lam.dtype).eps
    memo = {}

    def divided(lo: int, hi: int):
        if (lo, hi) not in memo:
            if lo == hi:
                memo[lo, hi] = value_of(0)(points[lo])
            else:
                order = hi - lo
                spread = points[hi] - points[lo]
                close = spread <= eps ** (1.0 / (order + 2)) * scale
                centroid = jnp.mean(points[lo : hi + 1], axis=0)
                taylor = value_of(order)(centroid) / math.factorial(order)
                far = (divided(lo + 1, hi) - divided(lo, hi - 1)) / jnp.where(close, 1.0, spread)
                memo[lo, hi] = jnp.where(close, taylor, far)
        return memo[lo, hi]

    return divided(0, k)
