"""Swarm dynamics: SwarmState / SwarmParams pytrees, one Langevin + viscous + cloning step.

The integrator is the symmetric splitting B A V O V A B of underdamped Langevin
dynamics (BAOAB of Leimkuhler and Matthews with the viscous force inside):

- B: v += dt/2 * (-grad V(x))            (fitness force by autodiff)
- A: x += dt/2 * v
- V: v += dt/2 * F_visc(v)               (explicit; convex combination when nu dt <= 2)
- O: v = c v + sqrt(T (1 - c^2)) sigma xi,  c = exp(-gamma dt), sigma sigma^T = D
- V, A, B as above.

D = I, or D = g^-1 with g the Hessian metric (the adaptive gas, `anisotropic=True`);
sigma = L^-T for the Cholesky factor g = L L^T. With position-dependent D the O
step omits the Ito drift T div D, so the adaptive gas samples exp(-V/T) only up
to that term (as the chapter's algorithm does).

Cloning (the Fractal Gas rule): each walker picks a random companion c and gets
the virtual reward VR = r^a d^b from its relativized reward r (from -V) and
relativized distance d to another random walker. Walker i clones with
probability clone_rate * clip((VR_c - VR_i) / VR_i, 0, 1), taking the
companion's position (plus a jitter of clone_jitter mean spacings) and velocity.
Dead walkers (non-finite fitness) always clone.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, PRNGKeyArray

from ..base._checks import check_choice, check_nonnegative, check_number, check_positive, real_array
from ..base._simplex import safe_sqrt, small_cholesky
from ..geometry._forces import (
    VISCOUS_WEIGHTS,
    apply_viscous,
    normalize_rows,
    weights_to_normalize,
    with_volume_weights,
)
from ..geometry._metric import HESSIAN_FLOORS, eigh, hessian_metric
from ..geometry._volumes import voronoi_volumes
from ..geometry._weights import DEFAULT_ALPHA, mean_nearest_neighbor_distance
from ..tessellation._graph import Tessellation

COND_LIMIT = 1e6  # chapter: raise eps_Sigma 10x when cond(g) exceeds this
EPS_SIGMA_RAISE = 10.0


def _param(name: str, default):
    """A differentiable scalar field; strings, complex numbers and ragged lists get a TypeError
    naming the field (before JAX's conversion error)."""

    def convert(value):
        if value is None or isinstance(value, jax.core.Tracer):
            return value
        real_array(value, name)
        return jnp.asarray(value)

    return eqx.field(converter=convert, default=default)


class SwarmParams(eqx.Module):
    """Physical parameters of the swarm (float fields are differentiable leaves).

    **Fields:**

    - `dt` (> 0), `gamma` (friction >= 0), `temperature` (>= 0), `nu` (viscous
      coupling >= 0), `eps_sigma` (Hessian-metric floor >= 0).
    - `length_scale`: viscous kernel width l; None = `alpha` times the mean
      nearest-neighbour distance, measured on the initial swarm (or every step
      with `adapt_length_scale=True`).
    - `alpha`: factor of that rule (chapter: 2-5; default 3).
    - `clone_rate` in [0, 1]: scales the cloning probability; `clone_jitter`:
      cloned walkers land this many mean spacings from their companion.
    - `reward_power`, `distance_power`: exponents a, b of the virtual reward.
    - `nu_initial`: start of the nu annealing schedule (chapter: 0.01 -> nu).
    - static: `weights` (the viscous weight rule, `VISCOUS_WEIGHTS`), `volume_weighting`,
      `anisotropic` (D = g^-1), `cloning`, `anneal_nu` (nu linear from
      `nu_initial` to `nu` over the run), `adapt_length_scale`,
      `adapt_eps_sigma` (x10 whenever max cond(g) > 1e6), `floor` ("clip"/"softabs").
    """

    dt: Float[Array, ""] = _param("dt", 0.01)
    gamma: Float[Array, ""] = _param("gamma", 1.0)
    temperature: Float[Array, ""] = _param("temperature", 0.1)
    nu: Float[Array, ""] = _param("nu", 0.1)
    eps_sigma: Float[Array, ""] = _param("eps_sigma", 0.1)
    length_scale: Float[Array, ""] | None = _param("length_scale", None)
    alpha: Float[Array, ""] = _param("alpha", DEFAULT_ALPHA)
    clone_rate: Float[Array, ""] = _param("clone_rate", 0.1)
    clone_jitter: Float[Array, ""] = _param("clone_jitter", 0.1)
    reward_power: Float[Array, ""] = _param("reward_power", 1.0)
    distance_power: Float[Array, ""] = _param("distance_power", 1.0)
    nu_initial: Float[Array, ""] = _param("nu_initial", 0.01)
    weights: str = eqx.field(static=True, default="kernel")
    volume_weighting: bool = eqx.field(static=True, default=False)
    anisotropic: bool = eqx.field(static=True, default=False)
    cloning: bool = eqx.field(static=True, default=True)
    anneal_nu: bool = eqx.field(static=True, default=False)
    adapt_length_scale: bool = eqx.field(static=True, default=False)
    adapt_eps_sigma: bool = eqx.field(static=True, default=False)
    floor: str = eqx.field(static=True, default="clip")

    def __check_init__(self):
        check_choice(self.weights, "weights", VISCOUS_WEIGHTS)
        check_choice(self.floor, "floor", HESSIAN_FLOORS)
        for name in ("gamma", "temperature", "nu", "eps_sigma", "clone_rate", "nu_initial"):
            check_nonnegative(getattr(self, name), name)
        for name in ("dt", "alpha", "length_scale", "clone_jitter"):  # jitter 0 would duplicate walkers
            check_positive(getattr(self, name), name)
        check_number(self.clone_rate, "clone_rate", low=0, high=1, hint=" (a probability scale)")
        for name in ("reward_power", "distance_power"):  # exponents of the virtual reward
            check_nonnegative(getattr(self, name), name)
        if self.anisotropic:
            check_positive(
                self.eps_sigma,
                "eps_sigma",
                " with anisotropic=True (the noise D = g^-1 needs a "
                "positive definite metric g = floor(H) + eps_Sigma I)",
            )

    @property
    def needs_metric(self) -> bool:
        return self.anisotropic or self.weights.startswith("metric") or self.adapt_eps_sigma


class ScutoidTrace(eqx.Module):
    """What the scutoid observables compare a state with (`SwarmState.scutoid_trace`).

    **Fields:** `parents` (N,) int32, the clone parent of each walker in the latest step (the
    walker itself where it did not clone); `neighbors` (N, K') int32, the neighbour rows of the
    graph at step `step` (K' = 0 until a run observes scutoids, then the graph's width);
    `interior` (N,) tier 2 then; `step` int32 (-1: none); `counts` (5,) int32 of the latest
    comparison: walkers compared (tier 2 at both steps), prisms, simple and complex scutoids,
    and their summed neighbour changes lost + gained (`jaxgeom.scutoids`)."""

    parents: Int[Array, " N"]
    neighbors: Int[Array, "N K"]
    interior: Bool[Array, " N"]
    step: Int[Array, ""]
    counts: Int[Array, 5]


def empty_scutoid_trace(n: int) -> ScutoidTrace:
    """(host) A trace with no step recorded yet."""
    return ScutoidTrace(
        *map(
            jnp.asarray,
            (
                np.arange(n, dtype=np.int32),
                np.zeros((n, 0), np.int32),
                np.zeros(n, bool),
                np.int32(-1),
                np.zeros(5, np.int32),
            ),
        )
    )


class SwarmState(eqx.Module):
    """Everything that evolves, as one pytree (carried through `jax.lax.scan`).

    **Fields:**

    - `positions`, `velocities`: (N, d); `fitness`: (N,) V at the positions;
      `force`: (N, d) -grad V there (reused by the next step's first kick).
    - `alive`: (N,) finite fitness; `cloned`: (N,) cloned in the latest step.
    - `volumes`: (N,) Voronoi volumes at the positions of step `volumes_step` (the
      latest observation; +inf where no finite volume is known: unbounded cells, every
      walker of a k-NN graph, before the first observation); `interior`: (N,) tier 2 at
      that time. They serve the volume weighting. (+inf, not the kernels' NaN: a state
      carries no NaN unless the swarm diverged, so `jax.debug_nans` finds real ones.)
    - `previous_volumes`, `previous_interior`: the same one step earlier (+inf / False
      when that step was not observed): the Raychaudhuri expansion compares them with
      `volumes`. They travel with the state, so a `simulate` call that continues another
      measures the expansion of its first step as one uninterrupted call does.
    - `volumes_step`: int32 step at which `volumes` were measured (-1: never).
    - `key`: PRNG key; `tess`: the current tessellation (its `points` follow
      `positions` between rebuilds); `step`: int32 step count.
    - `spacing0`: mean nearest-neighbour distance of the initial swarm.
    - `eps_factor`: current eps_Sigma / params.eps_sigma (10^raises).
    - `status`: int32 bit flags of problems met so far (`REBUILD_FAILED`: a traced
      rebuild could not triangulate the walkers and kept the previous graph).
    - `n_separated`: walkers moved apart because they coincided for the triangulator (cloning
      with a tiny jitter: Qhull merges walkers closer than its precision, CDT and shull only
      exact duplicates); each is moved by `SEPARATION` mean spacings or the dtype's resolution.
    - `n_triangulator_fallbacks`: host triangulations in which `triangulator` failed (raised,
      or its result failed the check) and Qhull built the graph instead.
    - `scutoid_trace`: the graph the scutoid observables compare with and the latest step's
      clone parents (`ScutoidTrace`).
    - `triangulator`: static, the host triangulator of the Delaunay rebuilds ("qhull",
      "cdt", "shull"; `init_swarm` resolves "auto").
    """

    positions: Float[Array, "N d"]
    velocities: Float[Array, "N d"]
    fitness: Float[Array, " N"]
    force: Float[Array, "N d"]
    alive: Bool[Array, " N"]
    cloned: Bool[Array, " N"]
    volumes: Float[Array, " N"]
    interior: Bool[Array, " N"]
    previous_volumes: Float[Array, " N"]
    previous_interior: Bool[Array, " N"]
    volumes_step: Int[Array, ""]
    key: PRNGKeyArray
    tess: Tessellation
    step: Int[Array, ""]
    spacing0: Float[Array, ""]
    eps_factor: Float[Array, ""]
    status: Int[Array, ""]
    n_separated: Int[Array, ""]
    n_triangulator_fallbacks: Int[Array, ""]
    scutoid_trace: ScutoidTrace
    triangulator: str = eqx.field(static=True, default="qhull")


# Health bits: the state entering a step is checked before it moves (`health`).
NONFINITE, RUNAWAY, ALL_DEAD, REBUILD_FAILED, OVERFLOWED_GRAPH = 1, 2, 4, 8, 16
# A walker farther than this many initial swarm radii (N^(1/d) x the initial mean spacing)
# from the swarm's mean position counts as diverged.
RUNAWAY_RADII = 1e6


def runaway_radius(state: SwarmState):
    n, d = state.positions.shape
    return RUNAWAY_RADII * state.spacing0 * n ** (1.0 / d)


def health(state: SwarmState):
    """Bit flags (int32) of a state: non-finite positions/velocities, runaway walkers,
    no walker with a finite fitness, a graph that outgrew its capacity (a traced rebuild
    then keeps the old graph), and any problem recorded in `state.status`."""
    x, v = state.positions, state.velocities
    finite = jnp.all(jnp.isfinite(x)) & jnp.all(jnp.isfinite(v))
    centre = jnp.mean(x, axis=0)
    far = jnp.max(jnp.sum((x - centre) ** 2, axis=1)) > runaway_radius(state) ** 2
    flags = (
        jnp.where(finite, 0, NONFINITE)
        | jnp.where(far, RUNAWAY, 0)
        | jnp.where(jnp.any(state.alive), 0, ALL_DEAD)
        | jnp.where(state.tess.overflow, OVERFLOWED_GRAPH, 0)
    )
    return (flags | state.status).astype(jnp.int32)


def fitness_and_force(fitness, x):
    """V and -grad V at every walker (autodiff); the force is 0 where V is not finite."""
    values, grads = jax.vmap(jax.value_and_grad(fitness))(x)
    ok = jnp.isfinite(values)[:, None] & jnp.all(jnp.isfinite(grads), axis=1, keepdims=True)
    return values, jnp.where(ok, -grads, 0.0)


def metric_field(fitness, params: SwarmParams, eps_sigma, x):
    """(N, d, d) Hessian metric g = floor(H) + eps_Sigma I at the walkers."""
    return jax.vmap(hessian_metric(fitness, eps_sigma, floor=params.floor))(x)


def cell_volumes(tess: Tessellation):
    """(volumes, interior): Voronoi volumes as the state carries them, +inf where no finite
    volume exists (unbounded cells; every walker of a k-NN graph), and tier-2 flags."""
    if tess.simplices is None:
        return jnp.full(tess.n_points, jnp.inf, tess.points.dtype), tess.interior
    volumes = voronoi_volumes(tess)
    return jnp.where(jnp.isnan(volumes), jnp.inf, volumes), tess.interior


def kernel_volumes(volumes):
    """Carried volumes (+inf: none known) in the kernels' convention (NaN: unbounded)."""
    return jnp.where(jnp.isfinite(volumes), volumes, jnp.nan)


def current_nu(params: SwarmParams, progress):
    """nu, or its linear annealing schedule nu_initial -> nu over the run (progress in [0, 1])."""
    if not params.anneal_nu:
        return params.nu
    return params.nu_initial + (params.nu - params.nu_initial) * progress


def viscous_length(params: SwarmParams, state: SwarmState, tess: Tessellation):
    if params.length_scale is not None:
        return params.length_scale
    spacing = mean_nearest_neighbor_distance(tess) if params.adapt_length_scale else state.spacing0
    return params.alpha * spacing


def viscous_weights(params: SwarmParams, state: SwarmState, tess: Tessellation, g):
    """Row-normalized weights (and row sums) used by both V half-steps."""
    w = weights_to_normalize(
        tess, weights=params.weights, length_scale=viscous_length(params, state, tess), metric=g, alpha=params.alpha
    )
    if params.volume_weighting:
        sqrt_det = 1.0 if g is None else jnp.sqrt(jnp.maximum(jnp.linalg.det(g), 0.0))
        w = with_volume_weights(tess, w, state.volumes * sqrt_det)  # Riemannian volumes V_j sqrt(det g_j)
    return normalize_rows(w)


def ornstein_uhlenbeck(params: SwarmParams, v, g, xi):
    """Exact O step v -> c v + sqrt(T (1 - c^2)) sigma xi with sigma sigma^T = D (I or g^-1);
    `xi` holds standard normals shaped like `v`."""
    c = jnp.exp(-params.gamma * params.dt)
    if params.anisotropic:
        chol = small_cholesky(g) if g.shape[-1] <= 4 else jnp.linalg.cholesky(g)  # L^-T xi has covariance g^-1
        xi = jax.vmap(lambda low, e: jax.scipy.linalg.solve_triangular(low, e, trans="T", lower=True))(chol, xi)
    return c * v + jnp.sqrt(params.temperature * (1.0 - c * c)) * xi


def relativize(values, mask):
    """Fractal Gas relativization: standardize, then z -> 1 + log(1 + z) (z > 0) or exp(z)."""
    count = jnp.maximum(jnp.sum(mask), 1).astype(values.dtype)
    safe = jnp.where(mask, values, 0.0)
    mean = jnp.sum(safe) / count
    std = safe_sqrt(jnp.sum(jnp.where(mask, (safe - mean) ** 2, 0.0)) / count)
    z = (safe - mean) / jnp.where(std > 0, std, 1.0)
    return jnp.where(
        mask, jnp.where(z > 0, 1.0 + jnp.log1p(jnp.where(z > 0, z, 0.0)), jnp.exp(jnp.minimum(z, 0.0))), 0.0
    )


def random_partner(key, n: int):
    """A uniformly random other walker for every walker (never itself)."""
    pick = jax.random.randint(key, (n,), 0, n - 1, dtype=jnp.int32)
    return pick + (pick >= jnp.arange(n, dtype=jnp.int32)).astype(jnp.int32)


def clone_decisions(params: SwarmParams, state: SwarmState, key):
    """(companion, clones): each walker's companion and whether it clones onto it."""
    n = state.positions.shape[0]
    k_comp, k_other, k_draw = jax.random.split(key, 3)
    companion, other = random_partner(k_comp, n), random_partner(k_other, n)
    alive = state.alive
    dist = safe_sqrt(jnp.sum((state.positions - state.positions[other]) ** 2, axis=1))
    reward = relativize(-jnp.where(alive, state.fitness, 0.0), alive)
    vr = reward**params.reward_power * relativize(dist, alive) ** params.distance_power
    ratio = (vr[companion] - vr) / jnp.where(vr > 0, vr, 1.0)
    prob = jnp.where(alive, params.clone_rate * jnp.clip(ratio, 0.0, 1.0), 1.0)
    clones = (jax.random.uniform(k_draw, (n,), vr.dtype) < prob) & alive[companion]
    return companion, clones


def apply_clones(params: SwarmParams, companion, clones, x, v, spacing, normals):
    """Cloned walkers take their companion's velocity and a jittered copy of its position
    (`normals`: standard normals shaped like `x`)."""
    jitter = params.clone_jitter * spacing * normals
    return (jnp.where(clones[:, None], x[companion] + jitter, x), jnp.where(clones[:, None], v[companion], v))


class StepStart(eqx.Module):
    """The opening of a step that does not need the graph, so that it can be computed
    ahead (`simulate` runs it while Qhull rebuilds the tessellation).

    **Fields:** `velocities` after the first kick, `positions` after the first drift,
    `noise` (the O step's standard normals), `jitter` (the clone jitter's standard
    normals), `companion` and `clones` (the clone decisions on the state entering the
    step; applied only on a step that clones), `key` (the state's next key).
    """

    velocities: Float[Array, "N d"]
    positions: Float[Array, "N d"]
    noise: Float[Array, "N d"]
    jitter: Float[Array, "N d"]
    companion: Int[Array, " N"]
    clones: Bool[Array, " N"]
    key: PRNGKeyArray


def begin_step(params: SwarmParams, state: SwarmState) -> StepStart:
    """B A of the splitting, the step's random draws and the clone decisions (no graph needed)."""
    half = 0.5 * params.dt
    key, k_noise, k_clone, k_jitter = jax.random.split(state.key, 4)
    v = state.velocities + half * state.force
    x = state.positions + half * v
    noise = jax.random.normal(k_noise, v.shape, v.dtype)
    if not params.cloning:
        n = x.shape[0]
        return StepStart(v, x, noise, jnp.zeros_like(x), jnp.arange(n, dtype=jnp.int32), jnp.zeros(n, bool), key)
    # materialise once: XLA otherwise re-derives the clone decisions inside every consumer (2x step time)
    companion, clones = jax.lax.optimization_barrier(clone_decisions(params, state, k_clone))
    return StepStart(v, x, noise, jax.random.normal(k_jitter, x.shape, x.dtype), companion, clones, key)


def swarm_step(fitness, params: SwarmParams, state: SwarmState, progress, do_clone) -> SwarmState:
    """One B A V O V A B step (module docstring) on the state's graph, plus cloning when
    `do_clone`: the composition of its three phases, `begin_step` (B A and the random
    draws: no graph), `move_on_graph` (V O V A and the clone jumps) and `finish_step` (B at
    the final positions: no graph). `simulate` runs the first and last apart, ahead of and
    after the graph's rebuild."""
    start = begin_step(params, state)
    return finish_step(fitness, params, move_on_graph(fitness, params, state, start, progress, do_clone))


def move_on_graph(fitness, params: SwarmParams, state: SwarmState, start: StepStart, progress, do_clone) -> SwarmState:
    """The part of a step that needs the graph: from `start` = `begin_step(params, state)`,
    V O V (viscous kicks around the Ornstein-Uhlenbeck step) and the second drift A, then the
    clone jumps when `do_clone`. The closing kick is left to `finish_step`."""
    half = 0.5 * params.dt
    v, x = start.velocities, start.positions
    tess = eqx.tree_at(lambda t: t.points, state.tess, x)
    eps = params.eps_sigma * state.eps_factor
    g = metric_field(fitness, params, eps, x) if params.needs_metric else None
    w, _ = viscous_weights(params, state, tess, g)
    nu = current_nu(params, progress)
    v = v + half * apply_viscous(tess, w, v, nu)
    v = ornstein_uhlenbeck(params, v, g, start.noise)
    v = v + half * apply_viscous(tess, w, v, nu)
    x = x + half * v
    clones = jnp.zeros(x.shape[0], bool)
    if params.cloning:
        clones = start.clones & do_clone
        x, v = apply_clones(params, start.companion, clones, x, v, mean_nearest_neighbor_distance(tess), start.jitter)
        x, v, clones = jax.lax.optimization_barrier((x, v, clones))
    parents = jnp.where(clones, start.companion, jnp.arange(x.shape[0], dtype=jnp.int32))
    return eqx.tree_at(
        lambda s: (s.positions, s.velocities, s.cloned, s.key, s.tess, s.step, s.eps_factor, s.scutoid_trace.parents),
        state,
        (
            x,
            v,
            clones,
            start.key,
            eqx.tree_at(lambda t: t.points, tess, x),
            state.step + 1,
            _raised_eps_factor(params, state, g),
            parents,
        ),
    )


def finish_step(fitness, params: SwarmParams, state: SwarmState) -> SwarmState:
    """The closing half kick at the step's final positions (V, -grad V, alive flags; no graph needed)."""
    values, force = fitness_and_force(fitness, state.positions)
    v = state.velocities + 0.5 * params.dt * force
    return eqx.tree_at(
        lambda s: (s.velocities, s.fitness, s.force, s.alive), state, (v, values, force, jnp.isfinite(values))
    )


def _raised_eps_factor(params: SwarmParams, state: SwarmState, g):
    """The chapter's rule: eps_Sigma x10 for the next step when max cond(g) > 1e6."""
    if not params.adapt_eps_sigma:
        return state.eps_factor
    lam = eigh(jax.lax.stop_gradient(g))[0]
    cond = jnp.max(lam[:, -1] / jnp.where(lam[:, 0] > 0, lam[:, 0], jnp.nan))
    return jnp.where(cond > COND_LIMIT, EPS_SIGMA_RAISE, 1.0) * state.eps_factor
