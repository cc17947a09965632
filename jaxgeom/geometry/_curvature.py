"""Regge curvature: hinge angles from squared edge lengths, deficit angles, Ricci scalar."""

from __future__ import annotations

import functools
import itertools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..base._simplex import det_entries, safe_sqrt
from ..tessellation._graph import Tessellation, edge_slots, takes_tessellation
from ._metric import (
    check_metric,
    edge_lengths,
    edge_pairs,
    riemannian_volumes,
    simplex_sq_lengths,
    simplex_sq_lengths_with_references,
    warns_on_defective_metric,
)
from ._volumes import voronoi_volumes

TWO_PI = 2.0 * math.pi
# Rounding of one hinge angle in ulps (the metric's own rounding and the length formulas;
# measured in float32 against float64 on Hessian metrics, tests/test_reliability.py).
RICCI_ULPS = 64.0


@functools.cache
def hinges(d: int) -> tuple[tuple[tuple[int, ...], tuple[int, int]], ...]:
    """Hinges ((d-2)-faces) of a d-simplex with the two vertices opposite each."""
    out = []
    for c, e in itertools.combinations(range(d + 1), 2):
        out.append((tuple(v for v in range(d + 1) if v not in (c, e)), (c, e)))
    return tuple(out)


def hinge_angle_vectors(sq_lengths, d: int):
    """(cos, sin)-proportional pair (x, y) of the dihedral angle at every hinge of one
    simplex, and the hinge's measure; the angle is atan2(y, x).

    Only the (d+1)d/2 squared edge lengths are used (a sequence, ordered as `edge_pairs(d)`). With the Gram matrix G
    based
    at a hinge vertex (hinge vectors H first, then the two opposite vertices c, e):
    x = det G[H+c, H+e] and y = sqrt(det G[H,H] det G) (the Desnanot-Jacobi
    identity gives x^2 + y^2 = det G[H+c, H+c] det G[H+e, H+e]). This adjugate form
    has no division, stays finite when metric lengths do not form a valid simplex
    (det G < 0 gives theta = 0 or pi), and avoids the cancellation of 1 - cos^2.

    **Returns:**

    `(x, y, size)`, each (number of hinges,), ordered as `hinges(d)`.
    """
    out = [hinge_angle_vector(sq_lengths, d, k) for k in range(len(hinges(d)))]
    return tuple(jnp.stack(parts) for parts in zip(*out, strict=True))


def hinge_angle_vector(sq_lengths, d: int, k: int):
    """`hinge_angle_vectors` of hinge k alone: (x, y, size)."""
    index = {p: j for j, p in enumerate(edge_pairs(d))}

    def sq(p, q):
        return 0.0 if p == q else sq_lengths[index[(min(p, q), max(p, q))]]

    hinge, (c, e) = hinges(d)[k]
    base, rest = hinge[0], list(hinge[1:])
    vecs = rest + [c, e]
    gram = [[0.5 * (sq(base, p) + sq(base, q) - sq(p, q)) for q in vecs] for p in vecs]
    m = len(rest)
    det_hh = det_entries([row[:m] for row in gram[:m]]) if m else 1.0
    x = det_entries([row[:m] + [row[m + 1]] for row in gram[: m + 1]])
    y = safe_sqrt(det_hh * det_entries(gram))
    size = safe_sqrt(det_hh) / math.factorial(m) if m else jnp.ones_like(y)
    return x, y, size


def _safe_atan2(y, x):
    degenerate = (y == 0) & (x == 0)
    return jnp.where(degenerate, 0.0, jnp.arctan2(y, jnp.where(degenerate, 1.0, x)))


def _metric_and_euclidean_sq_lengths(tess: Tessellation, metric, mode: str):
    """Squared simplex edge lengths in the metric and in Euclidean space (the same array
    when the metric is not used). The barrier materialises them once: fused into each of
    their many consumers, their gathers would be recomputed (2x slower with an array metric)."""
    # (Measured: a barrier on the stacked (S, P) arrays works; on a tuple of P columns XLA
    # still duplicated the producers, 4x slower.)
    if check_metric(tess, metric, mode) is None:
        sq_e = jax.lax.optimization_barrier(simplex_sq_lengths(tess))
        return sq_e, sq_e
    return jax.lax.optimization_barrier((simplex_sq_lengths(tess, metric, mode=mode), simplex_sq_lengths(tess)))


def _hinge_vectors(tess: Tessellation, metric, mode: str):
    """`hinge_angle_vectors` of every simplex in the metric, (x_g, y_g, size_g), and in
    Euclidean space, (x_e, y_e)."""
    if tess.simplices is None:
        raise ValueError("curvature needs Delaunay simplices; a k-NN graph has none. Use jaxgeom.delaunay.")
    vectors = jax.vmap(lambda sq: hinge_angle_vectors(sq, tess.dim))
    sq_g, sq_e = _metric_and_euclidean_sq_lengths(tess, metric, mode)
    x_e, y_e, _ = vectors(sq_e)
    return vectors(sq_g), (x_e, y_e)


def _all_hinge_angles(tess: Tessellation, metric, mode: str):
    (x_g, y_g, size_g), (x_e, y_e) = _hinge_vectors(tess, metric, mode)
    theta_g, theta_e = _safe_atan2(y_g, x_g), _safe_atan2(y_e, x_e)
    valid = tess.simplex_mask[:, None]
    return jnp.where(valid, theta_g, 0.0), jnp.where(valid, size_g, 0.0), jnp.where(valid, theta_e, 0.0)


@functools.cache
def _hinges_of_vertex(d: int) -> tuple[tuple[int, ...], ...]:
    """For each vertex of a d-simplex, the indices (in `hinges(d)`) of the hinges containing it."""
    return tuple(tuple(k for k, (h, _) in enumerate(hinges(d)) if v in h) for v in range(d + 1))


def _hinge_vertex_ids(tess: Tessellation):
    """(S, H, d-1) walker ids of every hinge of every simplex (sentinel on padding)."""
    return tess.simplices[:, np.array([h for h, _ in hinges(tess.dim)])]


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def angle_sums(tess: Tessellation, *, metric=None, mode: str = "full"):
    """Total hinge angle around each hinge, in the metric.

    **Returns:**

    2D: (N,) sum of triangle angles at each vertex. 3D: (N, K) sum of dihedral
    angles around each edge, aligned with `tess.neighbors` (0 on padding).
    """
    check_metric(tess, metric, mode)
    theta_g, _, _ = _all_hinge_angles(tess, metric, mode)
    return _per_hinge(tess, theta_g)


def _per_hinge(tess: Tessellation, per_simplex):
    """Sum a (S, H) per-simplex hinge quantity over the simplices around each hinge."""
    n, d = tess.n_points, tess.dim
    ids = _hinge_vertex_ids(tess)
    if d == 2:
        return jax.ops.segment_sum(per_simplex.ravel(), ids[..., 0].ravel(), num_segments=n)
    if d != 3:
        raise ValueError(f"per-hinge values are available for d = 2 and 3 (got d={d}); use ricci_scalar in higher d.")
    k_cap = tess.neighbors.shape[1]
    a, b = ids[..., 0], ids[..., 1]
    totals = jnp.zeros(n * k_cap + 1, per_simplex.dtype)
    for src, dst, first, second in ((a, b, 0, 1), (b, a, 1, 0)):
        shift = None
        if tess.simplex_shifts is not None:
            hv = np.array([h for h, _ in hinges(d)])
            sh = tess.simplex_shifts[:, hv]
            shift = sh[:, :, second] - sh[:, :, first]
        slot = edge_slots(tess, src, dst, shift)
        flat = jnp.where((src < n) & (slot < k_cap), src * k_cap + slot, n * k_cap)
        totals = totals.at[flat.ravel()].add(per_simplex.ravel())
    return jnp.where(tess.neighbor_mask, totals[:-1].reshape(n, k_cap), 0.0)


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def deficit_angles(tess: Tessellation, *, metric=None, mode: str = "full"):
    r"""Regge deficit angles $\delta_h = 2\pi - \sum_{\sigma \ni h} \theta_{\sigma h}$, the hinge
    angles $\theta_{\sigma h}$ of the simplices $\sigma$ around hinge $h$ measured with metric edge
    lengths.

    Hinges on the convex hull carry no deficit (0). A hinge is interior when its
    Euclidean angles close up to 2 pi (they sum to at most pi on the hull).

    **Returns:**

    2D: (N,) one deficit per vertex. 3D: (N, K) one per edge, aligned with
    `tess.neighbors` (both directions of an edge hold the same value; 0 on padding).
    """
    check_metric(tess, metric, mode)
    theta_g, _, theta_e = _all_hinge_angles(tess, metric, mode)
    total_g, total_e = _per_hinge(tess, theta_g), _per_hinge(tess, theta_e)
    return jnp.where(total_e > 1.5 * math.pi, TWO_PI - total_g, 0.0)


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def ricci_scalar(tess: Tessellation, *, metric=None, mode: str = "full", volumes=None) -> Float[Array, " N"]:
    r"""Regge Ricci scalar $R_i = \frac{2}{d-1} \sum_{h \ni i} \delta_h \, |h| \, / \, V_i$.

    The scalar curvature: $R = d (d - 1) K$ on a space of constant sectional curvature $K$
    ($R_i = 2 \delta_i / V_i$ in 2D).

    V_i is the Riemannian cell volume `riemannian_volumes(tess, metric)`. The deficit
    of an interior hinge h is a sum over the simplices around it of theta_ref - theta_g,
    where theta_ref is the angle in the hinge's own constant metric g_h (the vertex's
    metric in 2D, the mean metric of the hinge's edges in 3D and up): the angles of a
    constant metric close up to exactly 2 pi, and each difference is computed in one
    atan2, so a constant metric gives exactly R = 0 and a slowly varying one adds no
    cancellation of its own. What limits the precision is the metric's own rounding:
    see [`jaxgeom.ricci_resolution`][] for the smallest resolvable |R|.

    **Arguments:**

    - `tess`: Delaunay tessellation, d >= 2.
    - `metric`, `mode`: as in [`jaxgeom.edge_lengths`][].
    - `volumes`: Euclidean Voronoi volumes to reuse (default: computed).

    **Returns:**

    (N,) Ricci scalar; NaN on tier 0. Pointwise values are noisy on irregular
    points; region averages sum R_i V_i / sum V_i converge
    (`jaxgeom.riemannian_mean`).
    """
    total, _ = _hinge_sums(tess, metric, mode)
    return _per_volume(tess, total, _cell_volumes(tess, metric, mode, volumes))


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def ricci_resolution(tess: Tessellation, *, metric=None, mode: str = "full", volumes=None) -> Float[Array, " N"]:
    """The smallest |R_i| that `ricci_scalar` resolves in the points' dtype (N,).

    Every hinge angle carries an absolute error of about `RICCI_ULPS` x eps (the metric
    and the lengths are rounded), so R_i is uncertain by (2/(d-1)) RICCI_ULPS eps
    sum_h |h| / V_i: about 400 eps / h^2 in 2D at spacing h (float32, h = 1e-3: 5e1).
    A metric that varies less than its own rounding over a cell has lost its curvature
    (float32 may return 0 there); the resolution says so. A constant metric is exact
    (R = 0). NaN on tier 0. Measured against float64 on a Hessian metric at spacings
    1e-2 ... 1e-6 (tests/test_reliability.py): the float32 error of 99% of the walkers stays
    below this (2D: all, at most 0.3x; 3D: slivers, nearly flat tetrahedra whose angles
    are ill-conditioned, reach a few times it). This is the
    error of the computation on the given points; points far from the origin (|x| >> h)
    are themselves rounded to eps |x|, which moves R by about eps |x| / h^3 more.
    """
    _, errors = _hinge_sums(tess, metric, mode)
    return _per_volume(tess, errors, _cell_volumes(tess, metric, mode, volumes))


def _hinge_sums(tess: Tessellation, metric, mode: str):
    """Per walker: (2/(d-1)) sum over its hinges and their simplices of (theta_ref -
    theta_g) |h|, and the same sum of its rounding error, RICCI_ULPS eps |h|."""
    d = tess.dim
    if tess.simplices is None:
        raise ValueError("curvature needs Delaunay simplices; a k-NN graph has none. Use jaxgeom.delaunay.")
    sq_g, sq_ref = _metric_and_reference_sq_lengths(tess, metric, mode)
    # Angles depend on ratios of lengths only: scale each simplex to unit size, so that the
    # Gram determinants (length^2d) neither underflow nor overflow; |h| scales back below.
    # The scale's value cancels (angles use ratios, |h| is scaled back), so it carries no
    # gradient: reduce_max's derivative divides by the count of entries equal to the max, 0 where
    # XLA rounds two copies differently (seen at --xla_backend_optimization_level=0: NaN).
    scale = jax.lax.stop_gradient(jnp.max(sq_g, axis=1, keepdims=True))
    scale = jnp.where(scale > 0, scale, 1.0)
    sq_g, sq_ref = sq_g / scale, [sq / scale for sq in sq_ref]
    size_scale = jnp.sqrt(scale[:, 0]) ** (d - 2)
    eps = jnp.finfo(sq_g.dtype).eps
    diffs, errors = [], []
    for k in range(len(hinges(d))):
        angle = jax.vmap(functools.partial(hinge_angle_vector, d=d, k=k))
        x_g, y_g, size_g = angle(sq_g)
        x_r, y_r, _ = angle(sq_ref[k])
        diff = _safe_atan2(y_r * x_g - x_r * y_g, x_r * x_g + y_r * y_g)  # both angles lie in [0, pi]
        same = jnp.all(sq_ref[k] == sq_g, axis=1)  # exactly 0 (XLA's fused multiply-add would leave an ulp)
        diffs.append(jnp.where(same, 0.0, diff) * size_g * size_scale)
        # also where `same`: a metric that varies below its rounding has lost its curvature
        errors.append(RICCI_ULPS * eps * size_g * size_scale)
    valid = tess.simplex_mask
    factor = 2.0 / (d - 1)
    out = []
    for per_hinge in (diffs, errors):
        # sum each vertex's hinges inside the simplex first: d + 1 scattered values per simplex
        per_vertex = jnp.stack(
            [jnp.where(valid, sum(per_hinge[h] for h in hs), 0.0) for hs in _hinges_of_vertex(d)], axis=1
        )
        out.append(factor * jax.ops.segment_sum(per_vertex.ravel(), tess.simplices.ravel(), num_segments=tess.n_points))
    return tuple(out)


def _metric_and_reference_sq_lengths(tess: Tessellation, metric, mode: str):
    """(S, P) squared edge lengths in the metric, and for every hinge k the same lengths in
    the hinge's reference metric (the metric itself when it is not used: R = 0 exactly)."""
    if check_metric(tess, metric, mode) is None:
        sq = jax.lax.optimization_barrier(simplex_sq_lengths(tess))
        return sq, [sq] * len(hinges(tess.dim))
    sq_g, sq_ref = simplex_sq_lengths_with_references(
        tess, metric, mode=mode, hinge_edges=[_hinge_edge_ids(tess.dim, k) for k in range(len(hinges(tess.dim)))]
    )
    return jax.lax.optimization_barrier((sq_g, sq_ref))


def _hinge_edge_ids(d: int, k: int) -> tuple[int, ...]:
    """Positions in `edge_pairs(d)` of hinge k's edges; for d = 2 (a vertex hinge) the
    negative code -1 - vertex, meaning the vertex's own metric."""
    hinge = hinges(d)[k][0]
    if len(hinge) == 1:
        return (-1 - hinge[0],)
    return tuple(j for j, (a, b) in enumerate(edge_pairs(d)) if a in hinge and b in hinge)


def _cell_volumes(tess: Tessellation, metric, mode: str, volumes):
    """Riemannian cell volumes for `_per_volume`, which reads tiers 1-2 only: their cells lie
    inside any box, so the Euclidean volumes are taken unclipped (clipping to the box changes
    tier 0 alone and costs ~1.6 s at N = 1e4 in 3D)."""
    base = voronoi_volumes(tess, clip=False) if volumes is None else volumes
    return riemannian_volumes(tess, metric=metric, mode=mode, volumes=base)


def _per_volume(tess: Tessellation, numerator, volumes):
    """numerator / V on tiers 1-2, NaN on tier 0 (double `where`: finite gradients)."""
    ok = (tess.tier > 0) & jnp.isfinite(volumes) & (volumes != 0)
    return jnp.where(ok, numerator / jnp.where(ok, volumes, 1.0), jnp.nan)


@takes_tessellation
@eqx.filter_jit
def ricci_from_deficits(tess: Tessellation, metric=None, *, mode: str = "full") -> Float[Array, " N"]:
    """R_i from `deficit_angles` directly (2D and 3D): the textbook form of `ricci_scalar`."""
    delta = deficit_angles(tess, metric=metric, mode=mode)
    vol = _cell_volumes(tess, metric, mode, None)
    if tess.dim == 2:
        return _per_volume(tess, 2.0 * delta, vol)
    return _per_volume(tess, jnp.sum(delta * edge_lengths(tess, metric=metric, mode=mode), axis=1), vol)
