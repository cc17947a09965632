"""Tuning the swarm's physical parameters by gradient through whole simulations.

`simulation_loss` builds a `SimulationLoss`: a jittable, differentiable function of an
unconstrained vector theta that maps theta to positive (or bounded) parameters, runs
`simulate` (rebuild="callback", or "device") once per seed under `jax.vmap`, and averages
an objective of the histories. `tune` drives an optimistix minimiser (BFGS by default) or
jaxopt's L-BFGS-B over it and records every accepted iteration.

Semantics a user must know:

- Cloning is a discrete selection. The gradient returned with cloning on is the
  *pathwise* gradient with the selection held fixed: each walker's clone decision and
  companion are those of the run at theta, and the derivative flows through the
  companion's position and velocity that the clone takes. It ignores how theta moves the
  clone probabilities, so it is the derivative of the loss between two decision flips (what
  central differences with a small step measure), not of the expected loss. With cloning
  off the loss is smooth in theta apart from Delaunay flips (the graph is rebuilt
  without a gradient; a flip changes the viscous weights by a jump).
- A swarm that diverges (non-finite, runaway, all walkers dead: `history["diverged_step"]`)
  or an objective that is not finite gives a loss of +inf, never an exception, so a line
  search backs off from it. Its gradient is then not meaningful (NaN where the state was).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..base._checks import check_choice
from ..base._sharding import check_mesh, over_batch
from ._divergence import likely_cause
from ._dynamics import SwarmParams, SwarmState
from ._observables import ALL_OBSERVABLES
from ._simulate import REBUILD_MODES, simulate

TUNABLE = ("nu", "eps_sigma", "dt", "gamma", "temperature", "alpha", "clone_jitter", "nu_initial")
OBJECTIVES = ("final_fitness", "mean_fitness", "best_fitness", "match")
DEFAULT_OBSERVE = ("mean_fitness", "best_fitness", "velocity_variance")


def _positive_map(theta, lower, upper):
    """Unconstrained theta -> parameter: exp(theta) (no bounds), lower + exp(theta) (lower
    bound only), lower + (upper - lower) sigmoid(theta) (both)."""
    if lower is None:
        return jnp.exp(theta)
    if upper is None:
        return lower + jnp.exp(theta)
    return lower + (upper - lower) * jax.nn.sigmoid(theta)


def _inverse_map(value: float, lower, upper) -> float:
    if lower is None:
        return math.log(value)
    if upper is None:
        return math.log(value - lower)
    s = (value - lower) / (upper - lower)
    return math.log(s) - math.log1p(-s)


class SimulationLoss(eqx.Module):
    """theta -> the objective of `simulate` averaged over seeds (from `simulation_loss`).

    Call it as `loss(theta)` or `loss(theta, args)` (optimistix's signature; `args` is
    ignored). `loss.to_params(theta)` gives the `SwarmParams` it simulates, `loss.to_theta`
    the theta of given parameter values, `loss.per_seed(theta)` the (n_seeds,) losses
    before averaging."""

    fitness: Callable = eqx.field(static=True)
    state: SwarmState
    params: SwarmParams
    keys: Array
    tuned: tuple = eqx.field(static=True)
    bounds: tuple = eqx.field(static=True)  # (lower, upper) per tuned name, None where open
    objective: Any = eqx.field(static=True)  # a name of OBJECTIVES or a callable
    targets: tuple = eqx.field(static=True)  # ((name, value), ...) for "match"
    observe: tuple = eqx.field(static=True)
    n_steps: int = eqx.field(static=True)
    window: float = eqx.field(static=True)
    rebuild: str = eqx.field(static=True)
    rebuild_every: int = eqx.field(static=True)
    checkpoint: bool = eqx.field(static=True)
    mesh: object = eqx.field(static=True, default=None)  # a jax.sharding.Mesh splitting the seeds, or None

    @property
    def n_seeds(self) -> int:
        return self.keys.shape[0]

    def check_theta(self, theta) -> None:
        """theta must be a real (p,) vector, one entry per tuned parameter (shapes are static)."""
        if np.shape(theta) != (len(self.tuned),):
            raise ValueError(
                f"theta must have shape ({len(self.tuned)},), one entry per tuned parameter "
                f"{list(self.tuned)} (loss.to_theta({{...}}) builds it); got shape {np.shape(theta)}."
            )

    def to_params(self, theta: Float[Array, " p"]) -> SwarmParams:
        """The `SwarmParams` simulated at theta (the tuned fields replaced)."""
        dtype = self.state.positions.dtype
        values = tuple(_positive_map(jnp.asarray(theta[m], dtype), *self.bounds[m]) for m in range(len(self.tuned)))
        return eqx.tree_at(lambda p: tuple(getattr(p, name) for name in self.tuned), self.params, values)

    def to_theta(self, values=None) -> Float[Array, " p"]:
        """theta of physical values: a dict {name: value} (names left out keep `params`'
        value), a `SwarmParams`, or None (the loss's `params`)."""
        if isinstance(values, SwarmParams):
            values = {name: getattr(values, name) for name in self.tuned}
        values = {} if values is None else dict(values)
        unknown = sorted(set(values) - set(self.tuned))
        if unknown:
            raise ValueError(f"unknown tuned parameter(s) {unknown}; this loss tunes {list(self.tuned)}.")
        theta = []
        for name, (lower, upper) in zip(self.tuned, self.bounds, strict=True):
            value = float(values.get(name, getattr(self.params, name)))
            _check_inside(name, value, lower, upper)
            theta.append(_inverse_map(value, lower, upper))
        return jnp.asarray(theta, self.state.positions.dtype)

    def values(self, theta) -> dict:
        """{name: physical value} at theta (host floats)."""
        params = self.to_params(jnp.asarray(theta))
        return {name: float(getattr(params, name)) for name in self.tuned}

    def histories(self, theta):
        """(final states, histories) of every seed, stacked on a leading (n_seeds,) axis; the
        histories without the wall-clock times, which a traced run does not measure (NaN)."""

        def run(key, params):
            state = eqx.tree_at(lambda s: s.key, self.state, key)
            final, history = simulate(
                self.fitness,
                state,
                params,
                n_steps=self.n_steps,
                rebuild=self.rebuild,
                rebuild_every=self.rebuild_every,
                observe=self.observe,
                checkpoint=self.checkpoint,
            )
            return final, {name: value for name, value in history.items() if not name.startswith("seconds_")}

        return over_batch(run, self.mesh)(self.keys, self.to_params(theta))

    def per_seed(self, theta) -> Float[Array, " n_seeds"]:
        """The objective of each seed's run; +inf where the swarm diverged or the objective is
        not finite ("match": each seed's own averages against the targets)."""
        _, history = self.histories(theta)
        values = jax.vmap(self._objective)(history)
        return jnp.where((history["diverged_step"] >= 0) | ~jnp.isfinite(values), jnp.inf, values)

    def __call__(self, theta, args=None) -> Float[Array, ""]:
        self.check_theta(theta)
        if self.objective != "match":
            return jnp.mean(self.per_seed(theta))
        # Matching compares the seed average of each observable with its target (a method of
        # moments), so that the target's own parameters give exactly 0 on the same seeds.
        moments, diverged = self._moments(theta)
        targets = jnp.asarray([target for _, target in self.targets], moments.dtype)
        scales = jnp.asarray(self.target_scales(), moments.dtype)
        value = jnp.sum(((jnp.mean(moments, axis=0) - targets) / scales) ** 2)
        return jnp.where(diverged | ~jnp.isfinite(value), jnp.inf, value)

    def divergence(self, theta) -> str | None:
        """Why the loss at theta is +inf, when a seed's run diverged: the first step at which one
        did, in how many seeds, and the likely cause judged at the initial walkers; else None."""
        _, history = eqx.filter_jit(lambda loss, t: loss.histories(t))(self, jnp.asarray(theta))
        steps = np.asarray(history["diverged_step"]).reshape(-1)
        if not (steps >= 0).any():
            return None
        cause = likely_cause(self.fitness, self.to_params(jnp.asarray(theta)), self.state)
        return (
            f"the simulation diverged by step {int(steps[steps >= 0].min())} in {int((steps >= 0).sum())} of "
            f"{steps.size} seed(s). {cause}"
        )

    def seed_moments(self, theta) -> Float[Array, "n_seeds n_targets"]:
        """ "match": each seed's average of every matched observable over the last `window`
        of its run (the loss compares their seed mean with `targets`)."""
        return self._moments(theta)[0]

    def target_scales(self) -> np.ndarray:
        """The divisor of each target's error in the "match" loss: |target|, or 1 for a target 0."""
        return np.asarray([abs(target) or 1.0 for _, target in self.targets])

    def _moments(self, theta):
        _, history = self.histories(theta)
        moments = jnp.stack([jax.vmap(self._late_mean)(history[name]) for name, _ in self.targets], axis=1)
        return moments, jnp.any(history["diverged_step"] >= 0)

    def _objective(self, history: dict):
        if callable(self.objective):
            return self.objective(history)
        if self.objective == "final_fitness":
            return history["mean_fitness"][-1]
        if self.objective == "best_fitness":
            return history["best_fitness"][-1]
        if self.objective == "mean_fitness":
            return self._late_mean(history["mean_fitness"])
        terms = [
            ((self._late_mean(history[name]) - value) / scale) ** 2
            for (name, value), scale in zip(self.targets, self.target_scales(), strict=True)
        ]
        return sum(terms)

    def _late_mean(self, series):
        """Mean over the last `window` fraction of the recorded times (at least the final one)."""
        first = min(len(series) - 1, int(math.floor((1.0 - self.window) * (len(series) - 1))))
        return jnp.mean(series[first:])


def _check_inside(name: str, value: float, lower, upper) -> None:
    low = 0.0 if lower is None else lower
    if not (math.isfinite(value) and value > low and (upper is None or value < upper)):
        where = f"> {low}" + (f" and < {upper}" if upper is not None else "")
        raise ValueError(f"`{name}` = {value} cannot be tuned from: it must be {where} (the parameter map's range).")


def simulation_loss(
    fitness,
    state: SwarmState,
    objective="mean_fitness",
    *,
    n_steps: int,
    params: SwarmParams,
    tuned=("nu",),
    n_seeds: int = 1,
    key=None,
    targets: dict | None = None,
    bounds: dict | None = None,
    window: float | None = None,
    observe=None,
    rebuild: str = "callback",
    rebuild_every: int = 1,
    checkpoint: bool = True,
    mesh=None,
) -> SimulationLoss:
    """A differentiable loss of the swarm's parameters: theta -> objective of whole simulations.

    **Arguments:**

    - `fitness`, `state`: the landscape and the initial [`jaxgeom.SwarmState`][] (from
      `init_swarm`); every seed starts from `state` with its own PRNG key.
    - `objective`: "mean_fitness" (mean fitness averaged over the last `window` of the run:
      smoother than the final value), "final_fitness", "best_fitness" (final), "match"
      (sum over `targets` of (A - target)^2 / target^2, or the plain square for a target 0,
      A the observable averaged over the last `window` of the run and over the seeds), or
      a callable `history -> scalar` (history: the dict `simulate` returns for one seed,
      with the observables `observe`, without the unmeasured `seconds_*`). The loss is the
      mean over seeds of the objective (for "match": of the seed-averaged observables).
    - `n_steps`, `params`: the run and the [`jaxgeom.SwarmParams`][] whose fields `tuned`
      (names in `TUNABLE`; default: nu) are replaced by the map of theta. A tuned name the
      loss cannot depend on under `params` is refused with the reason (`ignored_parameter`):
      eps_sigma without a metric in the dynamics (weights "metric_*", `anisotropic=True`) or
      in an observed quantity, alpha without the adaptive "kernel" width, nu_initial without
      `anneal_nu`, clone_jitter without cloning, temperature at gamma = 0.
    - `n_seeds`: runs averaged (>= 1), vmapped; their keys are `jax.random.split(key,
      n_seeds)` with `key` (int or key) defaulting to `state.key`.
    - `bounds`: {name: (lower, upper)} (either may be None): the parameter is `lower +
      (upper - lower) sigmoid(theta)`, or `lower + exp(theta)`; unbounded names are
      `exp(theta)` (log parameters).
    - `window`: fraction of the run (at its end) that the time averages of "mean_fitness" and
      "match" cover, in (0, 1] (None: 0.5); refused with the other objectives, which have none.
    - `observe`: the observables a callable objective reads (default: mean and best fitness and
      velocity variance); refused with the named objectives, which record their own.
    - `rebuild`: "callback" (default) or "device" (2D Delaunay swarms); `rebuild_every`.
    - `checkpoint`: nested sqrt(n_steps) rematerialisation (memory ~ sqrt(n_steps)).
    - `mesh`: a `jax.sharding.Mesh` with a "batch" axis (`jaxgeom.batch_mesh()`): the seeds
      are split over its devices (`jax.shard_map`; `n_seeds` a multiple of its size), the
      loss and its gradient equal the one-device ones. None: `vmap` on one device.

    **Returns:** a [`jaxgeom.SimulationLoss`][] `loss`, with `loss(theta)` jittable and
    differentiable and `loss.to_theta({"nu": 0.1})` the theta of given values.
    """
    if window is not None and objective not in ("mean_fitness", "match"):
        raise ValueError(
            f"`window` sets the time average of objective 'mean_fitness' or 'match'; objective "
            f"{objective!r} has none. Leave window None."
        )
    if observe is not None and not callable(objective):
        raise ValueError(
            f"`observe` lists what a callable objective reads; objective {objective!r} records its own "
            "observables. Leave observe None."
        )
    window = 0.5 if window is None else window
    _check_loss_args(state, params, objective, n_steps, tuned, n_seeds, targets, window, rebuild)
    tuned = tuple(tuned)
    bound_pairs = _bounds_of(tuned, bounds)
    target_pairs = tuple((str(name), float(value)) for name, value in (targets or {}).items())
    observe = _observables_for(objective, target_pairs, observe)
    for name in tuned:
        reason = ignored_parameter(name, params, observe, tuned)
        if reason:
            raise ValueError(f"`tuned` names {name!r}, on which this loss cannot depend: {reason}")
    base = state.key if key is None else _key_like(key, state.key)
    keys = jax.random.split(base, n_seeds)
    check_mesh(mesh, n_seeds, "`n_seeds`")
    loss = SimulationLoss(
        fitness,
        state,
        params,
        keys,
        tuned,
        bound_pairs,
        objective,
        target_pairs,
        observe,
        int(n_steps),
        float(window),
        rebuild,
        int(rebuild_every),
        bool(checkpoint),
        mesh,
    )
    for name, (lower, upper) in zip(tuned, bound_pairs, strict=True):
        _check_inside(name, float(getattr(params, name)), lower, upper)
    if callable(objective):
        _check_callable_objective(loss)
    return loss


def _check_loss_args(state, params, objective, n_steps, tuned, n_seeds, targets, window, rebuild) -> None:
    if not isinstance(state, SwarmState):
        raise TypeError("`state` must be a jaxgeom.SwarmState; build one with jaxgeom.init_swarm(fitness, positions).")
    if not isinstance(params, SwarmParams):
        raise TypeError("`params` must be a jaxgeom.SwarmParams.")
    if not callable(objective):
        check_choice(objective, "objective", OBJECTIVES)
    for name, value, low in (("n_steps", n_steps, 1), ("n_seeds", n_seeds, 1)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < low:
            raise ValueError(f"`{name}` must be an integer >= {low}; got {value!r}.")
    if isinstance(tuned, str) or not tuned or len(set(tuned)) != len(tuple(tuned)):
        raise ValueError(f"`tuned` must be a non-empty tuple of distinct names from {TUNABLE}; got {tuned!r}.")
    for name in tuned:
        if name == "clone_rate":
            raise ValueError(
                "`clone_rate` cannot be tuned by gradient: it changes only the discrete clone "
                "decisions, which the pathwise gradient holds fixed, so its gradient is exactly 0. "
                "Choose it by a sweep of simulate runs."
            )
        check_choice(name, "tuned parameter", TUNABLE)
    if (objective == "match") != bool(targets):
        raise ValueError(
            "objective='match' needs `targets` ({observable: value}), and `targets` needs "
            f"objective='match'; got objective={objective!r}, targets={targets!r}."
        )
    for name, value in (targets or {}).items():
        check_choice(name, "target observable", ALL_OBSERVABLES)
        if not np.isfinite(value):
            raise ValueError(f"target {name!r} must be a finite number; got {value!r}.")
    if not (0.0 < window <= 1.0):
        raise ValueError(f"`window` must be in (0, 1]; got {window!r}.")
    if rebuild not in REBUILD_MODES[1:]:
        raise ValueError(f"`rebuild` must be 'callback' or 'device' (a loss is traced); got {rebuild!r}.")


METRIC_OBSERVABLES = ("mean_ricci", "ricci_resolution", "mean_metric_curvature", "eps_sigma")


def ignored_parameter(name: str, params: SwarmParams, observe: tuple, tuned: tuple = ()) -> str:
    """Why a loss of runs under `params` that reads the observables `observe` cannot depend on
    the parameter `name` ("" when it can). `tuned`: the parameters tuned with it."""
    if name == "eps_sigma" and not (_dynamics_use_metric(params) or set(observe) & set(METRIC_OBSERVABLES)):
        return (
            f"eps_Sigma enters only the Hessian metric g = floor(H) + eps_Sigma I, and these runs never use g "
            f"(weights={params.weights!r}, isotropic noise) nor does the loss read it (observables "
            f"{list(observe)}). Tune it with weights='metric_full' or 'metric_diagonal' or anisotropic=True, "
            "or leave it out of `tuned`."
        )
    if name == "alpha" and (params.weights != "kernel" or params.length_scale is not None):
        return (
            f"alpha sets the adaptive width of weights='kernel' without a length_scale; these runs use "
            f"weights={params.weights!r}, length_scale={_shown(params.length_scale)}. Leave it out of `tuned`."
        )
    if name == "nu_initial" and not params.anneal_nu:
        return "nu_initial starts the annealing schedule of anneal_nu=True; these runs keep nu constant."
    if name == "clone_jitter" and not params.cloning:
        return "clone_jitter places cloned walkers; these runs have cloning=False."
    if (
        name == "temperature"
        and "gamma" not in tuned
        and not isinstance(params.gamma, jax.core.Tracer)
        and float(params.gamma) == 0.0
    ):
        return (
            "at gamma = 0 the Ornstein-Uhlenbeck step has no noise (its variance is T (1 - exp(-2 gamma dt))), "
            "so the temperature does not enter. Set gamma > 0 or tune gamma with it."
        )
    return ""


def _dynamics_use_metric(params: SwarmParams) -> bool:
    """Whether a step reads the Hessian metric: noise g^-1, metric weights, or volume weights by
    sqrt(det g) (g is computed whenever the parameters need it)."""
    return (
        params.anisotropic or params.weights.startswith("metric") or (params.needs_metric and params.volume_weighting)
    )


def _shown(value) -> str:
    return "None" if value is None else f"{float(value):g}"


def _bounds_of(tuned: tuple, bounds: dict | None) -> tuple:
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(tuned))
    if unknown:
        raise ValueError(f"`bounds` names {unknown}, which are not tuned; tuned: {list(tuned)}.")
    out = []
    for name in tuned:
        lower, upper = bound_pair(bounds, name)
        if lower is None and upper is not None:
            lower = 0.0  # the parameters are non-negative
        if upper is not None and not upper > lower:
            raise ValueError(f"bounds for {name!r} must have lower < upper; got ({lower}, {upper}).")
        out.append((lower, upper))
    return tuple(out)


def bound_pair(bounds: dict, name: str) -> tuple:
    """(lower, upper) of `name` in `bounds` as floats or None (no bound), checked."""
    pair = bounds.get(name, (None, None))
    if isinstance(pair, str) or np.shape(pair) != (2,):
        raise ValueError(f"bounds for {name!r} must be a pair (lower, upper) of numbers or None; got {pair!r}.")
    return tuple(None if b is None else _bound(b, name) for b in pair)


def _bound(value, name: str) -> float:
    if isinstance(value, (str, bytes)) or np.iscomplexobj(value):
        raise TypeError(f"bounds for {name!r} must be real numbers or None; got {value!r}.")
    value = float(value)
    if np.isnan(value):
        raise ValueError(f"bounds for {name!r} must be numbers or None (no bound); got nan.")
    return value


def _observables_for(objective, targets: tuple, observe) -> tuple:
    if objective in ("final_fitness", "mean_fitness"):
        return ("mean_fitness",)
    if objective == "best_fitness":
        return ("best_fitness",)
    if objective == "match":
        return tuple(name for name, _ in targets)
    observe = DEFAULT_OBSERVE if observe is None else (observe,) if isinstance(observe, str) else tuple(observe)
    for name in observe:
        check_choice(name, "observable", ALL_OBSERVABLES)
    return observe


def _key_like(key, like):
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        key = jax.random.PRNGKey(key)
    elif not (
        isinstance(key, jax.Array)
        and (jnp.issubdtype(key.dtype, jax.dtypes.prng_key) or (key.dtype == jnp.uint32 and key.shape == (2,)))
    ):
        raise TypeError(f"`key` must be an int seed or a jax.random key (jax.random.PRNGKey(seed)); got {key!r}.")
    if jnp.issubdtype(like.dtype, jax.dtypes.prng_key) and not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.wrap_key_data(key)
    if not jnp.issubdtype(like.dtype, jax.dtypes.prng_key) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        return jax.random.key_data(key)
    return key


def _check_callable_objective(loss: SimulationLoss) -> None:
    """A user objective must be traceable and return one real scalar: checked on the shapes,
    without a run."""
    histories = jax.eval_shape(lambda t: loss.histories(t)[1], loss.to_theta())
    try:
        shape = jax.eval_shape(jax.vmap(loss.objective), histories)
    except jax.errors.JAXTypeError as err:  # float(), numpy or a Python branch on a traced value
        raise TypeError(
            f"the objective must be JAX-traceable: history -> scalar with jax.numpy (e.g. "
            f"h['mean_fitness'][-1], not float(np.asarray(...))), since the loss is jitted and "
            f"differentiated; tracing it failed: {type(err).__name__}: {str(err).splitlines()[0]}"
        ) from None
    if not (
        isinstance(shape, jax.ShapeDtypeStruct)
        and shape.shape == (loss.n_seeds,)
        and jnp.issubdtype(shape.dtype, jnp.floating)
    ):
        got = jax.tree_util.tree_map(lambda s: (s.shape, str(s.dtype)), shape)
        raise ValueError(
            f"the objective must return one float scalar per history; it returns {got} "
            f"for {loss.n_seeds} seed(s) (reduce it with jnp.mean or index the final step)."
        )
