"""Geodesic distances by the heat method (Crane, Weischedel and Wardetzky, 2013) on Delaunay simplices.

Everything is intrinsic: each simplex is known only through its squared *metric* edge
lengths (the curvature's machinery, `simplex_sq_length_columns`). With the Gram matrix G
of its edge vectors from vertex 0, G_ij = (l_0i^2 + l_0j^2 - l_ij^2) / 2, the barycentric
gradients satisfy grad(phi_i) . grad(phi_j) = (G^-1)_ij (i, j >= 1) and grad(phi_0) = -sum
grad(phi_i); the volume is sqrt(det G) / d!. That gives, in any dimension,

- the stiffness (cotangent Laplacian) of a simplex, vol B^T G^-1 B with B = [-1 | I]
  (in 2D the cotangent weights, in 3D the dihedral-angle cotangent weights),
- the lumped mass, vol / (d + 1) to each vertex,
- the gradient of a linear function, |grad u|^2 = du^T G^-1 du with du_i = u_i - u_0, and
  the integrated divergence of a piecewise-constant field X at vertex a, vol X . grad(phi_a).

The method: (M + t K) u = delta_source; X = -grad u / |grad u| per simplex; K phi = div X;
distance = phi - phi(source). Linear systems go through `lax.custom_linear_solve` (so
derivatives are implicit, with the matvec in JAX), solved either by a host factorisation
(CHOLMOD, or SuperLU) cached per operator ("direct") or by Jacobi-preconditioned conjugate gradients ("cg").
"""

from __future__ import annotations

import atexit
import collections
import hashlib
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from jaxtyping import Array, Bool, Float, Int

try:
    import cholespy
except ImportError:  # no wheel for this platform: SuperLU alone
    cholespy = None

from ..base._simplex import safe_sqrt, small_adjugate, small_det, small_positive_definite
from ..tessellation._graph import Tessellation
from ._metric import edge_pairs, simplex_sq_length_columns, simplex_sq_lengths_with_references

HEAT_BOUNDARIES = ("mean", "neumann", "dirichlet")
HEAT_SOLVERS = ("auto", "direct", "cg")
SOURCE_BATCH = 16  # sources solved together (one host call, one vmapped CG)
# CG's heat solution is trusted on simplices with a vertex where |u| > CG_TRUST * max u
# (float64, float32): three decades above the heat step's relative residual tolerance (`_solver`)
CG_TRUST = {True: 1e-9, False: 1e-2}


class HeatOperators(eqx.Module):
    """The discrete operators of one graph and metric (all per simplex except `mass`).

    **Fields:**

    - `simplices`: (S, d + 1) vertex ids, padding rows = N.
    - `stiffness`: (S, d + 1, d + 1) local stiffness matrices vol B^T G^-1 B (0 on
      padding and on simplices whose metric lengths form no simplex, det G <= 0).
    - `inverse_gram`: (S, d, d) G^-1 of each simplex (0 where invalid).
    - `volumes`: (S,) metric volumes (0 where invalid).
    - `mass`: (N,) lumped mass.
    - `t`: () heat time step.
    - `closes`: (S,) whether the simplex's own metric edge lengths closed (`closing_sq_lengths`).
    """

    simplices: Int[Array, "S d1"]
    stiffness: Float[Array, "S d1 d1"]
    inverse_gram: Float[Array, "S d d"]
    volumes: Float[Array, " S"]
    mass: Float[Array, " N"]
    t: Float[Array, ""]
    closes: Bool[Array, " S"]

    @property
    def n_points(self) -> int:
        return self.mass.shape[0]


def default_time_step(mean_edge, n: int, d: int):
    """t = N^(1/(2d)) h^2, h the mean metric edge length: the geometric mean of h and the
    domain's length L ~ h N^(1/d), squared, is t = h^(3/2) L^(1/2). A fixed t = h^2 leaves a
    direction error of the normalised gradient that does not shrink on irregular meshes
    (measured: a 1.5-2% median error at every N); t / h^2 -> infinity removes it, and
    sqrt(t) / L -> 0 keeps the boundary's and the curvature's bias vanishing. (t = h L, the
    other natural choice, is as good in 2D and 5x worse in 3D at N = 3e4, through the boundary.)"""
    return mean_edge**2 * n ** (0.5 / d)


def heat_operators(tess: Tessellation, metric=None, *, mode: str = "full", t=None) -> HeatOperators:
    """Assemble [`HeatOperators`][] from the squared metric edge lengths of the simplices."""
    d, n = tess.dim, tess.n_points
    valid = tess.simplex_mask
    sq, closes = closing_sq_lengths(tess, metric, mode)
    columns = [sq[:, k] for k in range(sq.shape[1])]
    gram = _gram(columns, d)
    scale = _unit_scale(sq, valid)
    unit = gram / scale[:, None, None]
    det = small_det(unit)
    ok = valid & (det > 0) & small_positive_definite(unit)
    safe_det = jnp.where(ok, det, 1.0)
    inverse = jnp.where(ok[:, None, None], small_adjugate(unit) / (safe_det * scale)[:, None, None], 0.0)
    volumes = jnp.where(ok, safe_sqrt(safe_det) * scale ** (d / 2) / math.factorial(d), 0.0)
    stiffness = volumes[:, None, None] * _expand_barycentric(inverse)
    stiffness = jnp.where(closes[:, None, None], stiffness, nonnegative_weights(stiffness))
    mass = jax.ops.segment_sum(jnp.repeat(volumes / (d + 1), d + 1), tess.simplices.ravel(), num_segments=n)
    if t is None:
        edges = jnp.where(valid[:, None], safe_sqrt(sq), 0.0)
        mean_edge = jnp.sum(edges) / jnp.maximum(jnp.sum(valid, dtype=jnp.int32) * sq.shape[1], 1).astype(sq.dtype)
        t = default_time_step(mean_edge, n, d)
    assert tess.simplices is not None  # Delaunay graphs only: refused at the boundary
    return HeatOperators(tess.simplices, stiffness, inverse, volumes, mass, jnp.asarray(t, sq.dtype), closes)


def closing_sq_lengths(tess: Tessellation, metric, mode: str):
    """(S, P) squared metric edge lengths that close every simplex of positive Euclidean
    volume, and (S,) whether a simplex's own edge lengths closed.

    Each edge is measured in its own metric, as the curvature measures it. Where those
    metrics differ so much along a simplex that its lengths violate a triangle (Cayley-Menger)
    inequality, G not positive definite (the metric varies on a scale shorter than the edges: a clipped
    Hessian metric across Rastrigin's wells with a few hundred walkers), the simplex takes
    the mean of its edge metrics instead: a constant metric, in which a nondegenerate
    simplex always closes. So the heat operators keep every simplex and stay connected.
    """
    if metric is None:
        sq = jnp.stack(simplex_sq_length_columns(tess, metric, mode=mode), axis=1)
        return sq, jnp.ones(sq.shape[0], bool)
    every_edge = tuple(range(len(edge_pairs(tess.dim))))
    sq_g, (sq_mean,) = simplex_sq_lengths_with_references(tess, metric, mode=mode, hinge_edges=(every_edge,))
    unit = sq_g / _unit_scale(sq_g, tess.simplex_mask)[:, None]
    closes = small_positive_definite(_gram([unit[:, k] for k in range(unit.shape[1])], tess.dim)) | ~tess.simplex_mask
    return jnp.where(closes[:, None], sq_g, sq_mean), closes


def _unit_scale(sq, valid):
    """(S,) the largest squared edge length of each valid simplex (1 elsewhere): dividing by it
    scales a simplex to unit size, so that det G (length^2d) neither under- nor overflows. The
    results do not depend on its value, so it carries no gradient (reduce_max's derivative
    divides by the count of entries equal to the max: 0 where XLA rounds the two copies
    differently, as at --xla_backend_optimization_level=0, which gave NaN gradients)."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.where(valid[:, None], sq, 0.0), axis=1))
    return jnp.where(scale > 0, scale, 1.0)


def nonnegative_weights(stiffness):
    """The local stiffness with its negative edge weights (positive off-diagonal entries) set to
    0 and the diagonal refilled so that rows still sum to 0: a graph Laplacian with non-negative
    weights, whose heat flow cannot undershoot (the discrete maximum principle)."""
    eye = jnp.eye(stiffness.shape[-1], dtype=stiffness.dtype)
    off = jnp.minimum(stiffness, 0.0) * (1.0 - eye)
    return off - eye * jnp.sum(off, axis=-1, keepdims=True)


def _gram(columns, d: int):
    """G_ij = (l_0i^2 + l_0j^2 - l_ij^2) / 2, i, j = 1..d, from columns ordered as `edge_pairs(d)`."""
    pairs = {pair: k for k, pair in enumerate(edge_pairs(d))}

    def sq(a, b):
        return 0.0 if a == b else columns[pairs[(min(a, b), max(a, b))]]

    rows = [[0.5 * (sq(0, i) + sq(0, j) - sq(i, j)) for j in range(1, d + 1)] for i in range(1, d + 1)]
    return jnp.stack([jnp.stack([jnp.broadcast_to(v, columns[0].shape) for v in row], -1) for row in rows], -2)


def _expand_barycentric(inverse):
    """B^T Q B for B = [-1 | I]: the (d + 1) x (d + 1) Gram matrix of all barycentric gradients."""
    first = -jnp.sum(inverse, axis=1, keepdims=True)  # grad(phi_0) . grad(phi_j)
    corner = jnp.sum(inverse, axis=(1, 2))[:, None, None]
    top = jnp.concatenate([corner, first], axis=2)
    return jnp.concatenate([top, jnp.concatenate([jnp.swapaxes(first, 1, 2), inverse], axis=2)], axis=1)


def apply_stiffness(op: HeatOperators, u: Float[Array, " N"]) -> Float[Array, " N"]:
    """K u: each simplex's stiffness times its vertex values, summed onto the vertices."""
    local = u.at[op.simplices].get(mode="fill", fill_value=0.0)
    return jax.ops.segment_sum(
        jnp.einsum("sab,sb->sa", op.stiffness, local).ravel(), op.simplices.ravel(), num_segments=op.n_points
    )


def stiffness_diagonal(op: HeatOperators) -> Float[Array, " N"]:
    local = jnp.diagonal(op.stiffness, axis1=1, axis2=2)
    return jax.ops.segment_sum(local.ravel(), op.simplices.ravel(), num_segments=op.n_points)


def unit_gradient_divergence(op: HeatOperators, u: Float[Array, " N"], u_far=None, trusted=None) -> Float[Array, " N"]:
    """Integrated divergence at every vertex of X = -grad u / |grad u| (X = 0 where grad u = 0).
    With `u_far` and `trusted` (N,), simplices without a vertex in `trusted` take the
    direction of grad u_far instead."""
    flux = _unit_gradient(op, u)
    if u_far is not None:
        trusted_simplex = jnp.any(trusted.at[op.simplices].get(mode="fill", fill_value=False), axis=1)
        flux = jnp.where(trusted_simplex[:, None], flux, _unit_gradient(op, u_far))
    per_vertex = op.volumes[:, None] * jnp.concatenate([-jnp.sum(flux, axis=1, keepdims=True), flux], axis=1)
    return jax.ops.segment_sum(per_vertex.ravel(), op.simplices.ravel(), num_segments=op.n_points)


def _unit_gradient(op: HeatOperators, u):
    """X . grad(phi_i), i = 1..d, of X = -grad u / |grad u| on every simplex: (S, d)."""
    local = u.at[op.simplices].get(mode="fill", fill_value=0.0)
    du = local[:, 1:] - local[:, :1]
    y = jnp.einsum("sij,sj->si", op.inverse_gram, du)  # coefficients of grad u in the dual basis
    norm = safe_sqrt(jnp.sum(du * y, axis=1))
    moving = (norm > 0)[:, None]
    return jnp.where(moving, -y / jnp.where(moving, norm[:, None], 1.0), 0.0)


class LinearSystem(eqx.Module):
    """A = diag(diag) + scale K on the walkers in `keep`, the identity on the others
    (Dirichlet rows): A = P (diag + scale K) P + (I - P), symmetric positive (semi)definite."""

    op: HeatOperators
    diag: Float[Array, " N"]
    scale: Float[Array, ""]
    keep: Bool[Array, " N"]

    def matvec(self, u):
        inner = jnp.where(self.keep, u, 0.0)
        return jnp.where(self.keep, self.diag * inner + self.scale * apply_stiffness(self.op, inner), u)

    @classmethod
    def build(cls, op: HeatOperators, diag, scale, keep) -> LinearSystem:
        """Walkers without a positive diagonal (in no valid simplex) become identity rows, so
        the system stays invertible; their distances are reported as NaN."""
        scale = jnp.asarray(scale, op.stiffness.dtype)
        return cls(op, diag, scale, keep & (diag + scale * stiffness_diagonal(op) > 0))

    def diagonal(self):
        return jnp.where(self.keep, self.diag + self.scale * stiffness_diagonal(self.op), 1.0)


def operator_key(op: HeatOperators):
    """(20,) uint8 digest of the simplices and stiffness, computed on the host once per call, so
    that each solve hashes only its small per-walker arrays (diag, keep) to find its factors."""
    return jax.pure_callback(
        lambda *a: np.frombuffer(_fingerprint(*a), np.uint8).copy(),
        jax.ShapeDtypeStruct((20,), jnp.uint8),
        op.simplices,
        jax.lax.stop_gradient(op.stiffness),
        vmap_method="sequential",
    )


def solve_direct(system: LinearSystem, b, key):
    """A^-1 b by a host factorisation (CHOLMOD through cholespy, else SuperLU), cached by the
    operator's contents (`key` from `operator_key`, and the system's diag, scale, keep); derivatives by implicit
    differentiation with the matvec in JAX."""
    arrays = (key, system.diag, system.scale, system.keep, system.op.simplices, system.op.stiffness)

    def solve(_, rhs):
        return jax.pure_callback(
            _host_solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), *arrays, rhs, vmap_method="expand_dims"
        )

    return jax.lax.custom_linear_solve(system.matvec, b, solve, symmetric=True)


def solve_cg(system: LinearSystem, b, *, rtol: float, max_steps: int):
    """A^-1 b by Jacobi-preconditioned conjugate gradients, stopped at |r|_2 <= rtol |b|_2;
    NaN where that is not reached in `max_steps`. Derivatives by implicit differentiation
    (`lax.custom_linear_solve`: the adjoint is one more CG solve)."""
    diag = system.diagonal()
    inverse_diag = jnp.where(diag > 0, 1.0 / jnp.where(diag > 0, diag, 1.0), 1.0)
    return jax.lax.custom_linear_solve(
        system.matvec, b, lambda mv, rhs: _pcg(mv, rhs, inverse_diag, rtol, max_steps), symmetric=True
    )


def _pcg(matvec, b, inverse_diag, rtol: float, max_steps: int):
    tol_sq = (rtol * rtol) * jnp.sum(b * b)

    def body(state):
        x, r, p, rz, step = state
        ap = matvec(p)
        pap = jnp.sum(p * ap)
        alpha = jnp.where(pap > 0, rz / jnp.where(pap > 0, pap, 1.0), 0.0)
        x, r = x + alpha * p, r - alpha * ap
        z = inverse_diag * r
        rz_new = jnp.sum(r * z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return x, r, z + beta * p, rz_new, step + 1

    def running(state):
        _, r, _, rz, step = state
        return (jnp.sum(r * r) > tol_sq) & (rz > 0) & (step < max_steps)

    z = inverse_diag * b
    x, r, _, _, _ = jax.lax.while_loop(running, body, (jnp.zeros_like(b), b, z, jnp.sum(b * z), 0))
    return jnp.where(jnp.sum(r * r) <= tol_sq, x, jnp.nan)


_FACTORS: collections.OrderedDict = collections.OrderedDict()
atexit.register(_FACTORS.clear)  # free the factorisations before nanobind's leak check at exit
DIRECT_BACKEND = "superlu" if cholespy is None else "cholmod"
FACTOR_CACHE_SIZE = 8


def _fingerprint(*arrays) -> bytes:
    digest = hashlib.blake2b(digest_size=20)
    for a in arrays:
        digest.update(repr((a.shape, a.dtype.str)).encode())
        digest.update(np.ascontiguousarray(a).data)
    return digest.digest()


def _host_solve(key, diag, scale, keep, simplices, stiffness, rhs):
    """Host side of `solve_direct`. Under vmap (expand_dims) every argument has leading batch
    axes, of size 1 where it is not batched: one factorisation per distinct operator."""
    operator = (key, diag, scale, keep, simplices, stiffness)
    lead = rhs.shape[:-1]
    n = rhs.shape[-1]
    ops = [np.broadcast_to(a, lead + a.shape[len(lead) :]).reshape((-1,) + a.shape[len(lead) :]) for a in operator]
    flat_rhs = np.asarray(rhs, np.float64).reshape(-1, n)
    out = np.empty_like(flat_rhs)
    if all(a.shape[: len(lead)] == (1,) * len(lead) for a in operator):  # one operator: a multi-column solve
        out[:] = _factor(*(a[0] for a in ops)).solve(flat_rhs.T).T
    else:
        for k in range(flat_rhs.shape[0]):
            out[k] = _factor(*(a[k] for a in ops)).solve(flat_rhs[k])
    return out.reshape(rhs.shape).astype(rhs.dtype)


def _factor(key, diag, scale, keep, simplices, stiffness):
    full_key = bytes(key) + _fingerprint(diag, scale, keep)
    if full_key in _FACTORS:
        _FACTORS.move_to_end(full_key)
        return _FACTORS[full_key]
    factor = new_factor(_assemble(simplices, stiffness, diag, scale, keep))
    _FACTORS[full_key] = factor
    while len(_FACTORS) > FACTOR_CACHE_SIZE:
        _FACTORS.popitem(last=False)
    return factor


def new_factor(matrix, backend: str = DIRECT_BACKEND):
    """A factorisation with `.solve(rhs)`: CHOLMOD's supernodal Cholesky (cholespy), whose
    multi-column solves are ~2.7x faster than SuperLU's at N = 1e5 (bench/README.md), or
    SuperLU where cholespy is missing or the matrix is not numerically positive definite."""
    if backend == "cholmod":
        try:
            return _Cholesky(matrix)
        except (RuntimeError, ValueError):
            pass
    try:
        return scipy.sparse.linalg.splu(
            matrix.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
        )
    except RuntimeError:  # a zero pivot without pivoting: an indefinite matrix, LU with partial pivoting
        pass
    try:
        return scipy.sparse.linalg.splu(matrix.tocsc())
    except RuntimeError:  # exactly singular: NaN distances, said by geodesic_distances
        return _Singular()


class _Singular:
    def solve(self, rhs):
        return np.full(np.shape(rhs), np.nan)


class _Cholesky:
    def __init__(self, matrix):
        coo = matrix.tocoo()
        self.solver = cholespy.CholeskySolverD(
            coo.shape[0],
            coo.row.astype(np.int32),
            coo.col.astype(np.int32),
            coo.data.astype(np.float64),
            cholespy.MatrixType.COO,
        )

    def solve(self, rhs):
        rhs = np.array(rhs, dtype=np.float64, order="C")  # a writable copy: cholespy rejects read-only input
        out = np.zeros_like(rhs)
        self.solver.solve(rhs, out)
        return out


def _assemble(simplices, stiffness, diag, scale, keep):
    """The sparse matrix of a `LinearSystem` (full, symmetric)."""
    n, d1 = diag.shape[0], simplices.shape[1]
    real = simplices[:, 0] < n
    s, k = np.asarray(simplices)[real], np.asarray(stiffness, np.float64)[real]
    rows, cols = np.repeat(s, d1, axis=1).ravel(), np.tile(s, (1, d1)).ravel()
    matrix = scipy.sparse.csr_matrix((float(scale) * k.ravel(), (rows, cols)), shape=(n, n))
    matrix = matrix + scipy.sparse.diags(np.asarray(diag, np.float64))
    keep = np.asarray(keep, bool)
    p = scipy.sparse.diags(keep.astype(np.float64))
    return (p @ matrix @ p + scipy.sparse.diags((~keep).astype(np.float64))).tocsr()


def heat_distances(
    tess: Tessellation, op: HeatOperators, sources: Int[Array, " M"], *, boundary: str = "mean", solver: str = "direct"
) -> Float[Array, "M N"]:
    """Heat-method distances from each source to every walker (see `jaxgeom.geodesic_distances`)
    with the operators `op` of `heat_operators`."""
    n, dtype = op.n_points, op.stiffness.dtype
    everyone = jnp.ones(n, bool)
    inside = everyone if tess.periodic else ~tess.hull
    boundary = "neumann" if tess.periodic else boundary  # a torus has no boundary
    # pinning one walker per connected component (adding c e_r e_r^T) makes K invertible; with
    # sum(b) = 0 on a component the pinned solution solves K phi = b there exactly, phi_r = 0
    k_diag = stiffness_diagonal(op)
    component = component_labels(op)
    root = component == jnp.arange(n, dtype=component.dtype)
    pin = jnp.where(root, jnp.where(k_diag > 0, k_diag, 1.0), 0.0)
    poisson = LinearSystem.build(op, pin, 1.0, everyone)
    solve = _solver(solver, op, tess.dim)
    heat = _heat_step(op, solve, boundary, inside, everyone, op.t)
    # CG meets a normwise tolerance: where u (~ exp(-r / sqrt t)) falls below it, its direction
    # is noise. There a second heat step with t' = N^(1/d) h^2 (sqrt(t') = sqrt(h L)) gives it.
    far_t = op.t * n ** (0.5 / tess.dim)
    far = _heat_step(op, solve, boundary, inside, everyone, far_t) if solver == "cg" else None
    floor = CG_TRUST[jnp.finfo(dtype).bits == 64]

    def one(source):
        delta = (jnp.arange(n, dtype=jnp.int32) == source).astype(dtype)
        u = heat(delta)
        if far is None:
            b = unit_gradient_divergence(op, u)
        else:
            b = unit_gradient_divergence(op, u, far(delta), jnp.abs(u) > floor * jnp.max(u))
        phi = solve(poisson, b, "poisson")
        distance = phi - phi.at[source].get(mode="fill", fill_value=jnp.nan)
        reached = component == component.at[source].get(mode="fill", fill_value=-1)
        return jnp.where(reached & poisson.keep & (op.mass > 0), distance, jnp.nan)

    return jax.lax.map(one, sources, batch_size=min(SOURCE_BATCH, sources.shape[0]))


def component_labels(op: HeatOperators) -> Int[Array, " N"]:
    """The smallest walker id of each walker's connected component in the graph of nonzero
    stiffness entries. Only meshes with simplices that did not close (whose clamped weights
    can cut walkers off) are searched; a mesh of closing simplices is one component
    (Delaunay meshes are connected), labelled 0."""
    n, d1 = op.n_points, op.simplices.shape[1]
    linked = (op.stiffness != 0) & ~jnp.eye(d1, dtype=bool)

    def sweep(state):
        labels, _ = state
        local = labels.at[op.simplices].get(mode="fill", fill_value=n)
        reach = jnp.min(jnp.where(linked, local[:, None, :], n), axis=2)
        new = jnp.minimum(labels, jax.ops.segment_min(reach.ravel(), op.simplices.ravel(), num_segments=n))
        new = jnp.minimum(new, new[new])  # pointer jumping: a label's own label is smaller or equal
        return new, jnp.any(new != labels)

    labels = jnp.arange(n, dtype=jnp.int32)
    search = jnp.any(~op.closes)
    labels, _ = jax.lax.while_loop(lambda s: s[1], sweep, (labels, search))
    return jnp.where(search, labels, 0)


def _heat_step(op: HeatOperators, solve, boundary: str, inside, everyone, t):
    """delta -> u: (M + t K) u = delta with the boundary rule of `boundary`."""
    neumann = LinearSystem.build(op, op.mass, t, everyone)
    dirichlet = LinearSystem.build(op, op.mass, t, inside)

    def step(delta):
        if boundary == "neumann":
            return solve(neumann, delta, "heat")
        if boundary == "dirichlet":
            return solve(dirichlet, jnp.where(inside, delta, 0.0), "heat")
        return 0.5 * (solve(neumann, delta, "heat") + solve(dirichlet, jnp.where(inside, delta, 0.0), "heat"))

    return step


def _solver(name: str, op: HeatOperators, d: int):
    """solve(system, b, kind): "direct", or CG to a tolerance per dtype and step (the heat step is
    well conditioned, cond ~ t / h^2, and is solved tighter: its far field is exponentially small)."""
    if name == "direct":
        key = operator_key(op)
        return lambda system, b, kind: solve_direct(system, b, key)
    double = jnp.finfo(op.stiffness.dtype).bits == 64
    rtol = {("heat", True): 1e-12, ("poisson", True): 1e-10, ("heat", False): 1e-5, ("poisson", False): 1e-4}
    max_steps = int(100 * op.n_points ** (1.0 / d)) + 100  # CG needs ~ sqrt(cond K) ~ N^(1/d) steps
    return lambda system, b, kind: solve_cg(system, b, rtol=rtol[(kind, double)], max_steps=max_steps)
