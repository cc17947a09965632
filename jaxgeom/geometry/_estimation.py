"""Gradient and Hessian of a fitness field estimated from its values at the walkers.

Every estimate is a per-walker least-squares fit over a padded stencil (the 1-ring
neighbours, or the 2-ring where the 1-ring is too small), vmapped over walkers.
Walkers whose stencil cannot support the fit get NaN and are counted; a NaN value
at one walker only removes that walker from its neighbours' stencils.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..base._checks import check_choice, check_nonnegative
from ..base._simplex import HIGHEST, WRITTEN_OUT_MAX_DIM, safe_sqrt
from ..tessellation._graph import (
    Tessellation,
    neighbor_displacements,
    neighbor_displacements_for_sums,
    take_or_zero,
    takes_tessellation,
)
from ._metric import emergent_metric
from ._weights import EDGE_WEIGHTS, check_weights

GRADIENT_METHODS = ("wls", "fd")
WEIGHTINGS = ("uniform", "inverse_distance", "gaussian")
HESSIAN_KINDS = ("full", "diagonal")
# Fraction of walkers (static capacity) that may fall back to a 2-ring stencil, by d.
# Measured on random Delaunay graphs: about 15% need it in 2D, 2% in 3D.
TWO_RING_FRACTION = {2: 0.2, 3: 0.0625}
# Columns of each neighbour row used for the 2-ring (rows keep padding last, so these are
# the first real neighbours): a subset of the 2-ring, still exact for quadratics, 2.5x (2D)
# to 6x (3D) fewer points than all K + K^2 slots.
# Beyond 3D the 2-ring is a fallback only (analyze's k covers the fit): 4 columns keep its
# normal equations (~d^4/8 entries over K + 4K points) in memory at d = 10.
TWO_RING_WIDTH = {2: 8, 3: 16}
TWO_RING_WIDTH_HIGH_D = 4
# Relative conditioning (smallest squared Cholesky pivot over the mean diagonal) below
# which a fit is degenerate, and below which a 1-ring quadratic fit moves to the 2-ring.
RCOND = 1e-10
RCOND_TWO_RING = 1e-4
# Chapter's step-size rule h = alpha * median neighbour distance, alpha = 0.5 for the
# diagonal Hessian: the smallest admissible step along an axis.
DIAGONAL_STEP_ALPHA = 0.5


class EstimateInfo(NamedTuple):
    """Diagnostics of an estimate: which walkers got a value, and why others did not.

    Every estimator returns it as the second element of `(estimate, info)` with
    `with_info=True`.

    **Fields:** `valid` (N,) bool; `n_invalid` () int; `two_ring` (N,) bool (stencil
    was the 2-ring); `n_over_capacity` () int (walkers that needed the 2-ring beyond
    its static capacity, left NaN); `axis_quality` (N, d) in [0, 1] for
    `estimate_hessian(kind="diagonal")` (the smaller cosine of the two neighbours used
    along each axis), else None.
    """

    valid: Bool[Array, " N"]
    n_invalid: Int[Array, ""]
    two_ring: Bool[Array, " N"]
    n_over_capacity: Int[Array, ""]
    axis_quality: Float[Array, "N d"] | None = None


def _value_differences(tess: Tessellation, values):
    """Per walker: neighbour value differences (N, K) (0 where unusable) and the usable mask
    (real neighbour with a finite value difference)."""
    dv = padded_values(values)[tess.neighbors] - values[:, None]
    usable = tess.neighbor_mask & jnp.isfinite(dv)
    return jnp.where(usable, dv, 0.0), usable


def padded_values(values):
    """Values with a 0 appended for the sentinel index N (callers mask padding slots)."""
    return jnp.concatenate([values, jnp.zeros((1,), values.dtype)])


def _weights_of_rows(sq, usable, weighting: str):
    return EDGE_WEIGHTS[weighting].fn(jnp.where(usable, sq, 0.0), usable, relative_eps=0.0)


def _weights(dx, usable, weighting: str):
    return EDGE_WEIGHTS[weighting].fn(jnp.sum(dx * dx, axis=-1), usable, relative_eps=0.0)


def _solve_normal(a, b, rcond: float = RCOND):
    """Solve the SPD normal equations a x = b: (x, ok), x = 0 where a is (numerically) singular.
    Callers turn those rows into NaN after every product: a NaN here would meet their
    scale factors, and the gradient of a masked-out NaN product is NaN."""
    scale = jax.lax.stop_gradient(jnp.trace(a) / a.shape[0])
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    ok = jnp.isfinite(scale) & (scale > 0)
    # Which systems are solvable is decided without a gradient; the factorisation that is
    # differentiated then sees only those (a failed Cholesky is NaN, and so is its derivative).
    diag = jnp.diagonal(jnp.linalg.cholesky(jax.lax.stop_gradient(jnp.where(ok, a, eye))))
    ok = ok & jnp.all(jnp.isfinite(diag)) & (jnp.min(diag) ** 2 > rcond * jnp.where(ok, scale, 1.0))
    chol = jnp.linalg.cholesky(jnp.where(ok, a, eye))
    x = jax.scipy.linalg.cho_solve((chol, True), jnp.where(ok, b, 0.0))
    return jnp.where(ok, x, 0.0), ok


@takes_tessellation
@eqx.filter_jit
def estimate_gradient(
    tess: Tessellation,
    values,
    *,
    method: str = "wls",
    weights: str = "uniform",
    order: int | None = None,
    with_info: bool = False,
):
    """Gradient of a field sampled at the walkers.

    **Arguments:**

    - `tess`: Delaunay or k-NN graph (any d).
    - `values`: (N,) field values V(x_i); NaN entries are left out of every stencil.
    - `method`: "wls" (default) fits a local polynomial by least squares and returns
      its linear coefficients. `order=2` (default) fits the quadratic model of
      [`jaxgeom.estimate_hessian`][] (with its 2-ring fallback), exact for quadratic V;
      `order=1` fits V_j - V_i = g . (x_j - x_i) over the 1-ring with `weights`,
      exact for linear V and cheaper. "fd" is the chapter's
      one-sided formula sum_j w_ij (V_j - V_i)(x_j - x_i) / |x_j - x_i|^2 with
      weights normalised to sum 1; it is not exact even for linear V.
    - `weights`: how much each stencil point's equation counts in the least squares of
      "wls" (both orders) and in the sum of "fd": "uniform", "inverse_distance" (1/|dx|) or
      "gaussian" (exp(-|dx|^2 / 2 s^2), s = the walker's median neighbour distance). A
      quadratic V is fitted exactly by `order=2` with any of them.
    - `with_info`: return `(estimate, info)`, info an [`jaxgeom.EstimateInfo`][].

    **Returns:**

    (N, d) gradients. Walkers whose stencil cannot determine the fit (order 1: fewer
    than d usable neighbours, i.e. d + 1 points with the walker itself; order 2: no
    well-conditioned fit on the 1-ring or 2-ring) are NaN and counted.
    On a k-NN graph the remedy is a larger k.
    """
    check_choice(method, "method", GRADIENT_METHODS)
    check_weights(weights, "weights", WEIGHTINGS)
    if order is not None and method == "fd":
        raise ValueError("`order` chooses the polynomial of method='wls'; method='fd' has none. Leave order None.")
    order = 2 if order is None else order
    if order not in (1, 2):
        raise ValueError(f"`order` must be 1 (linear fit) or 2 (quadratic fit); got {order!r}.")
    values = jnp.asarray(values, tess.points.dtype)
    if method == "wls" and order == 2:
        _, grad, info = _local_quadratic(tess, values, weights)
        return (grad, info) if with_info else grad
    dx = neighbor_displacements(tess)
    dv, usable = _value_differences(tess, values)
    w = _weights(dx, usable, weights)
    if method == "fd":
        sq = jnp.where(usable, jnp.sum(dx * dx, axis=-1), 1.0)
        w = w / jnp.maximum(jnp.sum(w, axis=1, keepdims=True), jnp.finfo(w.dtype).tiny)
        grad = jnp.sum((w * dv / sq)[..., None] * dx, axis=1)
        ok = jnp.sum(usable, axis=1) >= 1
    else:
        a = jnp.einsum("nk,nki,nkj->nij", w, dx, dx)
        b = jnp.einsum("nk,nki,nk->ni", w, dx, dv)
        grad, ok = jax.vmap(_solve_normal)(a, b)
        ok = ok & (jnp.sum(usable, axis=1) >= tess.dim)
    ok = ok & jnp.isfinite(values)
    grad = jnp.where(ok[:, None], grad, jnp.nan)
    return (grad, _info(ok, jnp.zeros_like(ok), 0)) if with_info else grad


def _info(ok, two_ring, over) -> EstimateInfo:
    return EstimateInfo(ok, jnp.sum(~ok).astype(jnp.int32), two_ring, jnp.asarray(over, jnp.int32))


def _quadratic_fit(dxs, dv, usable, rcond: float = RCOND, weighting: str = "uniform"):
    """Hessians and gradients of local quadratic fits for a batch of stencils, and whether
    each is well determined.

    **Arguments:** `dxs`: d arrays (M, P) of displacements up to d = WRITTEN_OUT_MAX_DIM,
    one (M, P, d) array above (`neighbor_displacements_for_sums`); `dv`: (M, P) value
    differences; `usable`: (M, P) mask. Fits V - V_i = g.u + sum_{a<=b} c_ab u_a u_b in
    the scaled displacement u = dx / s (s = mean stencil distance, for conditioning
    only: the fit is exact for quadratics at any scale). The normal equations are
    assembled entry by entry over the (M, P) arrays up to d = WRITTEN_OUT_MAX_DIM (XLA fuses
    each entry's product and sum; batched small matmuls are several times slower on CPU),
    as einsums above.
    """
    d = len(dxs) if isinstance(dxs, list) else dxs.shape[-1]
    if dv.shape[1] < (d + 1) * (d + 2) // 2 - 1:  # fewer stencil slots than coefficients: no fit is determined
        return (
            jnp.full((dv.shape[0], d, d), jnp.nan, dv.dtype),
            jnp.full((dv.shape[0], d), jnp.nan, dv.dtype),
            jnp.zeros(dv.shape[0], bool),
        )
    sq = sum(x * x for x in dxs) if isinstance(dxs, list) else jnp.sum(dxs * dxs, axis=-1)
    mask = usable.astype(dv.dtype)
    dist = safe_sqrt(sq)  # 0 on padding, with a finite gradient there
    scale = jnp.sum(dist * mask, axis=1) / jnp.maximum(jnp.sum(mask, axis=1), 1.0)
    scale = jnp.where(scale > 0, scale, 1.0)
    # weighted least squares: each equation times sqrt(w) (w = 1 for "uniform"; the weights
    # of a row only rescale its equations, so any positive weights keep quadratics exact)
    root_w = mask if weighting == "uniform" else safe_sqrt(_weights_of_rows(sq, usable, weighting)) * mask
    if d <= WRITTEN_OUT_MAX_DIM:
        u = [x / scale[:, None] for x in dxs]
        products = u + [u[a] * u[b] for a in range(d) for b in range(a, d)]
        feats = [f * root_w for f in products]
        dv = dv * root_w
        n_coef = len(feats)
        entries = {(p, q): jnp.sum(feats[p] * feats[q], axis=1) for p in range(n_coef) for q in range(p, n_coef)}
        pairs = [[entries[min(p, q), max(p, q)] for q in range(n_coef)] for p in range(n_coef)]
        a = jnp.stack([jnp.stack(row, -1) for row in pairs], -2)
        b = jnp.stack([jnp.sum(f * dv, axis=1) for f in feats], axis=-1)
    else:  # the same features as arrays: one op per feature or entry is d^2..d^4 ops to compile
        rows = dxs / scale[:, None, None]  # (M, P, d)
        first, second = np.triu_indices(d)  # the products u_a u_b, a <= b, row by row
        table = jnp.concatenate([rows, rows[..., first] * rows[..., second]], axis=-1) * root_w[..., None]
        dv = dv * root_w
        n_coef = table.shape[-1]  # (M, P, C)
        a = jnp.einsum("mpc,mpe->mce", table, table, precision=HIGHEST)
        b = jnp.einsum("mpc,mp->mc", table, dv, precision=HIGHEST)
    coef, ok = jax.vmap(lambda a_, b_: _solve_normal(a_, b_, rcond))(a, b)
    ok = ok & (jnp.sum(usable, axis=1) >= n_coef)
    grad = coef[:, :d] / scale[:, None]
    return (
        jnp.where(ok[:, None, None], _unpack_hessian(coef, scale, d), jnp.nan),
        jnp.where(ok[:, None], grad, jnp.nan),
        ok,
    )


def _unpack_hessian(coef, scale, d: int):
    """Hessian from the quadratic coefficients c (first d entries are the gradient)."""
    upper = np.zeros((d, d), np.int32)
    upper[np.triu_indices(d)] = d + np.arange(d * (d + 1) // 2)  # c_ab's place, a <= b, row by row
    h = coef[:, np.maximum(upper, upper.T)] * jnp.asarray(1.0 + np.eye(d), coef.dtype)
    return h / scale[:, None, None] ** 2


def _two_ring(tess: Tessellation, values, walkers):
    """2-ring stencils (displacements in `_quadratic_fit`'s layout, value differences, usable)
    of the given walkers.

    The 2-ring is the 1-ring plus the neighbours' neighbours (the first
    `TWO_RING_WIDTH[d]` of each row), without the walker itself; points reached along
    several paths appear several times (a weight).
    """
    n, k_cap = tess.neighbors.shape
    width = min(k_cap, TWO_RING_WIDTH.get(tess.dim, TWO_RING_WIDTH_HIGH_D))
    nbrs_pad = jnp.concatenate([tess.neighbors[:, :width], jnp.full((1, width), n, tess.neighbors.dtype)])
    first = nbrs_pad[walkers]  # (F, m)
    second = nbrs_pad[first].reshape(walkers.shape[0], -1)  # (F, m*m)
    ring = jnp.concatenate([first, second], axis=1)
    is_self = ring == walkers[:, None]
    high = tess.dim > WRITTEN_OUT_MAX_DIM  # one (F, P, d) array, else d (F, P) arrays
    dxs: Any
    if high:
        dxs = take_or_zero(tess.points, ring) - take_or_zero(tess.points, walkers)[:, None, :]
    else:
        dxs = [
            take_or_zero(tess.points[:, k], ring) - take_or_zero(tess.points[:, k], walkers)[:, None]
            for k in range(tess.dim)
        ]
    if tess.neighbor_shifts is not None:  # compose the stored image shifts along i -> j -> k
        shifts = jnp.concatenate([tess.neighbor_shifts[:, :width], jnp.zeros((1, width, tess.dim), jnp.int8)])
        shifts = shifts.astype(jnp.int32)
        s1 = shifts[walkers]  # (F, m, d)
        s2 = (shifts[first] + s1[:, :, None, :]).reshape(walkers.shape[0], -1, tess.dim)
        total = jnp.concatenate([s1, s2], axis=1)
        if high:
            dxs = dxs + total.astype(dxs.dtype) * jnp.asarray(tess.box_lengths)
        else:
            dxs = [x + total[..., k].astype(x.dtype) * jnp.asarray(tess.box_lengths)[k] for k, x in enumerate(dxs)]
        is_self = is_self & jnp.all(total == 0, axis=-1)  # another image of i is a real point
    ring = jnp.where(is_self, n, ring)
    vals = padded_values(values)
    dv = vals[ring] - vals[walkers][:, None]
    usable = (ring < n) & jnp.isfinite(dv)
    return dxs, jnp.where(usable, dv, 0.0), usable


@takes_tessellation
@eqx.filter_jit
def estimate_hessian(tess: Tessellation, values, *, kind: str = "full", with_info: bool = False):
    """Hessian of a field sampled at the walkers (local quadratic least squares).

    **Arguments:**

    - `tess`: Delaunay or k-NN graph (any d).
    - `values`: (N,) field values; NaN entries are left out of every stencil.
    - `kind`: "full" fits V_j - V_i = g.dx + dx^T H dx / 2 over the walker's 1-ring by
      least squares, in coordinates scaled by the median neighbour distance: exact
      for quadratic V. Walkers whose 1-ring has fewer than d(d+3)/2 usable
      neighbours, or whose 1-ring fit is poorly conditioned (relative pivot below
      `RCOND_TWO_RING`), use their 2-ring instead (at most `TWO_RING_FRACTION` of the
      walkers, a static capacity; walkers beyond it are NaN and counted in
      `n_over_capacity`). "diagonal" is the chapter's cheap proxy: (N, d) second
      derivatives along the axes from the neighbours best aligned with +e_a and -e_a
      (a three-point second difference with unequal steps, the off-axis linear part
      removed); `info.axis_quality` is the chapter's quality (N, d) in [0, 1], the
      smaller of the two cosines. It is biased: the off-axis curvature of the two
      neighbours stays in it (median error ~21% of the largest curvature on a quadratic
      with cross terms, 4000 uniform walkers, 2D and 3D), and an axis with no neighbour
      half a median spacing out on either side is NaN (an entry alone; ~33% of interior
      walkers have one in 2D, ~15% in 3D). Use "full" for values: it is exact on
      quadratics.
    - `with_info`: return `(estimate, info)`, info an [`jaxgeom.EstimateInfo`][].

    **Returns:**

    (N, d, d) Hessians (kind "full") or (N, d) diagonals; NaN where undetermined.
    On a k-NN graph with too few neighbours, the remedy is a larger k.
    """
    check_choice(kind, "kind", HESSIAN_KINDS)
    values = jnp.asarray(values, tess.points.dtype)
    if kind == "diagonal":
        diag, quality, ok = _diagonal_hessian(tess, values)
        return (diag, _info(ok, jnp.zeros_like(ok), 0)._replace(axis_quality=quality)) if with_info else diag
    hess, _, info = _local_quadratic(tess, values)
    return (hess, info) if with_info else hess


def _local_quadratic(tess: Tessellation, values, weighting: str = "uniform"):
    """Local quadratic fits on the 1-ring, refit on the 2-ring where the 1-ring is too
    small or poorly conditioned: (hessian (N, d, d), gradient (N, d), info); `weighting`
    weighs each stencil point's equation (weighted least squares)."""
    dv, usable = _value_differences(tess, values)
    hess, grad, ok = _quadratic_fit(neighbor_displacements_for_sums(tess), dv, usable, RCOND_TWO_RING, weighting)
    needs = ~ok & jnp.isfinite(values)
    capacity = max(1, math.ceil(TWO_RING_FRACTION.get(tess.dim, 0.0625) * tess.n_points))
    walkers = jnp.nonzero(needs, size=capacity, fill_value=tess.n_points)[0].astype(jnp.int32)
    dxs2, dv2, usable2 = _two_ring(tess, values, jnp.minimum(walkers, tess.n_points - 1))
    hess2, grad2, ok2 = _quadratic_fit(dxs2, dv2, usable2, weighting=weighting)
    ok2 = ok2 & (walkers < tess.n_points)
    hess = hess.at[walkers].set(hess2, mode="drop")
    grad = grad.at[walkers].set(grad2, mode="drop")
    ok = ok.at[walkers].set(ok2, mode="drop") & jnp.isfinite(values)
    two_ring = jnp.zeros_like(ok).at[walkers].set(walkers < tess.n_points, mode="drop")
    over = jnp.maximum(jnp.sum(needs) - capacity, 0)
    info = _info(ok, two_ring, over)
    return jnp.where(ok[:, None, None], hess, jnp.nan), jnp.where(ok[:, None], grad, jnp.nan), info


def _diagonal_hessian(tess: Tessellation, values):
    dx = neighbor_displacements(tess)
    dv, usable = _value_differences(tess, values)
    dist = jnp.where(usable, safe_sqrt(jnp.sum(dx * dx, axis=-1)), jnp.inf)
    # A neighbour is only roughly on the axis: remove the off-axis linear part of its
    # value difference with the WLS gradient, else g_perp . dx_perp / h^2 pollutes V''.
    grad = jnp.nan_to_num(estimate_gradient(tess, values, order=1))
    linear = jnp.einsum("nkd,nd->nkd", dx, grad)
    step = DIAGONAL_STEP_ALPHA * jnp.nanmedian(jnp.where(usable, dist, jnp.nan), axis=1, keepdims=True)
    diags, qualities = [], []
    for a in range(tess.dim):
        admissible = usable & (jnp.abs(dx[..., a]) >= step)
        cos = jnp.where(admissible, dx[..., a] / dist, -2.0)
        plus, minus = jnp.argmax(cos, axis=1), jnp.argmin(jnp.where(admissible, cos, 2.0), axis=1)
        take = lambda arr, idx: jnp.take_along_axis(arr, idx[:, None], axis=1)[:, 0]  # noqa: E731
        h_plus, h_minus = take(dx[..., a], plus), -take(dx[..., a], minus)
        off_axis = jnp.sum(linear, axis=-1) - linear[..., a]
        v_plus, v_minus = take(dv - off_axis, plus), take(dv - off_axis, minus)
        ok = (h_plus > 0) & (h_minus > 0)
        safe_p, safe_m = jnp.where(ok, h_plus, 1.0), jnp.where(ok, h_minus, 1.0)
        second = 2.0 * (v_plus / safe_p + v_minus / safe_m) / (safe_p + safe_m)
        diags.append(jnp.where(ok, second, jnp.nan))
        qualities.append(jnp.where(ok, jnp.clip(jnp.minimum(take(cos, plus), -take(cos, minus)), 0.0, 1.0), 0.0))
    diag, quality = jnp.stack(diags, axis=1), jnp.stack(qualities, axis=1)
    diag = jnp.where(jnp.isfinite(values)[:, None], diag, jnp.nan)  # an axis without neighbours: NaN alone
    return diag, quality, jnp.all(jnp.isfinite(diag), axis=1)


@takes_tessellation
def geometric_hessian(tess: Tessellation, eps_sigma, *, eps_reg: float = 1e-5) -> Float[Array, "N d d"]:
    """The validation Hessian H_geo = g_emergent - eps_Sigma I (chapter, Method 2).

    It assumes walkers sampled at equilibrium from a density whose neighbour
    covariance encodes g = H + eps_Sigma I; see `compare_estimation_methods`.
    """
    check_nonnegative(eps_sigma, "eps_sigma")
    g = emergent_metric(tess, eps_reg=eps_reg)
    return g - eps_sigma * jnp.eye(tess.dim, dtype=g.dtype)
