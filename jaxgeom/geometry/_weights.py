"""Edge weight rules w_ij over the padded neighbour lists: one registry, name -> rule.

Every rule maps squared edge lengths (N, K) and a mask of the slots that count to weights
(0 elsewhere). The viscous force, `edge_weights`, the graph Laplacian and the gradient
estimators each accept a subset of `EDGE_WEIGHTS`; a rule with `needs_metric` measures
its lengths in the metric g_edge of `jaxgeom.edge_lengths` (`metric_mode` says how much of
g), the others in Euclidean length. To add a weight mode, add one function and one entry.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._checks import check_choice, check_positive
from ..base._simplex import safe_sqrt
from ..tessellation._graph import Tessellation, mean_row_minimum, minimum_along_rows, neighbor_distances
from ._metric import edge_sq_lengths

DEFAULT_ALPHA = 3.0
# eps of w = 1 / (length + eps), relative to the mean nearest-neighbour length (no absolute
# regularisers: the result does not depend on the units). The chapter's absolute 1e-8 is
# this at unit spacing.
INVERSE_DISTANCE_EPS = 1e-8


def mean_nearest_neighbor_distance(tess: Tessellation):
    """Mean over walkers of the distance to their nearest neighbour."""
    return mean_row_minimum(neighbor_distances(tess), tess.neighbor_mask)


def uniform(sq, mask, **_):
    """w_ij = 1."""
    return mask.astype(sq.dtype)


def kernel(sq, mask, *, length_scale=None, alpha=DEFAULT_ALPHA, shift: str = "none", **_):
    """w_ij = exp(-|dx|^2 / (2 l^2)), l = `length_scale` or alpha * mean nearest-neighbour length.

    `shift` divides the weights by a constant that a normalisation cancels, so that they
    cannot all underflow when l is far below the spacing: "row" by each row's largest
    weight (row-normalised uses: the limit l -> 0 is nearest-neighbour weighting, not
    0 / 0), "global" by the largest of the graph (keeps w_ij = w_ji, as the Laplacian needs)."""
    scale = alpha * mean_row_minimum(safe_sqrt(sq), mask) if length_scale is None else length_scale
    exponent = sq / (2.0 * scale**2)
    if shift != "none":
        masked = jnp.where(mask, exponent, jnp.inf)
        smallest = minimum_along_rows(masked)[:, None] if shift == "row" else jnp.min(masked)
        exponent = exponent - jax.lax.stop_gradient(jnp.where(jnp.isfinite(smallest), smallest, 0.0))
    return jnp.where(mask, jnp.exp(-exponent), 0.0)


def inverse_distance(sq, mask, *, relative_eps=INVERSE_DISTANCE_EPS, **_):
    """w_ij = 1 / (|dx| + eps), eps = `relative_eps` x the mean nearest-neighbour length
    (the estimators' stencils exclude coincident walkers and use 0); NaN where the length and
    eps are both 0 (a zero metric)."""
    lengths = safe_sqrt(sq)
    eps = relative_eps * mean_row_minimum(lengths, mask)
    defined = mask & (lengths + eps > 0)  # a zero metric has no lengths at all: NaN, not inf
    return jnp.where(defined, 1.0 / jnp.where(defined, lengths + eps, 1.0), jnp.where(mask, jnp.nan, 0.0))


def gaussian(sq, mask, **_):
    """w_ij = exp(-|dx|^2 / (2 s_i^2)), s_i = walker i's median neighbour distance."""
    dist = safe_sqrt(sq)
    sigma = jnp.nanmedian(jnp.where(mask, dist, jnp.nan), axis=-1, keepdims=True)
    sigma = jnp.where(jnp.isfinite(sigma), sigma, 1.0)
    return jnp.where(mask, jnp.exp(-jnp.where(mask, sq, 0.0) / (2.0 * sigma**2)), 0.0)


class WeightRule(NamedTuple):
    fn: Callable
    metric_mode: str = "none"  # how much of the metric measures the lengths (`jaxgeom.edge_lengths`)

    @property
    def needs_metric(self) -> bool:
        return self.metric_mode != "none"


EDGE_WEIGHTS: dict[str, WeightRule] = {
    "uniform": WeightRule(uniform),
    "kernel": WeightRule(kernel),
    "inverse_distance": WeightRule(inverse_distance),
    "metric_diagonal": WeightRule(inverse_distance, "diagonal"),
    "metric_full": WeightRule(inverse_distance, "full"),
    "gaussian": WeightRule(gaussian),
}


def check_weights(name: str, argument: str, allowed: tuple[str, ...], metric=None) -> WeightRule:
    """The rule `name` (one of `allowed`), with a clear error for an unknown name or a
    metric rule without a metric."""
    check_choice(name, argument, allowed)
    rule = EDGE_WEIGHTS[name]
    if rule.needs_metric and metric is None:
        raise ValueError(
            f"{argument} {name!r} needs `metric` (an (N, d, d) array or a callable x -> g); "
            "pass one, or use 'kernel'/'inverse_distance' for Euclidean weights."
        )
    return rule


def check_length_scale(length_scale) -> None:
    check_positive(length_scale, "length_scale", " (or None for the adaptive rule)")


def check_alpha(alpha) -> None:
    check_positive(alpha, "alpha", " (the adaptive kernel width is alpha x the nearest-neighbour distance)")


def kernel_arguments(weights: str, length_scale, alpha, metric=None):
    """Check and resolve the kernel's width arguments of a public weight function: `length_scale`
    and `alpha` act only on weights="kernel" (alpha only without a length_scale), `metric` only on
    the metric rules; an argument a rule would ignore is refused. Returns alpha (None: the default)."""
    if length_scale is not None and weights != "kernel":
        raise ValueError(
            f"`length_scale` sets the width of weights='kernel'; weights={weights!r} does not use it. "
            "Leave it None, or use weights='kernel'."
        )
    if alpha is not None and (weights != "kernel" or length_scale is not None):
        raise ValueError(
            "`alpha` sets the adaptive width (alpha x the nearest-neighbour distance) of "
            f"weights='kernel' without a length_scale; here weights={weights!r}, length_scale="
            f"{length_scale!r}. Leave alpha None."
        )
    if metric is not None and not EDGE_WEIGHTS[weights].needs_metric:
        raise ValueError(
            f"`metric` is used by the metric weights ('metric_diagonal', 'metric_full'); weights="
            f"{weights!r} measures Euclidean lengths. Leave metric None, or use a metric rule."
        )
    check_length_scale(length_scale)
    if alpha is None:
        return DEFAULT_ALPHA
    check_alpha(alpha)
    return alpha


def weights_on_graph(
    tess: Tessellation, name: str, *, metric=None, length_scale=None, alpha=DEFAULT_ALPHA, shift: str = "none"
) -> Float[Array, "N K"]:
    """w_ij of rule `name` per neighbour slot of `tess` (0 on padding); names are not checked here."""
    rule = EDGE_WEIGHTS[name]
    sq = edge_sq_lengths(tess, metric if rule.needs_metric else None, mode=rule.metric_mode)
    return rule.fn(sq, tess.neighbor_mask, length_scale=length_scale, alpha=alpha, shift=shift)
