"""Metrics: the three accepted forms, metric edge lengths, Hessian and emergent metrics.

A `metric` argument is `None` (Euclidean), an (N, d, d) array of per-walker
tensors, or a JAX callable x (d,) -> g (d, d). Arrays are checked on the host
(symmetric, positive definite); callables are not, and `metric_defects` flags the
walkers where one is not a metric. The metric of an edge is g at the
edge midpoint for a callable and (g_i + g_j) / 2 for an array (both
symmetric in i and j, so every edge has one length).
`mode` picks how much of it is used: "none" (Euclidean), "diagonal", "full".
"""

from __future__ import annotations

import functools
import inspect
import itertools
import weakref
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..base._checks import (
    check_choice,
    check_nonnegative,
    check_walker_mask,
    metric_defect_masks,
    real_array,
    walker_values,
    warn_at_caller,
)
from ..base._simplex import (
    HIGHEST,
    JACOBI_SWEEPS,
    WRITTEN_OUT_MAX_DIM,
    dot,
    small_adjugate,
    small_det,
    small_eigh,
    spectral_function,
)
from ..tessellation._graph import (
    Tessellation,
    neighbor_displacements,
    neighbor_displacements_for_sums,
    simplex_coords,
    take_or_zero,
    takes_tessellation,
)
from ._volumes import voronoi_volumes

METRIC_MODES = ("none", "diagonal", "full")
HESSIAN_FLOORS = ("clip", "softabs")


def check_metric(tess: Tessellation, metric, mode: str):
    """Validate `metric` and `mode`; returns None when the metric is not used."""
    check_choice(mode, "mode", METRIC_MODES)
    if metric is None or mode == "none":
        return None
    if callable(metric):
        return metric
    if isinstance(metric, str):
        raise TypeError(
            f"`metric` must be None (Euclidean), a callable x (d,) -> g (d, d), or an (N, d, d) array; "
            f"got the string {metric!r}. For the Euclidean metric pass metric=None."
        )
    if not isinstance(metric, jax.core.Tracer):
        real_array(metric, "metric")
    g = jnp.asarray(metric)
    n, d = tess.points.shape
    if g.shape != (n, d, d):
        raise ValueError(
            f"`metric` must be None, a callable x (d,) -> g (d, d), or an array of shape "
            f"(N, d, d) = {(n, d, d)}; got an array of shape {g.shape}."
        )
    return g


def _with_mode(g, mode: str):
    return g * jnp.eye(g.shape[-1], dtype=g.dtype) if mode == "diagonal" else g


def _wrap(tess: Tessellation, x):
    """Positions moved back into the periodic box (a callable metric sees box coordinates)."""
    if not tess.periodic:
        return x
    assert tess.box_lengths is not None  # a periodic graph has its box
    return tess.box[0] + jnp.mod(x - tess.box[0], tess.box_lengths)


def _call_metric(metric: Callable, x):
    flat = x.reshape(-1, x.shape[-1])
    try:
        g = jax.vmap(metric)(flat)
    except jax.errors.JAXTypeError as err:  # float(), numpy or a Python branch on the traced x
        raise TypeError(
            f"the metric callable must be JAX-traceable, x (d,) -> g (d, d) with jax.numpy (no float(), "
            f"numpy calls or Python branches on x); tracing it failed: {type(err).__name__}: "
            f"{str(err).splitlines()[0]}"
        ) from None
    if jnp.issubdtype(g.dtype, jnp.complexfloating):
        raise TypeError(f"the metric callable must return a real floating-point matrix; it returned dtype {g.dtype}.")
    if g.shape[1:] != (x.shape[-1],) * 2:
        raise ValueError(
            f"the metric callable must map x (d,) to g (d, d) = {(x.shape[-1],) * 2}; it returned shape {g.shape[1:]}."
        )
    return g.reshape(x.shape + (x.shape[-1],))


def _quad(g, dx):
    """dx^T g dx over the last axes: written out up to d = WRITTEN_OUT_MAX_DIM (XLA fuses it),
    an einsum above."""
    d = dx.shape[-1]
    if d > WRITTEN_OUT_MAX_DIM:
        return jnp.einsum("...ij,...i,...j->...", g, dx, dx, precision=HIGHEST)
    return sum(g[..., i, j] * dx[..., i] * dx[..., j] for i in range(d) for j in range(d))


@takes_tessellation
@eqx.filter_jit
def metric_at_walkers(tess: Tessellation, metric, *, mode: str = "full"):
    """(N, d, d) metric at every walker (after `mode`), or None for Euclidean."""
    metric = check_metric(tess, metric, mode)
    if metric is None:
        return None
    g = _call_metric(metric, _wrap(tess, tess.points)) if callable(metric) else metric
    return _with_mode(g, mode)


@takes_tessellation
@eqx.filter_jit
def metric_defects(tess: Tessellation, metric) -> Bool[Array, " N"]:
    """Walkers where `metric` is not a valid metric tensor: the flag for callable metrics.

    The kernels check a concrete metric *array* on the host (symmetric, positive definite)
    and raise a `ValueError`. A *callable* metric is not checked there: that would evaluate
    it a second time in every call. Where it returns a matrix that is not symmetric
    positive definite, the kernels use it as given: only its symmetric part enters the
    quadratic forms, and an indefinite part gives NaN lengths, angles and curvatures at the
    edges it touches. Call this once (it is jittable) to find such walkers. (A concrete
    array is checked on entry like everywhere else, so it raises instead of returning a
    flag; under jit an array is flagged like a callable.)

    **Arguments:**

    - `tess`: any [`jaxgeom.Tessellation`][].
    - `metric`: None, (N, d, d) array, or callable x (d,) -> g (d, d).

    **Returns:**

    (N,) bool, True where g at the walker has a NaN or inf entry, is not symmetric (to
    100 eps) or is not positive definite; all False for the Euclidean metric.
    """
    return _defects(tess, metric, "full")


def _defects(tess: Tessellation, metric, mode: str):
    g = metric_at_walkers(tess, metric, mode=mode)
    if g is None:
        return jnp.zeros(tess.points.shape[0], bool)
    asym, indefinite = metric_defect_masks(g, jnp)
    return asym | indefinite | ~jnp.all(jnp.isfinite(g), axis=(1, 2))


_defect_count = eqx.filter_jit(lambda tess, metric, mode: jnp.sum(_defects(tess, metric, mode)))
# (id of the callable, id of the points) already checked by `warns_on_defective_metric`
_CHECKED_CALLABLES: dict[tuple[int, int], tuple] = {}


def warns_on_defective_metric(kernel):
    """Decorator for the public kernels that take `metric=`: a callable metric that is NaN, not
    symmetric or not positive definite at some walkers gives a `RuntimeWarning` naming how many
    and `jaxgeom.metric_defects`, once per callable and positions (a metric array is refused on
    entry instead). It costs one evaluation of g at the walkers, 4-19% of `ricci_scalar` or
    `viscous_force` with a Hessian metric (bench/README.md), nothing under a trace: there,
    call `metric_defects` yourself."""
    signature = inspect.signature(kernel)

    @functools.wraps(kernel)
    def call(tess, *args, **kwargs):
        out = kernel(tess, *args, **kwargs)
        bound = signature.bind_partial(tess, *args, **kwargs).arguments
        metric, mode = bound.get("metric"), bound.get("mode", "full")
        if not callable(metric) or mode == "none" or isinstance(tess.points, jax.core.Tracer):
            return out
        key = (id(metric), id(tess.points))
        refs = _CHECKED_CALLABLES.get(key)
        if refs is not None and refs[0]() is metric and refs[1]() is tess.points:
            return out
        count = int(_defect_count(tess, metric, mode))
        if count:
            warn_at_caller(
                f"{kernel.__name__}: the metric callable is NaN, not symmetric or not positive definite "
                f"at {count} of {tess.n_points} walkers, so results there are NaN or meaningless; "
                "jaxgeom.metric_defects(tess, metric) flags them.",
                RuntimeWarning,
            )
        if len(_CHECKED_CALLABLES) > 64:
            _CHECKED_CALLABLES.clear()
        try:  # weak references: the cache keeps neither the callable nor the positions alive
            _CHECKED_CALLABLES[key] = (weakref.ref(metric), weakref.ref(tess.points))
        except TypeError:
            pass
        return out

    return call


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def edge_lengths(tess: Tessellation, *, metric=None, mode: str = "full") -> Float[Array, "N K"]:
    """Metric length sqrt(dx^T g_edge dx) of every neighbour edge, aligned with `tess.neighbors`.

    **Arguments:**

    - `tess`: any [`jaxgeom.Tessellation`][] (Delaunay or k-NN).
    - `metric`: None, (N, d, d) array, or callable x -> g (see module docs).
    - `mode`: "none" (Euclidean), "diagonal" (diag(g) only) or "full".

    **Returns:**

    (N, K) lengths; 0 on padding slots.
    """
    return jnp.sqrt(edge_sq_lengths(tess, metric, mode=mode))


def edge_sq_lengths(tess: Tessellation, metric=None, *, mode: str = "full") -> Float[Array, "N K"]:
    """Squared metric edge lengths, aligned with `tess.neighbors` (0 on padding)."""
    metric = check_metric(tess, metric, mode)
    dx = neighbor_displacements(tess)
    mask = tess.neighbor_mask
    if metric is None:
        sq = dot(dx, dx)
    elif callable(metric):
        mid = jnp.where(mask[..., None], tess.points[:, None, :] + 0.5 * dx, tess.points[0])
        sq = _quad(_with_mode(_call_metric(metric, _wrap(tess, mid)), mode), dx)
    else:
        g = _with_mode(metric, mode)
        sq = 0.5 * (_quad(g[:, None], dx) + _quad(take_or_zero(g, tess.neighbors), dx))
    return jnp.where(mask, sq, 0.0)


def edge_pairs(d: int) -> tuple[tuple[int, int], ...]:
    """The (d + 1) d / 2 vertex pairs of a d-simplex, in a fixed order."""
    return tuple(itertools.combinations(range(d + 1), 2))


def simplex_sq_lengths(tess: Tessellation, metric=None, *, mode: str = "full") -> Float[Array, "S P"]:
    """Squared metric length of every simplex edge, pairs ordered as `edge_pairs(d)`."""
    return jnp.stack(simplex_sq_length_columns(tess, metric, mode=mode), axis=1)


def simplex_sq_length_columns(tess: Tessellation, metric=None, *, mode: str = "full") -> tuple:
    """`simplex_sq_lengths` as a tuple of P arrays (S,), the layout the angle kernels use."""
    metric = check_metric(tess, metric, mode)
    coords = simplex_coords(tess)  # d arrays (S, d + 1)
    pairs = edge_pairs(tess.dim)
    dx = [[c[:, b] - c[:, a] for c in coords] for a, b in pairs]  # per pair: d arrays (S,)
    if metric is None:
        return tuple(sum(x * x for x in v) for v in dx)
    if callable(metric):
        mid = jnp.stack([jnp.stack([0.5 * (c[:, a] + c[:, b]) for c in coords], -1) for a, b in pairs], 1)
        mid = jnp.where(tess.simplex_mask[:, None, None], mid, tess.points[0])
        dx_arr = jnp.stack([jnp.stack(v, -1) for v in dx], 1)
        sq = _quad(_with_mode(_call_metric(metric, _wrap(tess, mid)), mode), dx_arr)
        return tuple(sq[:, k] for k in range(len(pairs)))
    packed = _packed_table(_with_mode(metric, mode))
    g_verts = [[row[tess.simplices[:, v]] for row in packed] for v in range(tess.dim + 1)]
    return tuple(
        0.5 * (_quad_packed(g_verts[a], dx[k]) + _quad_packed(g_verts[b], dx[k])) for k, (a, b) in enumerate(pairs)
    )


def simplex_sq_lengths_with_references(tess: Tessellation, metric, *, mode: str = "full", hinge_edges=()):
    """(sq_g (S, P), [sq_ref (S, P) for each entry of `hinge_edges`]): squared simplex edge
    lengths in the edge metrics, and in each hinge's constant reference metric: the mean
    of the edge metrics of the edges listed in `hinge_edges[k]` (positions in
    `edge_pairs(d)`), or the metric at the simplex's vertex v for the entry -1 - v. Both use
    the same arithmetic, so equal metrics give bitwise equal lengths."""
    metric = check_metric(tess, metric, mode)
    coords = simplex_coords(tess)
    pairs = edge_pairs(tess.dim)
    dx = [[c[:, b] - c[:, a] for c in coords] for a, b in pairs]
    if callable(metric):
        mid = jnp.stack([jnp.stack([0.5 * (c[:, a] + c[:, b]) for c in coords], -1) for a, b in pairs], 1)
        mid = jnp.where(tess.simplex_mask[:, None, None], mid, tess.points[0])
        g = _with_mode(_call_metric(metric, _wrap(tess, mid)), mode)
        edge_g = [_packed_entries(g[:, k]) for k in range(len(pairs))]
        table = _packed_table(metric_at_walkers(tess, metric, mode=mode))
    else:
        table = _packed_table(_with_mode(metric, mode))
        edge_g = [[0.5 * (row[tess.simplices[:, a]] + row[tess.simplices[:, b]]) for row in table] for a, b in pairs]
    vertex_g = [[row[tess.simplices[:, v]] for row in table] for v in range(tess.dim + 1)]

    def reference(edges):
        if edges[0] < 0:
            return vertex_g[-1 - edges[0]]
        return [sum(edge_g[j][i] for j in edges) / len(edges) for i in range(len(table))]

    sq_g = jnp.stack([_quad_packed(edge_g[k], dx[k]) for k in range(len(pairs))], axis=1)
    return sq_g, [
        jnp.stack([_quad_packed(reference(edges), dx[k]) for k in range(len(pairs))], axis=1) for edges in hinge_edges
    ]


def _packed_entries(g):
    d = g.shape[-1]
    return [g[..., i, j] for i in range(d) for j in range(i, d)]


def _packed_table(g):
    """Upper-triangle entries of symmetric (N, d, d) tensors as d(d+1)/2 rows of length N + 1
    (a zero column for the sentinel): one 1-D gather per entry is the fast gather on CPU."""
    d = g.shape[-1]
    rows = [g[:, i, j] for i in range(d) for j in range(i, d)]
    return [jnp.concatenate([r, jnp.zeros((1,), r.dtype)]) for r in rows]


def _quad_packed(entries, dx):
    """dx^T g dx for g given by its packed upper-triangle entries; dx is a list of d arrays."""
    d = len(dx)
    out, k = 0.0, 0
    for i in range(d):
        for j in range(i, d):
            out = out + (1.0 if i == j else 2.0) * entries[k] * dx[i] * dx[j]
            k += 1
    return out


def sqrt_det_metric(tess: Tessellation, metric=None, *, mode: str = "full") -> Float[Array, " N"]:
    """sqrt(det g) at every walker (1 for Euclidean); NaN where det g <= 0."""
    g = metric_at_walkers(tess, metric, mode=mode)
    if g is None:
        return jnp.ones(tess.n_points, tess.points.dtype)
    # sqrt(det g) = s^(d/2) sqrt(det(g / s)) with s the largest entry of each g: det g alone
    # overflows or underflows (g = 1e200 I: det = 1e400) where the result is representable
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(g), axis=(1, 2)))
    scale = jnp.where(scale > 0, scale, 1.0)
    unit = g / scale[:, None, None]
    det = small_det(unit) if tess.dim <= 4 else jnp.linalg.det(unit)
    return jnp.where(det > 0, jnp.sqrt(jnp.where(det > 0, det, 1.0)) * jnp.sqrt(scale) ** tess.dim, jnp.nan)


@takes_tessellation
@warns_on_defective_metric
@eqx.filter_jit
def riemannian_volumes(tess: Tessellation, *, metric=None, mode: str = "full", volumes=None) -> Float[Array, " N"]:
    """Riemannian cell volumes V_i sqrt(det g(x_i)).

    **Arguments:**

    - `tess`: a Delaunay tessellation.
    - `metric`, `mode`: as in [`jaxgeom.edge_lengths`][].
    - `volumes`: Euclidean cell volumes to reuse; default `voronoi_volumes(tess)`.

    **Returns:**

    (N,) volumes; NaN for unbounded cells.
    """
    base = voronoi_volumes(tess) if volumes is None else volumes
    unbounded = jnp.isnan(base)  # keep NaN out of the product so gradients stay finite
    return jnp.where(unbounded, jnp.nan, jnp.where(unbounded, 0.0, base) * sqrt_det_metric(tess, metric, mode=mode))


def riemannian_mean(values, weights, mask=None) -> Float[Array, ""]:
    """Weighted mean sum(w O) / sum(w) over walkers in `mask` with finite O and w.

    Pass `weights=riemannian_volumes(...)` and `mask=tess.interior` for the
    Riemannian average of an observable over tier-2 walkers.
    """
    values, weights = walker_values(values, "values"), walker_values(weights, "weights", nonnegative=True)
    if values.shape != weights.shape:
        raise ValueError(
            f"`values` and `weights` must have the same shape (N,); got {values.shape} and {weights.shape}."
        )
    check_walker_mask(mask, "mask", values.shape)
    ok = jnp.isfinite(values) & jnp.isfinite(weights)
    if mask is not None:
        ok = ok & mask
    w = jnp.where(ok, weights, 0.0)
    return jnp.sum(w * jnp.where(ok, values, 0.0)) / jnp.sum(w)


def eigh(m):
    """Symmetric eigendecomposition: `small_eigh` (no LAPACK call) up to d = 4."""
    return small_eigh(m) if m.shape[-1] in JACOBI_SWEEPS else jnp.linalg.eigh(m)


class HessianParts(NamedTuple):
    """What a `hessian_metric` callable is made of (its attribute `hessian_parts`)."""

    fitness: Callable
    eps_sigma: Any  # float, or a traced scalar
    floor: str


def hessian_parts(metric) -> HessianParts | None:
    """The parts of a callable returned by `hessian_metric`, or None for any other metric."""
    parts = getattr(metric, "hessian_parts", None)
    return parts if isinstance(parts, HessianParts) else None


def hessian_metric(fitness: Callable, eps_sigma, *, floor: str = "clip") -> Callable:
    r"""The Hessian metric $g(x) = \operatorname{floor}(H(x)) + \epsilon_\Sigma I$ of a fitness $V$,
    $H = \nabla^2 V$.

    **Arguments:**

    - `fitness`: JAX function x (d,) -> scalar V(x); H = jax.hessian(fitness).
    - `eps_sigma`: spectral floor eps_Sigma >= 0 (may be a traced value, e.g.
      under `jax.grad`).
    - `floor`: "clip" maps eigenvalues lambda -> max(lambda, 0) + eps_Sigma, so g = H +
      eps_Sigma I wherever H is positive semi-definite. "softabs" maps lambda ->
      lambda coth(lambda / eps_Sigma) (SoftAbs with alpha = 1/eps_Sigma): smooth, >= eps_Sigma, and
      ~|lambda| for |lambda| >> eps_Sigma.

    **Returns:**

    A callable x (d,) -> g (d, d), usable as `metric=` everywhere. Its derivatives in x and in
    eps_Sigma, of every order, are those of the floor as a function of the matrix (Daleckii and
    Krein's divided differences, `base._simplex.spectral_function`): finite and right where H
    is indefinite or has repeated eigenvalues. At an eigenvalue exactly 0 the clip floor has
    a kink; its derivative there is the mean of the two one-sided ones (what central
    differences give).
    """
    if not callable(fitness):
        raise TypeError(f"`fitness` must be a JAX function x (d,) -> scalar V(x); got {type(fitness).__name__}.")
    check_choice(floor, "floor", HESSIAN_FLOORS)
    check_nonnegative(eps_sigma, "eps_sigma")  # a spectral floor
    if isinstance(eps_sigma, (int, float)) and eps_sigma == 0:
        warn_at_caller(
            "hessian_metric: eps_sigma = 0 leaves g = floor(H) singular wherever the Hessian has an "
            "eigenvalue <= 0 (a zero metric on a linear landscape); lengths, curvatures and metric "
            "weights are NaN there. Give eps_sigma > 0 (the spectral floor eps_Sigma)."
        )
    if isinstance(eps_sigma, (int, float)):  # the same callable for the same arguments: no recompilation
        return _cached_hessian_metric(fitness, float(eps_sigma), floor)
    return _hessian_metric(fitness, eps_sigma, floor)


@functools.lru_cache(maxsize=64)
def _cached_hessian_metric(fitness: Callable, eps_sigma: float, floor: str) -> Callable:
    return _hessian_metric(fitness, eps_sigma, floor)


def _hessian_metric(fitness: Callable, eps_sigma, floor: str, eigh: Callable = eigh) -> Callable:
    """The metric callable; `eigh` is the eigensolver of the floor (`small_eigh` up to d = 4;
    `metric_curvature` passes LAPACK's). The floor is a `spectral_function`: its derivatives of
    every order come from divided differences of the floor, never from the eigensolver's."""
    hess = jax.hessian(fitness)

    def clip(x):
        h = hess(x)
        eye = jnp.eye(h.shape[-1], dtype=h.dtype)
        # exactly 0 where H is positive semi-definite, so g = H + eps_Sigma I there
        return h + eps_sigma * eye + spectral_function(_clip_correction, eigh, h, jnp.zeros((), h.dtype))

    def softabs(x):
        h = hess(x)
        return spectral_function(_softabs, eigh, h, jnp.asarray(eps_sigma, h.dtype))

    metric = clip if floor == "clip" else softabs
    # what `metric_curvature` reads to use the Hessian-geometry formulas (g = Hess(V + eps |x|^2 / 2))
    metric.hessian_parts = HessianParts(fitness, eps_sigma, floor)  # type: ignore[attr-defined]  # a function's attribute
    return metric


def _clip_correction(lam, _):
    """What the clip floor adds to an eigenvalue: max(-lambda, 0) (slope 1/2 at the kink)."""
    return jnp.maximum(-lam, 0.0)


def _softabs(lam, eps_sigma):
    """lambda coth(lambda / eps_Sigma), its Taylor series eps_Sigma + lambda^2 / (3 eps_Sigma) near 0."""
    small = jnp.abs(lam) < 1e-3 * eps_sigma
    safe = jnp.where(small, 1.0, lam)
    return jnp.where(small, eps_sigma + lam**2 / (3.0 * eps_sigma), safe / jnp.tanh(safe / eps_sigma))


@takes_tessellation
@eqx.filter_jit
def emergent_metric(tess: Tessellation, *, eps_reg: float = 1e-5) -> Float[Array, "N d d"]:
    """Emergent metric g_i = inverse(C_i + eps_reg (tr C_i / d) I).

    C_i = mean over walker i's neighbours of dx dx^T, padding ignored. The
    regulariser is relative to the local scale, so the metric is scale covariant
    (g -> g / s^2 under x -> s x). Walkers without neighbours get NaN.
    """
    check_nonnegative(eps_reg, "eps_reg")
    degree = tess.degree
    d = tess.dim
    dx = neighbor_displacements_for_sums(tess)
    if d > WRITTEN_OUT_MAX_DIM:
        cov = jnp.einsum("nki,nkj->nij", dx, dx, precision=HIGHEST)
    else:
        cov = jnp.stack([jnp.stack([jnp.sum(dx[i] * dx[j], axis=1) for j in range(d)], -1) for i in range(d)], -2)
    cov = cov / jnp.maximum(degree, 1)[:, None, None].astype(cov.dtype)
    reg = eps_reg * jnp.trace(cov, axis1=1, axis2=2) / d
    c = cov + reg[:, None, None] * jnp.eye(d, dtype=cov.dtype)
    if d <= 4:
        det = small_det(c)
        g = small_adjugate(c) / jnp.where(det != 0, det, 1.0)[:, None, None]
        g = jnp.where((det != 0)[:, None, None], g, jnp.nan)
    else:
        g = jnp.linalg.inv(c)
    return jnp.where((degree > 0)[:, None, None], 0.5 * (g + jnp.swapaxes(g, 1, 2)), jnp.nan)
