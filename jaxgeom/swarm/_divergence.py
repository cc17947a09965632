"""Divergence is an error, never silent: health codes of the states, `SimulationDiverged`
with the step and the likely cause (dt against the landscape's stiffness, a singular metric)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..geometry._metric import eigh
from ._dynamics import (
    ALL_DEAD,
    NONFINITE,
    OVERFLOWED_GRAPH,
    REBUILD_FAILED,
    RUNAWAY,
    RUNAWAY_RADII,
    SwarmParams,
    SwarmState,
    health,
    metric_field,
    runaway_radius,
)


class SimulationDiverged(FloatingPointError):
    """The swarm left the representable or plausible range (`simulate` names the step and cause)."""


_health = jax.jit(health)
_metric_field = eqx.filter_jit(metric_field)


@eqx.filter_jit
def _largest_curvature_and_slope(fitness, x):
    """Per walker: the largest Hessian eigenvalue of V and |grad V|."""
    curvature = jax.vmap(lambda p: eigh(jax.hessian(fitness)(p))[0][-1])(x)  # no batched LAPACK
    return curvature, jnp.linalg.norm(jax.vmap(jax.grad(fitness))(x), axis=1)


def check_health(fitness, params: SwarmParams, codes, first_step: int, before: SwarmState) -> None:
    """Raise `SimulationDiverged` at the first non-zero health code (`codes[i]` belongs to the
    state entering step `first_step + i`); `before` is the last state known to be sound."""
    bad = np.flatnonzero(np.asarray(codes))
    if bad.size:
        step = first_step + int(bad[0])
        raise SimulationDiverged(divergence_message(fitness, params, before, step, int(np.asarray(codes)[bad[0]])))


def divergence_message(fitness, params: SwarmParams, before: SwarmState, step: int, code: int) -> str:
    """What went wrong by `step` (health bits `code`) and its likely cause, judged on `before`."""
    what = []
    if code & NONFINITE:
        what.append("walkers have non-finite positions or velocities")
    if code & RUNAWAY:
        what.append(
            f"walkers lie farther than {float(runaway_radius(before)):.3g} ({RUNAWAY_RADII:g} initial "
            "swarm radii) from the swarm's centre"
        )
    if code & ALL_DEAD:
        what.append("no walker has a finite fitness")
    if code & OVERFLOWED_GRAPH:
        what.append(
            "the graph outgrew its capacity (build the state with init_swarm(..., capacity=a larger jaxgeom.Capacity))"
        )
    if code & REBUILD_FAILED:
        what.append("Qhull could not triangulate the walkers (degenerate or non-finite positions)")
    return (
        f"simulate: the swarm diverged by step {step} (t = {step * float(params.dt):.4g}): "
        f"{'; '.join(what)}. {likely_cause(fitness, params, before)}"
    )


def likely_cause(fitness, params: SwarmParams, state: SwarmState) -> str:
    """One sentence: why a swarm diverged from `state`, judged there (a singular metric, dt
    against the landscape's stiffness, or forces that outgrew the step)."""
    everywhere = np.asarray(state.positions)
    x = jnp.asarray(everywhere[np.isfinite(everywhere).all(axis=1)])
    if params.needs_metric:
        g = np.asarray(_metric_field(fitness, params, params.eps_sigma * state.eps_factor, x))
        lam = np.linalg.eigvalsh(np.where(np.isfinite(g), g, 0.0))[:, 0]
        if not np.isfinite(g).all() or lam.min() <= 0:
            zero = int(np.sum(np.all(g == 0, axis=(1, 2))))
            uses = "the anisotropic noise D = g^-1 is" if params.anisotropic else f"the {params.weights!r} weights are"
            return (
                f"Likely cause: the Hessian metric g = floor(H) + eps_Sigma I (eps_sigma = "
                f"{float(params.eps_sigma):.3g}) is singular or not positive definite at "
                f"{int(np.sum(lam <= 0) + np.sum(~np.isfinite(g).all(axis=(1, 2))))} walker(s)"
                f"{f', the zero metric at {zero}' if zero else ''} (smallest eigenvalue {lam.min():.3g}), so "
                f"{uses} undefined; raise eps_sigma or use floor='softabs'."
            )
    curvatures, slopes = map(np.asarray, _largest_curvature_and_slope(fitness, x))
    curvature = float(np.max(curvatures[np.isfinite(curvatures)], initial=0.0))
    slope = float(np.max(slopes[np.isfinite(slopes)], initial=0.0))
    omega_dt = float(params.dt) * np.sqrt(max(curvature, 0.0))
    if omega_dt > 2.0:
        return (
            f"Likely cause: dt = {float(params.dt):.3g} is too large for this landscape (|grad V| reaches "
            f"{slope:.1e} and the largest Hessian eigenvalue {curvature:.1e} at the walkers of step "
            f"{int(state.step)}): dt * sqrt(largest eigenvalue) = {omega_dt:.3g}, and the kicks are stable only "
            f"below 2; reduce dt below {2.0 / np.sqrt(curvature):.3g}."
        )
    return (
        "Likely cause: the forces grew faster than the step resolves (the landscape is steep or unbounded "
        f"below where the walkers went; dt = {float(params.dt):.3g}); reduce dt, or bound the landscape."
    )
