"""Swarm observables: one table, name -> (function of a `_View`, whether it needs cells).

An observable is a scalar of the swarm state entering a step (and of the final state),
recorded by `jaxgeom.simulate` in its history. To add one, add a function of `_View`
and one row of `OBSERVABLE_TABLE`; "geometric" rows need Voronoi cells (they refresh the
cell volumes and are NaN on a k-NN graph).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._simplex import safe_sqrt
from ..geometry._cells import shape_distortion, volume_distortion
from ..geometry._curvature import ricci_resolution, ricci_scalar
from ..geometry._metric import hessian_metric, riemannian_mean, riemannian_volumes
from ..geometry._metric_curvature import DEFAULT_PROBES, EXACT_HESSIAN_MAX_DIM, metric_curvature
from ..geometry._scutoids import neighbour_changes
from ..geometry._weights import weights_on_graph
from ..tessellation._graph import neighbor_displacements
from ._dynamics import (
    ScutoidTrace,
    SwarmParams,
    SwarmState,
    cell_volumes,
    current_nu,
    kernel_volumes,
    metric_field,
    viscous_length,
)


def _finite_mean(values, mask):
    ok = mask & jnp.isfinite(values)
    return jnp.sum(jnp.where(ok, values, 0.0)) / jnp.sum(ok).astype(values.dtype)


def _variance(v, weights):
    """The weighted variance of the velocity per component: tr Cov_w(v) / d (T at equilibrium)."""
    mean = jnp.sum(weights[:, None] * v, axis=0) / jnp.sum(weights)
    return jnp.sum(weights * jnp.mean((v - mean) ** 2, axis=1)) / jnp.sum(weights)


class _View(eqx.Module):
    """What an observable reads: the state with its cell volumes refreshed (`new`; its
    `previous_volumes` are those of the step before, for the expansion)."""

    fitness: Callable | None = eqx.field(static=True)  # None: a recorded trajectory without a landscape
    params: SwarmParams
    new: SwarmState
    progress: Float[Array, ""]


def _observed_metric(s: _View):
    """The Hessian metric at the observed walkers, with the current eps_Sigma; None (Euclidean)
    for a recorded trajectory analysed without a landscape (`analyze_trajectory`)."""
    if s.fitness is None:
        return None
    return metric_field(s.fitness, s.params, s.params.eps_sigma * s.new.eps_factor, s.new.positions)


def _tier2_riemannian_mean(kernel):
    """The observable sum_i f_i V_i sqrt(det g_i) / sum_i V_i sqrt(det g_i) over tier-2 walkers,
    f = kernel(tess, metric=g, volumes=V) in the Hessian metric g."""

    def observable(s: _View):
        g = _observed_metric(s)
        volumes = kernel_volumes(s.new.volumes)
        values = kernel(s.new.tess, metric=g, volumes=volumes)
        return riemannian_mean(values, riemannian_volumes(s.new.tess, metric=g, volumes=volumes), s.new.interior)

    return observable


def _mean_expansion(s: _View):
    """d ln(sum_i V_i) / dt over the walkers tier 2 at both steps: the expansion of the region
    their cells cover, the volume-weighted mean of the cells' expansion.

    Cells change by ~100% per step under the noise, and the plain mean of (V_i' - V_i) /
    (V_i dt) is then dominated by that jitter (E[V'/V] > 1 by Jensen's inequality), while
    the cells' exchanges of volume cancel in the sum. Clones stay in the sum: a walker that
    jumps to its companion leaves its old cell to its old neighbours and takes part of the
    companion's neighbours' cells, so the covered region is unchanged; leaving clones (and
    their new neighbours) out counted the cells they vacated as growth (+3..+7 per unit time
    on the contracting default run, now -0.3 on average). Exact under x -> s x: d ln(s^d)/dt."""
    new = s.new
    before, after = new.previous_volumes, new.volumes
    valid = (
        new.previous_interior & new.interior & jnp.isfinite(before) & jnp.isfinite(after) & (before > 0) & (after > 0)
    )
    total_before = jnp.sum(jnp.where(valid, before, 0.0))
    total_after = jnp.sum(jnp.where(valid, after, 0.0))
    ok = (total_before > 0) & (new.volumes_step == new.step)
    ratio = jnp.where(ok, total_after, 1.0) / jnp.where(ok, total_before, 1.0)
    return jnp.where(ok, jnp.log(ratio) / s.params.dt, jnp.nan)


def _mean_metric_curvature(s: _View):
    """The exact Ricci scalar of the Hessian metric (`metric_curvature`), averaged over walkers
    in the Riemannian measure: weights V_i sqrt(det g_i) with V_i the Voronoi volume (tier-2
    walkers of a Delaunay graph) or the k-NN volume r_k(i)^d (k-NN graph: 1 / density up to a
    constant), in log space so that d = 100 does not overflow. The exact Hessian form up to
    d = EXACT_HESSIAN_MAX_DIM, the stochastic one (DEFAULT_PROBES probe pairs, a key derived
    from the state's) above; walkers it flags (NaN) drop out of the mean."""
    tess, eps = s.new.tess, s.params.eps_sigma * s.new.eps_factor
    assert s.fitness is not None  # refused without a landscape (analyze_trajectory); simulate always has one
    metric = hessian_metric(s.fitness, eps, floor=s.params.floor)
    d = tess.dim
    probes = None if d <= EXACT_HESSIAN_MAX_DIM else DEFAULT_PROBES
    key = jax.random.fold_in(s.new.key, 33) if probes else None
    values = metric_curvature(metric, s.new.positions, probes=probes, key=key)
    log_w, ok = riemannian_log_weights(tess, _observed_metric(s))
    ok = ok & s.new.alive & jnp.isfinite(values)
    return weighted_mean_from_logs(values, log_w, ok)


def riemannian_log_weights(tess, g):
    """(log w, usable): log of V_i sqrt(det g_i), V_i the Voronoi volume (tier-2 walkers of a
    Delaunay graph) or the k-NN volume r_k(i)^d, r_k the longest neighbour edge (a k-NN graph:
    1 / density up to a constant factor). Logs: r^d and det g overflow at d = 100."""
    log_sqrt_det = jnp.linalg.slogdet(g)[1] / 2
    if tess.simplices is None:
        r = jnp.max(safe_sqrt(jnp.sum(neighbor_displacements(tess) ** 2, axis=-1)), axis=1)
        log_volume, ok = tess.dim * jnp.log(jnp.where(r > 0, r, 1.0)), r > 0
    else:
        volumes, interior = cell_volumes(tess)
        log_volume, ok = jnp.log(jnp.where(volumes > 0, volumes, 1.0)), interior & (volumes > 0)
    log_w = log_volume + log_sqrt_det
    return log_w, ok & jnp.isfinite(log_w)


def weighted_mean_from_logs(values, log_w, ok):
    """sum w O / sum w over `ok`, the weights given by their logs (shifted by their maximum)."""
    log_w = jnp.where(ok, log_w, -jnp.inf)
    w = jnp.exp(log_w - jax.lax.stop_gradient(jnp.max(jnp.where(ok, log_w, -1e30))))
    return jnp.sum(jnp.where(ok, w * values, 0.0)) / jnp.sum(w)


def _scutoid_share(s: _View, k: int):
    """counts[k] / counts[0] of the state's scutoid trace: NaN where no walker was compared."""
    counts = s.new.scutoid_trace.counts
    dtype = s.new.positions.dtype
    return jnp.where(counts[0] > 0, counts[k].astype(dtype) / jnp.maximum(counts[0], 1).astype(dtype), jnp.nan)


def _degree_weighted_variance(s: _View):
    g = _observed_metric(s) if s.params.weights.startswith("metric") else None
    w = weights_on_graph(
        s.new.tess, s.params.weights, length_scale=viscous_length(s.params, s.new, s.new.tess), metric=g
    )
    return _variance(s.new.velocities, jnp.sum(w, axis=1))


class Observable(NamedTuple):
    fn: Callable  # _View -> scalar
    geometric: bool = False  # needs Voronoi cells: NaN on a k-NN graph
    opt_in: bool = False  # recorded only when named in `observe` (not in the default OBSERVABLES)


OBSERVABLE_TABLE: dict[str, Observable] = {
    "mean_fitness": Observable(lambda s: _finite_mean(s.new.fitness, s.new.alive)),
    "best_fitness": Observable(lambda s: jnp.min(jnp.where(s.new.alive, s.new.fitness, jnp.inf))),
    "velocity_variance": Observable(lambda s: _variance(s.new.velocities, jnp.ones_like(s.new.fitness))),
    "degree_weighted_variance": Observable(_degree_weighted_variance),
    "mean_ricci": Observable(_tier2_riemannian_mean(ricci_scalar), True),
    # the smallest |mean_ricci| the dtype resolves: `ricci_resolution` averaged like R
    "ricci_resolution": Observable(_tier2_riemannian_mean(ricci_resolution), True),
    "volume_distortion": Observable(lambda s: volume_distortion(s.new.tess, s.new.volumes), True),
    "mean_shape_distortion": Observable(lambda s: _finite_mean(shape_distortion(s.new.tess), s.new.interior), True),
    "mean_expansion": Observable(_mean_expansion, True),
    "n_clones": Observable(lambda s: jnp.sum(s.new.cloned).astype(s.new.fitness.dtype)),
    "nu": Observable(lambda s: current_nu(s.params, s.progress)),
    "eps_sigma": Observable(lambda s: s.params.eps_sigma * s.new.eps_factor),
    # the exact curvature the Regge proxy "mean_ricci" approximates; any graph, any d
    "mean_metric_curvature": Observable(_mean_metric_curvature, opt_in=True),
    # the scutoids of the step that led to the state (`jaxgeom.scutoids`): the fractions of the
    # walkers tier 2 at both steps whose cells are prisms, simple or complex scutoids, and
    # their mean neighbour change lost + gained; NaN at a state without the step before
    "prism_fraction": Observable(lambda s: _scutoid_share(s, 1), True, True),
    "simple_scutoid_fraction": Observable(lambda s: _scutoid_share(s, 2), True, True),
    "complex_scutoid_fraction": Observable(lambda s: _scutoid_share(s, 3), True, True),
    "mean_neighbor_change": Observable(lambda s: _scutoid_share(s, 4), True, True),
}
SCUTOID_OBSERVABLES = ("prism_fraction", "simple_scutoid_fraction", "complex_scutoid_fraction", "mean_neighbor_change")
OBSERVABLES = tuple(name for name, row in OBSERVABLE_TABLE.items() if not row.opt_in)  # the default set
ALL_OBSERVABLES = tuple(OBSERVABLE_TABLE)


def observe_state(fitness, params: SwarmParams, state: SwarmState, progress, observe: tuple[str, ...]):
    """Refresh the state's cell volumes on its current graph and measure `observe`.

    Returns `(state, {name: scalar})`. Geometric observables are NaN on a k-NN graph.
    """
    new = refresh_cells(params, state, observe)
    return new, measure(fitness, params, new, progress, observe)


def needs_cells(params: SwarmParams, observe: tuple[str, ...]) -> bool:
    """Whether the step (volume weighting) or an observable of `observe` needs the cells."""
    return params.volume_weighting or any(OBSERVABLE_TABLE[name].geometric for name in observe)


def reads_tiers(params: SwarmParams, observe: tuple[str, ...]) -> bool:
    """Whether a step or the observables `observe` read the graph's tiers (the cells, the
    scutoid trace); where not, `simulate` builds its graphs without them and computes them
    only for the state it returns (`deferred_tiers`)."""
    return needs_cells(params, observe) or any(name in SCUTOID_OBSERVABLES for name in observe)


def refresh_cells(params: SwarmParams, state: SwarmState, observe: tuple[str, ...]) -> SwarmState:
    """The state with its cell volumes and tiers on its current graph, where the step
    (volume weighting) or an observable needs them; else the state unchanged.

    The volumes measured before move to `previous_volumes` when they belong to the step
    before (NaN otherwise); a state already measured at its step keeps its fields, so a
    continued `simulate` call compares the same two steps as one uninterrupted call. The
    scutoid trace (`refresh_scutoids`) is refreshed the same way when a scutoid observable
    is asked for."""
    if any(name in SCUTOID_OBSERVABLES for name in observe):
        state = refresh_scutoids(state)
    if not needs_cells(params, observe):
        return state
    volumes, interior = cell_volumes(state.tess)
    measured = state.volumes_step == state.step
    adjacent = state.volumes_step == state.step - 1
    previous = jnp.where(measured, state.previous_volumes, jnp.where(adjacent, state.volumes, jnp.inf))
    previous_interior = jnp.where(measured, state.previous_interior, adjacent & state.interior)
    return eqx.tree_at(
        cell_fields,
        state,
        (volumes, interior, previous, previous_interior, state.step.astype(jnp.int32), state.scutoid_trace),
    )


def cell_fields(state: SwarmState) -> tuple:
    """The fields of a state that `refresh_cells` sets."""
    return (
        state.volumes,
        state.interior,
        state.previous_volumes,
        state.previous_interior,
        state.volumes_step,
        state.scutoid_trace,
    )


def refresh_scutoids(state: SwarmState) -> SwarmState:
    """The scutoid counts of the step from the trace's graph to the state's (when the trace
    holds the step before; zero counts otherwise), and the state's graph as the new trace. A
    state already traced at its step keeps its trace (a continued `simulate` call)."""
    trace, tess = state.scutoid_trace, state.tess
    if tess.simplices is None or trace.neighbors.shape[1] == 0:  # k-NN: no cells (NaN); not prepared
        return state
    n = tess.n_points
    parents = trace.parents
    shared, lost, gained = neighbour_changes(trace.neighbors[parents], tess.neighbors, n)
    walkers = trace.interior[parents] & tess.interior & (trace.step == state.step - 1)
    kinds = [(lost == 0) & (gained == 0), (lost + gained > 0) & (lost <= 1) & (gained <= 1), (lost > 1) | (gained > 1)]
    counts = jnp.stack(
        [jnp.sum(walkers)]
        + [jnp.sum(walkers & kind) for kind in kinds]
        + [jnp.sum(jnp.where(walkers, lost + gained, 0))]
    ).astype(jnp.int32)
    width = trace.neighbors.shape[1]
    rows = (
        tess.neighbors[:, :width]
        if width <= tess.neighbors.shape[1]
        else jnp.pad(tess.neighbors, ((0, 0), (0, width - tess.neighbors.shape[1])), constant_values=n)
    )
    fresh = ScutoidTrace(parents, rows, tess.interior, state.step.astype(jnp.int32), counts)
    kept = jax.tree_util.tree_map(lambda a, b: jnp.where(trace.step == state.step, a, b), trace, fresh)
    return eqx.tree_at(lambda s: s.scutoid_trace, state, kept)


def prepare_scutoid_trace(state: SwarmState, observe: tuple[str, ...]) -> SwarmState:
    """A state whose trace rows are as wide as its graph's, when a scutoid observable is asked
    for (a new swarm's trace has none; a grown graph widens them), padded with the sentinel N."""
    width, k = state.scutoid_trace.neighbors.shape[1], state.tess.neighbors.shape[1]
    if not any(name in SCUTOID_OBSERVABLES for name in observe) or width >= k or state.tess.simplices is None:
        return state
    rows = jnp.pad(state.scutoid_trace.neighbors, ((0, 0), (0, k - width)), constant_values=state.tess.n_points)
    return eqx.tree_at(lambda s: s.scutoid_trace.neighbors, state, rows)


def measure(fitness, params: SwarmParams, new: SwarmState, progress, observe: tuple[str, ...]):
    """{name: scalar} of `new` (a state from `refresh_cells`)."""
    view = _View(fitness, params, new, jnp.asarray(progress))
    dtype = new.positions.dtype
    nan = jnp.asarray(jnp.nan, dtype)
    geometric = new.tess.simplices is not None
    return {
        name: nan
        if OBSERVABLE_TABLE[name].geometric and not geometric
        else jnp.asarray(OBSERVABLE_TABLE[name].fn(view), dtype)
        for name in observe
    }
