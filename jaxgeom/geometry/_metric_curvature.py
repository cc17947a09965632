"""The Ricci scalar of a metric given as a function, in any dimension: no triangulation.

Three forms, one entry point (`metric_curvature`):

- "christoffel": any callable metric x -> g(x). Christoffel symbols from `jax.jacfwd` of
  g, the Ricci tensor from their derivatives (the reference; d^4 memory and d^4..d^5 work
  per walker).
- "hessian": a Hessian metric g = Hess V + eps_Sigma I = Hess(V + eps_Sigma |x|^2 / 2)
  (`hessian_metric`, where its floor is not active). Hessian geometry (Shima, "The
  Geometry of Hessian Structures", ch. 3) gives the scalar curvature from the third
  derivatives T = D^3 V alone,

      S = (|T|_g^2 - |tr_g T|_g^2) / 4,
      |T|_g^2 = g^ia g^jb g^kc T_ijk T_abc,  (tr_g T)_k = g^ij T_ijk,

  in the convention where the round sphere is positive. Exact: T in a g-orthonormal frame
  (O(d^4) per walker). Stochastic (`probes=m`): unbiased from m probe pairs, no d^3 tensor.
- Walkers where the metric is not positive definite, or where a Hessian metric's floor is
  active (so g is not a Hessian metric there), are flagged and NaN, never averaged.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..base._checks import check_choice, check_integer, host_points, metric_defect_masks
from ._metric import HessianParts, _call_metric, _hessian_metric, hessian_parts

CURVATURE_METHODS = ("auto", "christoffel", "hessian")
# "auto" recomputes walkers where a Hessian metric's floor is active with the Christoffel form
# up to this dimension, and flags them (NaN) above it: there the d^4 memory and d^5 work per
# walker (bench/README.md, "Curvature in any dimension") would dwarf the Hessian form's cost.
CHRISTOFFEL_FALLBACK_MAX_DIM = 10
# the exact Hessian form up to this dimension in `analyze` and the `simulate` observable,
# the stochastic form with `DEFAULT_PROBES` probe pairs above it
EXACT_HESSIAN_MAX_DIM = 16
DEFAULT_PROBES = 64
# walkers per chunk: the float64 intermediates of one chunk stay near this many bytes
CHUNK_BYTES = 1 << 28


class CurvatureInfo(eqx.Module):
    """Diagnostics of [`jaxgeom.metric_curvature`][] (its `with_info=True` output).

    - `standard_error`: (N,) standard error of the stochastic estimate (0 for exact forms).
    - `not_positive_definite`: (N,) the metric is not symmetric positive definite (S is NaN).
    - `floor_active`: (N,) a Hessian metric whose floor changes Hess V + eps_Sigma I there: g
      is not a Hessian metric at that walker. S comes from the Christoffel form where d <=
      `CHRISTOFFEL_FALLBACK_MAX_DIM` and `method="auto"`; else it is NaN. (All False with
      method="christoffel", which needs no Hessian structure.)
    - `ricci`: (N, d, d) Ricci tensor (with `ricci=True`), else None.
    - `method`: the form used ("christoffel", "hessian" or "hessian-stochastic").
    """

    standard_error: Float[Array, " N"]
    not_positive_definite: Bool[Array, " N"]
    floor_active: Bool[Array, " N"]
    ricci: Float[Array, "N d d"] | None
    method: str = eqx.field(static=True)


def christoffel_symbols(metric: Callable, x: Float[Array, " d"]) -> Float[Array, "d d d"]:
    """Gamma[k, i, j] = Gamma^k_ij = g^kl (d_i g_lj + d_j g_li - d_l g_ij) / 2 at x."""
    g = metric(x)
    dg = jax.jacfwd(metric)(x)  # dg[a, b, c] = d_c g_ab
    first = 0.5 * (jnp.swapaxes(dg, 1, 2) + dg - jnp.transpose(dg, (2, 0, 1)))  # Gamma_lij
    d = x.shape[0]
    return jnp.linalg.solve(g, first.reshape(d, d * d)).reshape(d, d, d)


def ricci_tensor(metric: Callable, x: Float[Array, " d"]) -> Float[Array, "d d"]:
    """R_sn = R^r_srn = d_r G^r_ns - d_n G^r_rs + G^r_rl G^l_ns - G^r_nl G^l_rs (G = Gamma),
    the convention in which the round sphere has positive curvature."""

    def both(y):
        gamma = christoffel_symbols(metric, y)
        return gamma, gamma

    dgamma, gamma = jax.jacfwd(both, has_aux=True)(x)  # dgamma[k, i, j, m] = d_m Gamma^k_ij
    ric = (
        jnp.einsum("rnsr->sn", dgamma)
        - jnp.einsum("rrsn->sn", dgamma)
        + jnp.einsum("rrl,lns->sn", gamma, gamma)
        - jnp.einsum("rnl,lrs->sn", gamma, gamma)
    )
    return 0.5 * (ric + ric.T)


def _christoffel_walker(metric: Callable, x, want_ricci: bool):
    """(S, not positive definite, Ricci tensor or None) at one walker by the Christoffel form."""
    g = metric(x)
    asymmetric, indefinite = metric_defect_masks(g[None], jnp)  # as `metric_defects`
    not_pd = asymmetric[0] | indefinite[0] | ~jnp.all(jnp.isfinite(g))
    ric = ricci_tensor(metric, x)
    scalar = jnp.trace(jnp.linalg.solve(g, ric))
    return jnp.where(not_pd, jnp.nan, scalar), not_pd, (ric if want_ricci else None)


def _cholesky_fails(m) -> Bool[Array, ""]:
    """Whether symmetric m is not positive definite: a Cholesky pivot is NaN or <= 0."""
    return ~jnp.all(jnp.diagonal(jnp.linalg.cholesky(m)) > 0)


def _metric_of(parts: HessianParts, h):
    """(g, floor active): g = H + eps_Sigma I from the Hessian H of V, and whether the floor
    changes it near x (always for softabs; for clip where H is not positive definite)."""
    h = 0.5 * (h + h.T)
    g = h + parts.eps_sigma * jnp.eye(h.shape[0], dtype=h.dtype)
    active = jnp.asarray(parts.floor == "softabs") | _cholesky_fails(h)
    return g, active


def _safe_cholesky(g):
    """(L, failed): the Cholesky factor of g, the identity where g is not positive definite
    (a finite stand-in, so that gradients through the masked value stay finite)."""
    eye = jnp.eye(g.shape[0], dtype=g.dtype)
    failed = _cholesky_fails(jax.lax.stop_gradient(g))
    return jnp.linalg.cholesky(jnp.where(failed, eye, g)), failed


def _in_frame(t, low):
    """T_abc in the g-orthonormal frame: L^-1 applied to each index (g = L L^T)."""
    d = low.shape[0]
    for _ in range(3):  # solve on the first index, then rotate it to the back
        t = jax.scipy.linalg.solve_triangular(low, t.reshape(d, -1), lower=True).reshape(d, d, d)
        t = jnp.transpose(t, (1, 2, 0))
    return t


def _hessian_exact_walker(parts: HessianParts, x):
    """(S, not positive definite, floor active) from T = D^3 V in a g-orthonormal frame."""

    def hessian_twice(y):
        h = jax.hessian(parts.fitness)(y)
        return h, h

    t, h = jax.jacfwd(hessian_twice, has_aux=True)(x)  # T_ijk = d_k H_ij, and H
    g, active = _metric_of(parts, h)
    low, failed = _safe_cholesky(g)
    not_pd = failed & ~active  # where active, g is not H + eps_Sigma I
    tt = _in_frame(t, low)
    trace = jnp.einsum("aac->c", tt)
    scalar = 0.25 * (jnp.sum(tt * tt) - jnp.sum(trace * trace))
    return jnp.where(not_pd | active, jnp.nan, scalar), not_pd, active


def _third_covector(fitness: Callable, x, a, b):
    """T(a, b, .) = grad_x D^2 V(x)[a, b]: a third derivative contracted on two slots."""

    def second(y):
        return jax.jvp(lambda u: jax.jvp(fitness, (u,), (a,))[1], (y,), (b,))[1]

    return jax.grad(second)(x)


def _hessian_stochastic_walker(parts: HessianParts, x, key, probes: int):
    """(S, standard error, not positive definite, floor active) from `probes` probe pairs.

    With z, z' ~ N(0, g^-1) independent, u = T(z, z, .), u' = T(z', z', .), v = T(z, z', .):
    E[v^T g^-1 v] = |T|_g^2 and E[u^T g^-1 u'] = |tr_g T|_g^2 (E[z z^T] = g^-1), so each
    sample (|L^-1 v|^2 - (L^-1 u).(L^-1 u')) / 4 is an unbiased estimate of S. Contracting the
    third slot exactly (a gradient instead of a third probe) lowers the variance of the
    nested-jvp form E[T(z1, z2, z3)^2] at the cost of one reverse pass."""
    g, active = _metric_of(parts, jax.hessian(parts.fitness)(x))
    d = x.shape[0]
    low, failed = _safe_cholesky(g)
    not_pd = failed & ~active
    xi = jax.random.normal(key, (2, probes, d), g.dtype)
    z = jax.scipy.linalg.solve_triangular(low.T, xi.reshape(-1, d).T, lower=False).T.reshape(2, probes, d)
    third = jax.vmap(lambda a, b: _third_covector(parts.fitness, x, a, b))
    pairs_a = jnp.concatenate([z[0], z[1], z[0]])
    pairs_b = jnp.concatenate([z[0], z[1], z[1]])
    w = jax.scipy.linalg.solve_triangular(low, third(pairs_a, pairs_b).T, lower=True).T.reshape(3, probes, d)
    samples = 0.25 * (jnp.sum(w[2] ** 2, axis=1) - jnp.sum(w[0] * w[1], axis=1))
    scalar = jnp.mean(samples)
    error = jnp.std(samples, ddof=1) / math.sqrt(probes) if probes > 1 else jnp.full((), jnp.nan, g.dtype)
    bad = not_pd | active
    return jnp.where(bad, jnp.nan, scalar), jnp.where(bad, jnp.nan, error), not_pd, active


def metric_curvature(
    metric: Callable,
    points,
    *,
    probes: int | None = None,
    key=None,
    method: str = "auto",
    ricci: bool = False,
    chunk: int | None = None,
    with_info: bool = False,
):
    """The Ricci scalar of a metric x -> g(x) at every walker, in any dimension.

    No triangulation: the curvature of the metric itself at the walkers, the quantity the
    Regge proxy `ricci_scalar` approximates on a Delaunay graph. Jittable and
    differentiable (in the points and in whatever the metric closes over, e.g. eps_Sigma).

    **Arguments:**

    - `metric`: a JAX callable x (d,) -> g (d, d), e.g. from [`jaxgeom.hessian_metric`][].
    - `points`: (N, d) walker positions.
    - `probes`: None for an exact form; an int m >= 1 for the unbiased stochastic Hessian
      form with m probe pairs (a `hessian_metric` only; cost m x a few evaluations of V
      and one Cholesky factor per walker, no d^3 tensor: for large d).
    - `key`: PRNG key for the probes (required with `probes`).
    - `method`: "auto" (the Hessian form for a `hessian_metric`, the Christoffel form for
      any other callable), "christoffel" (the autodiff reference, any metric) or "hessian".
      With "auto", walkers where a Hessian metric's floor is active (there g is not a
      Hessian metric) take the Christoffel form when d <= 10 and are NaN above.
    - `ricci`: also return the Ricci tensor (Christoffel form) in the info.
    - `chunk`: walkers per batch (memory stays bounded); default: about 256 MiB of
      float64 intermediates per batch.
    - `with_info`: return `(scalar, info)`, info a [`jaxgeom.CurvatureInfo`][].

    A `hessian_metric` callable is recognised by its `hessian_parts` attribute; wrapped in
    another function it is a general metric to this function (the Christoffel form). Either
    way the floor's second derivatives come from its spectral function's own rules (divided
    differences; `jaxgeom.hessian_metric`), finite at repeated eigenvalues, and never from
    differentiating an eigensolver.

    **Returns:**

    (N,) Ricci scalar S, positive on the round sphere (S = d(d-1)/R^2); NaN (flagged in the
    info) where the metric is not positive definite or a floor is active beyond the
    fallback.
    """
    points, parts, form = _check_arguments(metric, points, probes, key, method, ricci, chunk)
    n, d = points.shape
    chunk = _default_chunk(d, form, probes, parts) if chunk is None else chunk
    fallback = method == "auto" and form == "hessian" and d <= CHRISTOFFEL_FALLBACK_MAX_DIM
    scalar, info = _curvature(metric, points, key, parts, form, probes, ricci, min(chunk, n), fallback)
    return (scalar, info) if with_info else scalar


def _check_arguments(metric, points, probes, key, method, ricci, chunk):
    check_choice(method, "method", CURVATURE_METHODS)
    if not callable(metric):
        raise TypeError(
            "`metric` must be a JAX callable x (d,) -> g (d, d) (curvature needs the metric's derivatives, "
            f"which an array of values does not have); got {type(metric).__name__}. For the fitness "
            "metric pass jaxgeom.hessian_metric(fitness, eps_sigma)."
        )
    points = _checked_points(points)
    _check_metric_output(metric, points)
    parts = hessian_parts(metric)
    if method == "hessian" and parts is None:
        raise ValueError(
            "method='hessian' needs a metric from jaxgeom.hessian_metric (g = Hess V + eps_Sigma I); "
            "for any other callable use method='christoffel' or 'auto'."
        )
    if probes is not None:
        check_integer(probes, "probes", 1)
        if parts is None or method == "christoffel":
            raise ValueError(
                "`probes` (the stochastic form) needs the Hessian form: a metric from "
                "jaxgeom.hessian_metric with method 'auto' or 'hessian'; use probes=None otherwise."
            )
        if key is None:
            raise ValueError("`probes` draws random probes: give `key`, e.g. key=jax.random.key(0).")
    if chunk is not None:
        check_integer(chunk, "chunk", 1)
    if ricci and method == "hessian":
        raise ValueError("`ricci=True` computes the Ricci tensor by the Christoffel form: use method='christoffel'.")
    if ricci:
        method = "christoffel"
    if method == "auto":
        method = "christoffel" if parts is None else "hessian"
    return points, parts, method


def _checked_points(points):
    """(N, d) float points: checked on the host (`host_points`) when concrete, by shape and
    dtype when traced."""
    if not isinstance(points, jax.core.Tracer):
        return jnp.asarray(host_points(points))
    if points.ndim != 2:
        raise ValueError(f"`points` must have shape (N, d), one row per walker; got shape {points.shape}.")
    if not jnp.issubdtype(points.dtype, jnp.floating):
        raise TypeError(f"`points` must be a float array (float32 or float64); got dtype {points.dtype}.")
    return points


def _check_metric_output(metric, points):
    """Traceable, (d, d), real (`_call_metric`, traced only) and floating."""
    d = points.shape[1]
    out = jax.eval_shape(lambda x: _call_metric(metric, x), jax.ShapeDtypeStruct((1, d), points.dtype))
    if not jnp.issubdtype(out.dtype, jnp.floating):
        raise TypeError(f"the metric callable must return a real floating-point matrix; it returned dtype {out.dtype}.")


def _default_chunk(d: int, method: str, probes, parts) -> int:
    """Walkers per batch so that one batch's float64 intermediates stay near CHUNK_BYTES
    (per walker, XLA's memory analysis: the Christoffel form 17-24 d^4 bytes at d = 10-50,
    the exact Hessian form ~24 d^3, the stochastic one ~110 bytes per probe and dimension)."""
    if method == "christoffel":
        per_walker = 32 * d**4
    else:
        per_walker = 32 * d**3 if probes is None else 128 * probes * d + 32 * d * d
        if d <= CHRISTOFFEL_FALLBACK_MAX_DIM:  # the fallback may run on the same batch
            per_walker = max(per_walker, 32 * d**4)
    return max(1, CHUNK_BYTES // per_walker)


@eqx.filter_jit
def _curvature(metric, points, key, parts, method, probes, want_ricci, chunk, fallback):
    n, d = points.shape
    if parts is not None:  # the same metric with LAPACK's eigh in its floor (see `_hessian_metric`)
        metric = _hessian_metric(parts.fitness, parts.eps_sigma, parts.floor, eigh=jnp.linalg.eigh)
    keys = jax.random.split(key, n) if probes is not None else jnp.zeros((n,), points.dtype)

    def christoffel(x):
        return jax.vmap(lambda y: _christoffel_walker(metric, y, want_ricci))(x)

    def batch(x, k):
        if method == "christoffel":
            s, npd, ric = christoffel(x)
            return s, jnp.zeros_like(s), npd, jnp.zeros_like(npd), ric
        if probes is None:
            s, npd, active = jax.vmap(lambda y: _hessian_exact_walker(parts, y))(x)
            se = jnp.zeros_like(s)
        else:
            s, se, npd, active = jax.vmap(lambda y, kk: _hessian_stochastic_walker(parts, y, kk, probes))(x, k)
        if fallback:  # only batches holding a floor-active walker pay for the Christoffel form
            s, se, npd = jax.lax.cond(
                jnp.any(active), lambda: _replace(christoffel(x), s, se, npd, active), lambda: (s, se, npd)
            )
        return s, se, npd, active, None

    s, se, npd, active, ric = _chunks(batch, (points, keys), n, chunk)
    name = "christoffel" if method == "christoffel" else "hessian" if probes is None else "hessian-stochastic"
    return s, CurvatureInfo(se, npd, active, ric, name)


def _replace(christoffel, s, se, npd, active):
    """The Christoffel form's (S, 0, not positive definite) at the floor-active walkers."""
    exact, exact_npd, _ = christoffel
    return jnp.where(active, exact, s), jnp.where(active, 0.0, se), jnp.where(active, exact_npd, npd)


def _chunks(fn, args, n: int, chunk: int):
    """fn over consecutive batches of `chunk` walkers (the leading axis of every arg)."""
    if chunk >= n:
        return fn(*args)
    pad = (-n) % chunk
    batched = [jnp.concatenate([a, jnp.repeat(a[:1], pad, axis=0)]).reshape((-1, chunk) + a.shape[1:]) for a in args]
    out = jax.lax.map(lambda b: fn(*b), batched)
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:])[:n], out)
