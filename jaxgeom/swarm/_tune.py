"""`tune`: a thin driver over optimistix (BFGS by default) or jaxopt's L-BFGS-B.

The optimistix path runs the solver's own `init` / `step` / `terminate` in the order
`optimistix.minimise` does, one jitted step at a time, so it can record every accepted
iteration (loss, gradient norm, parameters) and stop on a non-finite loss with the
iteration named. Both paths minimise loss / |grad loss(theta0)|: the losses of a matching
problem are often tiny (1e-4), and unscaled, a first quasi-Newton step of -grad is so
short that optimistix's Cauchy test (and scipy's ftol) stop at once. The iterates are
those of `optimistix.minimise(scaled(loss, scale), solver, theta0)`.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..base._checks import check_nonnegative, check_positive, warn_at_caller
from ..base._progress import check_progress, close_bar, open_bar, raise_if_interrupted
from ._dynamics import SwarmParams
from ._tuning import SimulationLoss, _inverse_map, bound_pair

SOLVERS = ("bfgs", "nonlinear_cg", "lbfgsb")


class TuningFailed(FloatingPointError):
    """The loss or its gradient stopped being finite at an accepted iteration; `result`
    holds the iterations recorded up to there."""

    def __init__(self, message: str, result: TuneResult):
        super().__init__(message)
        self.result = result


class TuningInterrupted(KeyboardInterrupt):
    """Ctrl-C during `tune`: `result` holds the iterations accepted before it (None if none was)."""

    def __init__(self, result: TuneResult | None):
        done = 0 if result is None else len(result.iterations) - 1
        super().__init__(f"tune: interrupted after {done} iteration(s)")
        self.result = result


@dataclasses.dataclass
class TuneResult:
    """What `tune` found.

    - `theta`, `values` ({name: physical value}), `params` (the `SwarmParams` at theta),
      `loss` at theta.
    - `iterations`: one dict per accepted iterate, the start included: `iteration`,
      `loss`, `grad_norm` (of the loss in theta), `values`, `gradient` ({name: d loss / d theta}).
    - `solver`, `n_steps` (solver steps, rejected line-search trials included),
      `converged`, `message`, `seconds` (wall clock, compilation included).
    - `scale`: the norm of the loss's gradient at the start; the solver minimises
      loss / scale (`scaled(loss, scale)`), so that its first step has unit length in
      theta (log parameters) whatever the loss's units. `optimistix.minimise(scaled(loss,
      scale), solver, theta0)` reproduces the iterates.
    - `standard_errors`: {name: standard error of the value}, the sandwich (delta-method)
      estimate of a "match" fit (`parameter_errors`); NaN, with the reason in
      `error_note`, where it is not defined. `covariance`: its (p, p) matrix in theta.
    - `zero_gradient`: the tuned names whose gradient was exactly 0 at every recorded
      iterate (the loss did not move them; `tune` warns); empty when every one moved.
    """

    theta: np.ndarray
    values: dict
    params: SwarmParams
    loss: float
    iterations: list
    solver: str
    n_steps: int
    converged: bool
    message: str
    seconds: float
    scale: float
    standard_errors: dict = dataclasses.field(default_factory=dict)
    covariance: np.ndarray | None = None
    error_note: str = ""
    zero_gradient: tuple = ()


def _solver_of(solver, rtol: float, atol: float):
    if solver is None or solver == "bfgs":
        return "bfgs", optx.BFGS(rtol=rtol, atol=atol)
    if solver == "nonlinear_cg":
        return "nonlinear_cg", optx.NonlinearCG(rtol=rtol, atol=atol)
    if solver == "lbfgsb":
        return "lbfgsb", None
    if isinstance(solver, optx.AbstractMinimiser):
        return type(solver).__name__, solver
    raise ValueError(
        f"unknown solver {solver!r}; valid values are {', '.join(map(repr, SOLVERS))} "
        "or an optimistix.AbstractMinimiser instance."
    )


def _start(loss: SimulationLoss, start):
    if start is None or isinstance(start, (dict, SwarmParams)):
        return loss.to_theta(start)
    theta = jnp.asarray(start, loss.state.positions.dtype)
    if theta.shape != (len(loss.tuned),) or not bool(jnp.all(jnp.isfinite(theta))):
        raise ValueError(
            f"`start` as an array is theta (unconstrained, one entry per tuned name {list(loss.tuned)}), "
            f"finite; got shape {theta.shape}. Give physical values as a dict instead."
        )
    return theta


def tune(
    loss: SimulationLoss,
    start=None,
    *,
    solver=None,
    max_steps: int = 50,
    rtol: float = 1e-4,
    atol: float | None = None,
    bounds: dict | None = None,
    progress=False,
    target_seeds: int | None = None,
) -> TuneResult:
    """Minimise a [`jaxgeom.SimulationLoss`][] over its tuned parameters.

    **Arguments:**

    - `loss`: from `jaxgeom.simulation_loss`.
    - `start`: physical values {name: value} (names left out: `loss.params`), a
      `SwarmParams`, theta itself (an array), or None (`loss.params`).
    - `solver`: "bfgs" (default, `optimistix.BFGS`), "nonlinear_cg", any
      `optimistix.AbstractMinimiser`, or "lbfgsb" (`jaxopt.ScipyBoundedMinimize`, the
      option for hard `bounds` {name: (lower, upper)} in physical units; optimistix's
      minimisers take no bounds, use `simulation_loss(bounds=...)` with them instead).
    - `max_steps`: solver steps (optimistix) or iterations (L-BFGS-B); `rtol`, `atol` (None:
      1e-6): the optimistix Cauchy termination (L-BFGS-B: `rtol` is scipy's `tol`; `atol` refused).
    - `progress`: a `tqdm.auto` bar over the iterations, showing the loss and the values:
      False (default), True, "auto" (shown in a terminal or a notebook) or a tqdm bar.
    - `target_seeds`: the number of independent runs that the targets of a "match" loss
      were averaged over, for their share of the standard errors (None: the targets are
      exact, the errors are the simulation's alone).

    **Returns:** a [`jaxgeom.TuneResult`][]. **Raises:** `TuningFailed` (naming the
    iteration) when an accepted iterate has a non-finite loss or gradient, e.g. a start
    at which the swarm diverges.
    """
    if not isinstance(loss, SimulationLoss):
        raise TypeError("`loss` must be a jaxgeom.SimulationLoss from jaxgeom.simulation_loss(...).")
    check_progress(progress)
    if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"`max_steps` must be an integer >= 1; got {max_steps!r}.")
    check_positive(rtol, "rtol", " (the solver's relative tolerance)")
    name, _ = _solver_of(solver, rtol, 0.0)
    if atol is not None and name == "lbfgsb":
        raise ValueError(
            "`atol` is optimistix's absolute tolerance; solver='lbfgsb' (scipy) takes `rtol` only. Leave atol None."
        )
    atol = 1e-6 if atol is None else atol
    check_nonnegative(atol, "atol")
    name, minimiser = _solver_of(solver, rtol, atol)
    if bounds is not None and name != "lbfgsb":
        raise ValueError(
            "hard `bounds` need solver='lbfgsb'; with optimistix solvers give them to "
            "simulation_loss(bounds=...) (a sigmoid map of theta)."
        )
    theta0 = _start(loss, start)
    began = time.perf_counter()
    bar, owned = open_bar(progress, max_steps + 1, f"tune ({name})", unit="it")
    recorder = _Recorder(loss, bar, name)
    try:
        value, grad = _value_and_grad(loss, theta0)
        recorder.add(theta0, value, grad)
        scale = jnp.maximum(jnp.linalg.norm(grad), jnp.finfo(grad.dtype).tiny)
        if name == "lbfgsb":
            theta, n_steps, converged, message = _run_lbfgsb(loss, theta0, scale, max_steps, rtol, bounds, recorder)
        else:
            theta, n_steps, converged, message = _run_optimistix(loss, minimiser, theta0, scale, max_steps, recorder)
        raise_if_interrupted()  # a Ctrl-C in the last iteration: no iterate is recorded after it
        errors, covariance, note = parameter_errors(loss, theta, target_seeds)
        raise_if_interrupted()
    except KeyboardInterrupt:
        raise TuningInterrupted(recorder.partial("interrupted", time.perf_counter() - began)) from None
    finally:
        close_bar(bar, owned)
    best = recorder.iterations[-1]
    frozen = zero_gradient(recorder.iterations, loss.tuned)
    if frozen:
        warn_at_caller(
            f"tune: the gradient in {list(frozen)} was exactly 0 at every iterate, so the solver never "
            "moved them: the loss does not depend on them here (result.zero_gradient). Leave them out "
            "of `tuned`, or make the loss read them.",
            RuntimeWarning,
        )
    return TuneResult(
        np.asarray(theta),
        loss.values(theta),
        loss.to_params(jnp.asarray(theta)),
        best["loss"],
        recorder.iterations,
        name,
        n_steps,
        converged,
        message,
        time.perf_counter() - began,
        float(scale),
        errors,
        covariance,
        note,
        frozen,
    )


def zero_gradient(iterations: list, tuned: tuple) -> tuple:
    """The tuned names whose recorded gradient is exactly 0 at every iterate."""
    return tuple(name for name in tuned if all(record["gradient"][name] == 0.0 for record in iterations))


def parameter_errors(loss: SimulationLoss, theta, target_seeds: int | None = None):
    """Standard errors of the parameters of a "match" fit at theta (`tune` reports them).

    **Arguments:**

    - `loss`: a [`jaxgeom.SimulationLoss`][] with objective "match" and n_seeds >= 2.
    - `theta`: where (the fit's optimum: `TuneResult.theta`).
    - `target_seeds`: the number of independent runs the targets average (None: exact).

    **Returns:** `({name: standard error of the value}, covariance of theta (p, p), note)`.

    The fit is a method of moments: theta solves min |W^(1/2) (m(theta) - t)|^2 with m the
    seed mean of the matched observables and W = diag(1 / target_scale^2). To first order
    theta_hat - theta = B J^T W (t - m), B = (J^T W J)^-1, J = dm/dtheta (forward-mode
    derivative through the simulations), so Cov(theta_hat) = B J^T W Sigma W J B (the
    sandwich), Sigma = S (1 / n_seeds + 1 / target_seeds) with S the seed-to-seed covariance
    of the observables at theta_hat. The values' errors follow through the parameter map.
    NaN (with the reason) for other objectives, one seed, or observables that do not
    identify every parameter (J^T W J singular)."""
    nan = {name: float("nan") for name in loss.tuned}
    if loss.objective != "match":
        return nan, None, "standard errors are computed for objective='match' (a fit to observables)"
    if loss.n_seeds < 2:
        return nan, None, "standard errors need n_seeds >= 2 (the seed-to-seed spread)"
    if target_seeds is not None and (not isinstance(target_seeds, (int, np.integer)) or target_seeds < 1):
        raise ValueError(f"`target_seeds` must be an integer >= 1 or None; got {target_seeds!r}.")
    moments, jac, rates = (np.asarray(a, float) for a in _error_ingredients(loss, jnp.asarray(theta)))
    weight = np.diag(1.0 / loss.target_scales() ** 2)
    information = jac.T @ weight @ jac
    if not np.all(np.isfinite(information)) or np.linalg.cond(information) > 1e12:
        return nan, None, "the matched observables do not identify every tuned parameter (J^T W J is singular)"
    spread = np.atleast_2d(np.cov(moments, rowvar=False))
    sigma = spread * (1.0 / loss.n_seeds + (1.0 / target_seeds if target_seeds else 0.0))
    bread = np.linalg.inv(information)
    covariance = bread @ jac.T @ weight @ sigma @ weight @ jac @ bread
    errors = np.abs(rates) * np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    return dict(zip(loss.tuned, errors.tolist(), strict=True)), covariance, ""


@eqx.filter_jit
def _error_ingredients(loss, theta):
    """(per-seed moments (n_seeds, m), J = d mean / d theta (m, p), d value / d theta (p,))."""

    def mean_and_moments(t):
        moments = loss.seed_moments(t)
        return jnp.mean(moments, axis=0), moments

    jac, moments = jax.jacfwd(mean_and_moments, has_aux=True)(theta)
    values = lambda t: jnp.stack([getattr(loss.to_params(t), name) for name in loss.tuned])  # noqa: E731
    return moments, jac, jnp.diag(jax.jacfwd(values)(theta))


class _Recorder:
    """The list of accepted iterates; raises `TuningFailed` at the first non-finite one."""

    def __init__(self, loss: SimulationLoss, bar, name: str):
        self.loss, self.bar, self.name = loss, bar, name
        self.iterations: list[dict[str, Any]] = []
        self.thetas: list[np.ndarray] = []

    def add(self, theta, value, grad) -> None:
        record: dict[str, Any] = {
            "iteration": len(self.iterations),
            "loss": float(value),
            "grad_norm": float(np.linalg.norm(np.asarray(grad))),
            "values": self.loss.values(theta),
            "gradient": dict(zip(self.loss.tuned, np.asarray(grad, float).tolist(), strict=True)),
        }
        self.iterations.append(record)
        if self.bar is not None:
            shown = " ".join(f"{k}={v:.4g}" for k, v in record["values"].items())
            self.bar.set_postfix_str(f"loss {record['loss']:.4g} {shown}", refresh=False)
            self.bar.update(1)
        self.thetas.append(np.asarray(theta))
        raise_if_interrupted()
        if not (np.isfinite(record["loss"]) and np.isfinite(record["grad_norm"])):
            partial = self.partial("non-finite", float("nan"))
            what = "loss" if not np.isfinite(record["loss"]) else "gradient"
            diverged = self.loss.divergence(theta)
            why = diverged or "the swarm diverged or an observable is undefined there."
            assert partial is not None  # this iterate was recorded
            raise TuningFailed(
                f"tune: the {what} is not finite at iteration {record['iteration']} ({record['values']}): {why} "
                "Start closer to sound values (a smaller dt, a larger eps_sigma), bound the parameters, or use "
                "float64.",
                partial,
            )

    def partial(self, message: str, seconds: float) -> TuneResult | None:
        """A `TuneResult` at the last recorded iterate (not converged), None before the first."""
        if not self.iterations:
            return None
        theta, record = self.thetas[-1], self.iterations[-1]
        return TuneResult(
            theta,
            record["values"],
            self.loss.to_params(jnp.asarray(theta)),
            record["loss"],
            self.iterations,
            self.name,
            len(self.iterations),
            False,
            message,
            seconds,
            float("nan"),
            error_note=f"the run stopped ({message}) before it converged",
            zero_gradient=zero_gradient(self.iterations, self.loss.tuned),
        )


@eqx.filter_jit
def _value_and_grad(loss, theta):
    return jax.value_and_grad(loss)(theta)


def scaled(loss: SimulationLoss, scale):
    """The function `tune` minimises: fn(theta, args) = loss(theta) / scale (optimistix's signature)."""
    return lambda y, args: loss(y) / scale


def _as_fn(loss, scale):
    fn = scaled(loss, scale)
    return lambda y, args: (fn(y, args), None)


@eqx.filter_jit
def _init(solver, loss, scale, theta):
    f_struct = jax.ShapeDtypeStruct((), theta.dtype)
    return solver.init(_as_fn(loss, scale), theta, None, {}, f_struct, None, frozenset())


@eqx.filter_jit
def _step(solver, loss, scale, theta, state):
    fn = _as_fn(loss, scale)
    theta, state, _ = solver.step(fn, theta, None, {}, state, frozenset())
    done, result = solver.terminate(fn, theta, None, {}, state, frozenset())
    return theta, state, done, result


def _run_optimistix(loss, solver, theta0, scale, max_steps: int, recorder: _Recorder):
    """optimistix.minimise's loop (init; while not terminated: step), recording accepted iterates
    (the first, theta0, is recorded by `tune`)."""
    theta, state = theta0, _init(solver, loss, scale, theta0)
    accepted, done, result, n_steps = 1, False, optx.RESULTS.successful, 0
    while n_steps < max_steps and not done:
        raise_if_interrupted()  # every solver step: rejected line-search trials record no iterate
        theta, state, done, result = _step(solver, loss, scale, theta, state)
        n_steps, done = n_steps + 1, bool(done) or bool(result != optx.RESULTS.successful)
        info = getattr(state, "f_info", None)
        count = int(getattr(state, "num_accepted_steps", n_steps))
        if info is not None and count > accepted:
            accepted = count
            recorder.add(theta, info.f * scale, info.grad * scale)
    if getattr(state, "f_info", None) is None:  # a solver without f_info: record the final iterate
        value, grad = _value_and_grad(loss, theta)
        recorder.add(theta, value, grad)
    converged = done and bool(result == optx.RESULTS.successful)
    if converged:
        message = "converged"
    elif result != optx.RESULTS.successful:
        message = optx.RESULTS[result]  # type: ignore[misc]  # an equinox Enumeration: indexable
    else:
        message = f"max_steps={max_steps} reached"
    return theta, n_steps, converged, message


def _run_lbfgsb(loss, theta0, scale, max_steps: int, tol: float, bounds, recorder: _Recorder):
    import jaxopt

    seen = {}

    def fun(theta):
        raise_if_interrupted()
        value, grad = _value_and_grad(loss, theta)
        seen[np.asarray(theta).tobytes()] = (value, grad)
        return value / scale, grad / scale

    def callback(theta):
        value, grad = seen.get(np.asarray(theta, np.asarray(theta0).dtype).tobytes()) or _value_and_grad(loss, theta)
        recorder.add(theta, value, grad)

    lower, upper = _theta_bounds(loss, bounds)
    solver = jaxopt.ScipyBoundedMinimize(
        fun=fun, value_and_grad=True, method="l-bfgs-b", maxiter=max_steps, tol=tol, jit=False, callback=callback
    )
    theta, info = solver.run(theta0, bounds=(lower, upper))
    converged = bool(info.success)
    return theta, int(info.iter_num), converged, "converged" if converged else f"scipy status {int(info.status)}"


def _theta_bounds(loss: SimulationLoss, bounds: dict | None):
    """Physical bounds {name: (lower, upper)} as bounds on theta (the map is increasing)."""
    bounds = dict(bounds or {})
    unknown = sorted(set(bounds) - set(loss.tuned))
    if unknown:
        raise ValueError(f"`bounds` names {unknown}, which are not tuned; tuned: {list(loss.tuned)}.")
    lower, upper = [], []
    for name, (map_lower, map_upper) in zip(loss.tuned, loss.bounds, strict=True):
        lo, hi = bound_pair(bounds, name)
        if lo is not None and hi is not None and not lo < hi:
            raise ValueError(f"bounds for {name!r} must have lower < upper; got ({lo}, {hi}).")
        open_below = lo is None or lo <= (map_lower or 0.0)
        open_above = hi is None or (map_upper is not None and hi >= map_upper)
        lower.append(-np.inf if open_below else _inverse_map(float(lo), map_lower, map_upper))
        upper.append(np.inf if open_above else _inverse_map(float(hi), map_lower, map_upper))
    dtype = loss.state.positions.dtype
    return jnp.asarray(lower, dtype), jnp.asarray(upper, dtype)
