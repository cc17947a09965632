"""Normalized graph Laplacian L = I - D^-1/2 W D^-1/2 of the neighbour graph and its spectral gap."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
from jaxtyping import Array, Float, Int

from ..base._checks import check_choice, check_integer, check_positive, refuse_unused, warn_at_caller
from ..tessellation._graph import Tessellation, padded_to_csr, take_or_zero, takes_tessellation
from ..tessellation._triangulators import morton_codes
from ._weights import (
    check_weights,
    kernel_arguments,
    weights_on_graph,
)

LAPLACIAN_WEIGHTS = ("kernel", "uniform")
SPECTRAL_METHODS = ("scipy", "lobpcg")
LOBPCG_RTOL = 1e-2
# Edges lighter than this fraction of the heaviest count as absent when the graph is split
# into connected components (kernel weights of stragglers underflow to 0 in float32). At
# 1e-12 clusters joined by such edges formed one "component" whose gap (~1e-15) was below
# float64 rounding; kernel weights fall below 1e-8 at 6.1 length scales.
COMPONENT_RTOL = 1e-8


def gap_rounding_level(n_walkers: int) -> float:
    """The largest spectral gap indistinguishable from 0 in float64 for a normalized Laplacian
    of `n_walkers` walkers (||L|| <= 2): 2 n eps. Gaps below it are reported as rounding."""
    return 2.0 * max(int(n_walkers), 1) * float(np.finfo(np.float64).eps)


class GraphLaplacian(eqx.Module):
    """Normalized Laplacian L = I - D^-1/2 W D^-1/2 over the padded neighbour lists.

    W holds one weight per neighbour slot. Delaunay graphs are symmetric; k-NN
    graphs are not, and use W_sym = (W + W^T) / 2. Walkers with zero degree get
    L_ii = 0 (Chung's convention: each isolated walker is its own component).

    **Fields:** `neighbors` (N, K), `weights` (N, K) (0 on padding),
    `inv_sqrt_degree` (N,) (0 where isolated), static `symmetric`.
    """

    neighbors: Int[Array, "N K"]
    weights: Float[Array, "N K"]
    inv_sqrt_degree: Float[Array, " N"]
    symmetric: bool = eqx.field(static=True)

    @property
    def n(self) -> int:
        return self.neighbors.shape[0]

    def adjacency_matvec(self, x):
        """W_sym @ x for x of shape (N,) or (N, m)."""
        w = self.weights.reshape(self.weights.shape + (1,) * (x.ndim - 1))
        out = jnp.sum(w * take_or_zero(x, self.neighbors), axis=1)
        if self.symmetric:
            return out
        pushed = (w * x[:, None]).reshape((-1,) + x.shape[1:])
        transpose = jax.ops.segment_sum(pushed, self.neighbors.ravel(), num_segments=self.n)
        return 0.5 * (out + transpose)

    def matvec(self, x):
        """L @ x for x of shape (N,) or (N, m); jittable."""
        s = self.inv_sqrt_degree.reshape((-1,) + (1,) * (x.ndim - 1))
        return jnp.where(s > 0, x - s * self.adjacency_matvec(s * x), 0.0)

    def to_scipy(self) -> scipy.sparse.csr_matrix:
        """The same operator as a scipy CSR matrix (host)."""
        adj = padded_to_csr(self.neighbors, self.weights, self.n)
        if not self.symmetric:
            adj = 0.5 * (adj + adj.T)
        s = scipy.sparse.diags(np.asarray(self.inv_sqrt_degree, dtype=np.float64))
        active = scipy.sparse.diags((np.asarray(self.inv_sqrt_degree) > 0).astype(np.float64))
        return (active - s @ adj @ s).tocsr()


@takes_tessellation
@eqx.filter_jit
def graph_laplacian(
    tess: Tessellation, *, length_scale=None, weights: str = "kernel", alpha: float | None = None
) -> GraphLaplacian:
    """The normalized graph Laplacian L = I - D^-1/2 W D^-1/2 on the neighbour graph.

    **Arguments:**

    - `tess`: Delaunay or k-NN [`jaxgeom.Tessellation`][].
    - `length_scale`: kernel width l of w_ij = exp(-|x_j - x_i|^2 / (2 l^2)).
      `None` uses the chapter's adaptive rule l = alpha * mean nearest-neighbour distance.
    - `weights`: "kernel" or "uniform" (w_ij = 1).
    - `alpha`: factor of the adaptive rule (None: 3). `length_scale` and `alpha` act on
      "kernel" only, and are refused with "uniform".

    **Returns:**

    A [`jaxgeom.GraphLaplacian`][] with a jittable `matvec` and `to_scipy()`.
    """
    check_weights(weights, "weights", LAPLACIAN_WEIGHTS)
    alpha = kernel_arguments(weights, length_scale, alpha)
    w = weights_on_graph(tess, weights, length_scale=length_scale, alpha=alpha, shift="global")
    symmetric = tess.simplices is not None
    degree = jnp.sum(w, axis=1)
    if not symmetric:
        degree = 0.5 * (degree + jax.ops.segment_sum(w.ravel(), tess.neighbors.ravel(), num_segments=tess.n_points))
    inv_sqrt = jnp.where(degree > 0, 1.0 / jnp.sqrt(jnp.where(degree > 0, degree, 1.0)), 0.0)
    return GraphLaplacian(tess.neighbors, w, inv_sqrt, symmetric)


@takes_tessellation
def spectral_gap(
    tess: Tessellation,
    *,
    k: int = 6,
    length_scale=None,
    weights: str = "kernel",
    alpha: float | None = None,
    method: str = "scipy",
    tol=None,
    maxiter: int | None = None,
    seed: int | None = None,
) -> Float[Array, " k"]:
    """The k smallest eigenvalues of the normalized Laplacian, ascending.

    lambda_0 = 0 (the constant mode D^1/2 1) and lambda_1 is the spectral gap.

    **Arguments:**

    - `tess`, `length_scale`, `weights`, `alpha`: as in [`jaxgeom.graph_laplacian`][].
    - `k`: number of eigenvalues, 1 <= k < N.
    - `method`: "scipy" runs `scipy.sparse.linalg.eigsh` in shift-invert mode on the
      host (relative error ~1e-12, float64). "lobpcg" is jittable: LOBPCG
      (`jax.experimental.sparse.linalg.lobpcg_standard`) on 2I - L with the constant
      mode deflated, for at most `maxiter` iterations. Its residuals are checked
      afterwards: an eigenvalue whose residual |L u - lambda u| exceeds `tol` is
      returned as NaN, never as a silent wrong number; so is one whose residual exceeds
      1% of its value (an eigenvalue lies within the residual of it).
    - `tol`, `maxiter` (None: 2000), `seed` (None: 0): of "lobpcg" only, refused with "scipy".
    - `tol`: LOBPCG residual tolerance; default 1e-8 in float64 and 1e-3 in float32.
      Measured at N = 1e4 in 2D (lambda_1 ~ 2.6e-4): float64 agrees with scipy to
      3e-11 relative; float32 reaches only ~3e-3 relative on lambda_1 (2.5e-3 with
      tol=1e-4), the limit of single precision for eigenvalues this small.
    - `seed`: PRNG seed of the LOBPCG start block.

    **Returns:**

    (k,) eigenvalues, ascending; NaN where LOBPCG did not converge. With "scipy", a
    `UserWarning` says when kernel weights underflowed to 0 (length_scale far below the
    spacing): the graph has then fallen apart and its small eigenvalues are 0.
    """
    check_choice(method, "method", SPECTRAL_METHODS)
    if method == "scipy":
        refuse_unused(
            {"tol": tol, "maxiter": maxiter, "seed": seed},
            of="method='lobpcg'",
            chosen="method='scipy'",
            why=" (shift-invert eigsh)",
        )
    maxiter, seed = (2000 if maxiter is None else maxiter), (0 if seed is None else seed)
    check_positive(tol, "tol", " (LOBPCG's residual tolerance; None: 1e-8 in float64, 1e-3 in float32)")
    check_integer(maxiter, "maxiter", 1)
    check_integer(seed, "seed")
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or not 1 <= k < tess.n_points:
        raise ValueError(f"`k` must be an int with 1 <= k < N = {tess.n_points}; got {k!r}.")
    if method == "lobpcg" and 5 * (k - 1) >= tess.n_points:  # LOBPCG's search block: 5 (k - 1) < N
        raise ValueError(
            f"method='lobpcg' needs 5 (k - 1) < N = {tess.n_points}; got k={k}. "
            f"Use k <= {(tess.n_points - 1) // 5 + 1} or method='scipy'."
        )
    lap = graph_laplacian(tess, length_scale=length_scale, weights=weights, alpha=alpha)
    if method == "scipy":
        warn_if_underflowed(lap, tess)
        matrix = lap.to_scipy()
        order = nested_dissection_order(np.asarray(tess.points, dtype=np.float64), matrix)
        return jnp.asarray(_scipy_smallest(matrix[order][:, order], int(k)), dtype=tess.points.dtype)
    if tol is None:
        tol = 1e-8 if tess.points.dtype == jnp.float64 else 1e-3
    return _lobpcg_smallest(lap, int(k), tol, maxiter, seed)


def warn_if_underflowed(lap: GraphLaplacian, tess: Tessellation) -> None:
    """Kernel weights that underflow to 0 cut the graph: its small eigenvalues are then 0 by
    construction (the symmetric kernel graph's true limit as l -> 0), which is worth saying."""
    cut = int(np.sum((np.asarray(lap.weights) == 0) & np.asarray(tess.neighbor_mask)))
    if cut:
        warn_at_caller(
            f"{cut} edge(s) of the kernel graph have weight 0 (underflow: length_scale is far below "
            "the walker spacing), so the graph falls apart and its smallest eigenvalues are 0 by "
            "construction. Use a larger length_scale, or None for the adaptive rule."
        )


@takes_tessellation
def bulk_spectral_gap(
    tess: Tessellation, *, length_scale=None, weights: str = "kernel", alpha: float | None = None
) -> tuple[float, int, int]:
    """(gap, n_components, n_outside): the spectral gap of the largest connected component
    of the weighted graph, the number of components, and the walkers outside the largest.

    Edges lighter than `COMPONENT_RTOL` x the heaviest are absent, both for the component
    test and in the component's Laplacian: a few stragglers far from a clustered swarm
    (kernel weights exp(-134), 0 in float32) split the graph, and its gap is then 0 (or
    ~1e-58) although the bulk mixes at a definite rate. Host, scipy; the gap is NaN when
    the largest component has fewer than 3 walkers. A gap below `gap_rounding_level` of the
    component's size is rounding (a bottleneck lighter than float64 resolves).
    """
    lap = graph_laplacian(tess, length_scale=length_scale, weights=weights, alpha=alpha)
    w = np.asarray(lap.weights, np.float64)
    keep = w > COMPONENT_RTOL * w.max() if w.size and w.max() > 0 else np.zeros_like(w, bool)
    adjacency = padded_to_csr(lap.neighbors, np.where(keep, w, 0.0), lap.n)
    adjacency.eliminate_zeros()
    n_comp, labels = scipy.sparse.csgraph.connected_components(adjacency, directed=False)
    largest = np.flatnonzero(labels == np.argmax(np.bincount(labels)))
    if len(largest) < 3:
        return float("nan"), int(n_comp), int(lap.n - len(largest))
    sub = adjacency[largest][:, largest]
    sub = 0.5 * (sub + sub.T) if not lap.symmetric else sub
    inv_sqrt = scipy.sparse.diags(1.0 / np.sqrt(np.asarray(sub.sum(axis=1)).ravel()))
    matrix = (scipy.sparse.identity(len(largest)) - inv_sqrt @ sub @ inv_sqrt).tocsr()
    order = nested_dissection_order(np.asarray(tess.points, np.float64)[largest], matrix)
    gap = _scipy_smallest(matrix[order][:, order], 2)[1]
    return float(gap), int(n_comp), int(lap.n - len(largest))


def _scipy_smallest(matrix, k: int) -> np.ndarray:
    """k smallest eigenvalues of a PSD sparse matrix with spectrum in [0, 2].

    Shift-invert Lanczos around sigma = -0.01 / N: L - sigma I is positive definite,
    and a shift far below the gap (lambda_1 ~ 1/N in 2D) keeps the wanted eigenvalues
    well separated after inversion (sigma = -0.01 took 5x more solves at N = 1e5).
    Callers pass the matrix in a fill-reducing (nested-dissection) order, so SuperLU
    factorises it as given, without pivoting (the matrix is positive definite):
    at N = 1e5 in 2D the factorisation takes 0.35 s (COLAMD on Morton-sorted input:
    0.59 s) and the whole call 1.0 s instead of 1.35 s.
    """
    n = matrix.shape[0]
    if n <= 200 or k >= n - 1:
        return np.linalg.eigvalsh(matrix.toarray())[:k]
    sigma = -0.01 / n
    lu = scipy.sparse.linalg.splu(
        (matrix - sigma * scipy.sparse.identity(n)).tocsc(),
        permc_spec="NATURAL",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    inverse = scipy.sparse.linalg.LinearOperator((n, n), matvec=lu.solve, matmat=lu.solve, dtype=np.float64)
    vals = scipy.sparse.linalg.eigsh(
        matrix,
        k=k,
        sigma=sigma,
        which="LM",
        OPinv=inverse,
        return_eigenvectors=False,
        v0=np.ones(n) / np.sqrt(n) + 1e-3 * np.arange(n) / n,
    )
    return np.sort(np.clip(vals, 0.0, None))


def nested_dissection_order(points: np.ndarray, matrix, leaf_size: int = 32) -> np.ndarray:
    """Fill-reducing permutation of a sparse graph on points: geometric nested dissection.

    The cells of the Morton quadtree (octree) are the dissection pieces: at level l
    every piece is halved by bit l of the Morton code, and the endpoints on the lower
    side of the edges that cross the cut become that piece's separator. Vertices are
    ordered by the post-order of their piece (children before their separator), then
    along the Morton curve. Levels stop at pieces of about `leaf_size` points.
    """
    code, n_bits = morton_codes(points)
    upper = scipy.sparse.triu(matrix, 1).tocoo()
    depth = min(n_bits, max(0, int(np.ceil(np.log2(max(len(points) / leaf_size, 1.0))))))
    level = _separator_levels(code, n_bits, depth, upper.row, upper.col)
    piece = (code >> (np.uint64(n_bits) - level.astype(np.uint64))).astype(np.int64)
    post_order = (piece + 1) * (2 ** (depth - level + 1) - 1) - 1
    return np.lexsort((code, post_order))


def _separator_levels(code, n_bits: int, depth: int, i, j) -> np.ndarray:
    """Dissection level of each vertex: the level whose separator holds it, else `depth`."""
    level = np.full(len(code), depth, np.int64)
    ci, cj = code[i], code[j]
    for lev in range(depth):
        bit = np.uint64(n_bits - 1 - lev)
        cut = ((ci >> bit) != (cj >> bit)) & ((ci >> (bit + np.uint64(1))) == (cj >> (bit + np.uint64(1))))
        lower_i = ((ci[cut] >> bit) & np.uint64(1)) == 0
        separator = np.where(lower_i, i[cut], j[cut])
        level[separator] = lev
        keep = (level[i] == depth) & (level[j] == depth)
        i, j, ci, cj = i[keep], j[keep], ci[keep], cj[keep]
    return level


@eqx.filter_jit
def _lobpcg_smallest(lap: GraphLaplacian, k: int, tol, maxiter: int, seed: int):
    from jax.experimental.sparse.linalg import lobpcg_standard

    sqrt_deg = jnp.where(
        lap.inv_sqrt_degree > 0, 1.0 / jnp.where(lap.inv_sqrt_degree > 0, lap.inv_sqrt_degree, 1.0), 0.0
    )
    u = sqrt_deg / jnp.linalg.norm(sqrt_deg)  # the exact null vector of L

    def shifted(x):  # 2 I - L with u deflated: eigenvalues 2 - lambda_1, 2 - lambda_2, ...
        return 2.0 * x - lap.matvec(x) - 2.0 * jnp.outer(u, u @ x)

    if k == 1:
        return jnp.zeros((1,), u.dtype)
    x0 = jax.random.normal(jax.random.PRNGKey(seed), (lap.n, k - 1), u.dtype)
    # lobpcg_standard stops when |A v - theta v| < tol' 10 n (theta + |A v|), with |A v| <= 2:
    # tol' = tol / (40 n) makes that the absolute residual `tol` checked below.
    theta, vecs, _ = lobpcg_standard(shifted, x0, m=maxiter, tol=tol / (40.0 * lap.n))
    lam = 2.0 - theta
    residual = jnp.linalg.norm(lap.matvec(vecs) - vecs * lam, axis=0)
    # An eigenvalue lies within the residual of lam (Bauer-Fike): demand 1% relative accuracy
    # too, so that small eigenvalues in float32 are NaN rather than silently wrong.
    lam = jnp.where((residual <= 10.0 * tol) & (residual <= LOBPCG_RTOL * lam), lam, jnp.nan)
    return jnp.concatenate([jnp.zeros((1,), lam.dtype), jnp.sort(lam)])
