"""The scutoidal viscous force: a row-normalized graph Laplacian on velocities.

F_i = nu * sum_j w_ij / sum_k w_ik * (v_j - v_i) over the neighbours listed in
the Tessellation. Conservation: for a symmetric weight (every
weight rule on a Delaunay graph, without volume weighting) sum_i deg_i F_i = 0 and the
degree-weighted velocity variance never increases; for any non-negative
weights an explicit step with nu dt <= 1 makes each new velocity a convex
combination of old ones. The plain mean velocity is NOT conserved.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._checks import check_nonnegative
from ..tessellation._graph import Tessellation, takes_tessellation
from ._metric import warns_on_defective_metric
from ._weights import (
    DEFAULT_ALPHA,
    check_weights,
    kernel_arguments,
    weights_on_graph,
)

VISCOUS_WEIGHTS = ("uniform", "kernel", "inverse_distance", "metric_diagonal", "metric_full")


@takes_tessellation
@warns_on_defective_metric
def edge_weights(
    tess: Tessellation, *, weights: str = "kernel", length_scale=None, metric=None, alpha: float | None = None
) -> Float[Array, "N K"]:
    """Raw edge weights w_ij of the viscous force, aligned with `tess.neighbors` (0 on padding).

    `weights` and the other arguments as in [`jaxgeom.viscous_force`][]."""
    check_weights(weights, "weights", VISCOUS_WEIGHTS, metric)
    alpha = kernel_arguments(weights, length_scale, alpha, metric)
    scale = None if length_scale is None else jnp.asarray(length_scale)  # arrays: no recompile per value
    return _edge_weights(tess, weights, scale, metric, alpha)


@eqx.filter_jit
def _edge_weights(tess, weights, length_scale, metric, alpha):
    return weights_on_graph(tess, weights, metric=metric, length_scale=length_scale, alpha=alpha)


def weights_to_normalize(
    tess: Tessellation, *, weights: str, length_scale=None, metric=None, alpha: float | Array = DEFAULT_ALPHA
) -> Float[Array, "N K"]:
    """`edge_weights` up to a per-row factor that row normalisation cancels: kernel weights are
    divided by each row's largest, so that they tend to nearest-neighbour weighting as l -> 0
    instead of underflowing to 0 / 0."""
    return weights_on_graph(tess, weights, metric=metric, length_scale=length_scale, alpha=alpha, shift="row")


def row_normalized_weights(
    tess: Tessellation,
    *,
    weights: str = "kernel",
    length_scale=None,
    metric=None,
    volume_weights=None,
    alpha: float = DEFAULT_ALPHA,
) -> Float[Array, "N K"]:
    """w_ij (V_j) / sum_k w_ik (V_k); rows of isolated walkers (zero degree) are all 0."""
    w = weights_to_normalize(tess, weights=weights, length_scale=length_scale, metric=metric, alpha=alpha)
    return normalize_rows(with_volume_weights(tess, w, volume_weights))[0]


def with_volume_weights(tess: Tessellation, weights, volume_weights):
    """w_ij V_j; edges to non-finite volumes (unbounded cells) are dropped."""
    if volume_weights is None:
        return weights
    vol = jnp.asarray(volume_weights, weights.dtype)
    vol = jnp.concatenate([jnp.where(jnp.isfinite(vol), vol, 0.0), jnp.zeros((1,), weights.dtype)])
    return weights * vol[tess.neighbors]


def normalize_rows(weights):
    """(W~, degree): weights divided by their row sums (rows summing to 0 stay 0, rows with a
    NaN weight, undefined by a zero metric, are NaN)."""
    degree = jnp.sum(weights, axis=1)
    safe = jnp.where(degree > 0, degree, 1.0)[:, None]
    normalized = jnp.where(degree[:, None] > 0, weights / safe, 0.0)
    return jnp.where(jnp.isnan(degree)[:, None], jnp.nan, normalized), degree


def apply_viscous(tess: Tessellation, normalized_weights, velocities, nu) -> Float[Array, "N d"]:
    """nu * sum_j W~_ij (v_j - v_i), coordinate by coordinate (one 1-D gather each)."""
    row_sum = jnp.sum(normalized_weights, axis=1)
    cols = []
    for k in range(velocities.shape[1]):
        table = jnp.concatenate([velocities[:, k], jnp.zeros((1,), velocities.dtype)])
        cols.append(jnp.sum(normalized_weights * table[tess.neighbors], axis=1) - row_sum * velocities[:, k])
    return nu * jnp.stack(cols, axis=1)


@takes_tessellation
@warns_on_defective_metric
def viscous_force(
    tess: Tessellation,
    velocities,
    *,
    nu,
    weights: str = "kernel",
    length_scale=None,
    metric=None,
    volume_weights=None,
    alpha: float | None = None,
) -> Float[Array, "N d"]:
    """The scutoidal viscous force F_i = nu sum_j w_ij / sum_k w_ik (v_j - v_i), O(N K).

    **Arguments:**

    - `tess`: Delaunay or k-NN [`jaxgeom.Tessellation`][] at the current positions.
    - `velocities`: (N, d) walker velocities.
    - `nu`: coupling strength nu >= 0 (a differentiable scalar).
    - `weights`: edge weights w_ij: "uniform" (1), "kernel"
      (exp(-|dx|^2 / (2 l^2))), "inverse_distance" (1 / (|dx| + eps)),
      "metric_diagonal" (1 / (|dx|_diag(g_edge) + eps)), "metric_full"
      (1 / (sqrt(dx^T g_edge dx) + eps)); eps = 1e-8 times the mean nearest-neighbour
      length, g_edge as in [`jaxgeom.edge_lengths`][].
    - `length_scale`: l of "kernel"; None = alpha * mean nearest-neighbour distance.
      The row-normalised kernel is computed relative to each row's nearest neighbour, so
      l far below the spacing tends to nearest-neighbour weighting (never 0 / 0).
    - `metric`: (N, d, d) array or callable x -> g; required by the metric modes, refused
      by the others.
    - `volume_weights`: optional (N,) cell volumes V_j; weights become w_ij V_j
      (edges to non-finite volumes are dropped). This breaks w_ij = w_ji.
    - `alpha`: factor of the adaptive length rule of "kernel" (None: 3). `length_scale` and
      `alpha` are refused with the rules that do not use them.

    **Returns:**

    (N, d) forces; 0 for walkers without neighbours.
    """
    check_weights(weights, "weights", VISCOUS_WEIGHTS, metric)  # volume_weights: takes_tessellation
    check_nonnegative(nu, "nu")
    alpha = kernel_arguments(weights, length_scale, alpha, metric)
    scale = None if length_scale is None else jnp.asarray(length_scale)  # arrays: no recompile per value
    return _viscous_force(tess, jnp.asarray(velocities), jnp.asarray(nu), weights, scale, metric, volume_weights, alpha)


@eqx.filter_jit
def _viscous_force(tess, velocities, nu, weights, length_scale, metric, volume_weights, alpha):
    w = row_normalized_weights(
        tess, weights=weights, length_scale=length_scale, metric=metric, volume_weights=volume_weights, alpha=alpha
    )
    return apply_viscous(tess, w, velocities, nu)
