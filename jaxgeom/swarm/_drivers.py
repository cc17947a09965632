"""The drivers of one swarm, one function each: `_simulate_host` (jitted chunks, Qhull on the
host between them, overlapped with the graph-free work), `_simulate_callback` (one traced scan,
rebuilt through a callback or on the device) and `_simulate_split` (the walkers split over
devices, Qhull on the host where the device rebuild is not certified)."""

from __future__ import annotations

import contextlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from ..base._progress import close_bar, open_bar, raise_if_interrupted
from ..base._sharding import BATCH_AXIS, WALKER_AXIS, check_mesh, shard_walkers
from ..tessellation._delaunay import deferred_tiers
from ._divergence import _health, check_health
from ._dynamics import SwarmState
from ._history import _bulk_gap, _history
from ._observables import prepare_scutoid_trace, reads_tiers
from ._rebuild import grown, update_host
from ._steps import (
    _begin_step,
    _finish_and_begin,
    _is_traced,
    _measure_first,
    _observe_final,
    _progress,
    _run_callback,
    _run_chunk,
    _run_split,
)


class SimulationInterrupted(KeyboardInterrupt):
    """Ctrl-C during `simulate` (rebuild="host"): `state` and `history` are those of the steps
    completed before it (`steps` of `n_steps`), as `simulate` would have returned them."""

    def __init__(self, state, history: dict, steps: int, n_steps: int):
        super().__init__(f"simulate: interrupted at step {steps} of {n_steps}")
        self.state, self.history, self.steps, self.n_steps = state, history, steps, n_steps


def _simulate_host(fitness, state, params, n_steps, rebuild_every, observe, gap_every, k, progress):
    n_total = jnp.asarray(n_steps, jnp.int32)
    gaps, reallocations, seconds = [], 0, {"rebuild": 0.0, "steps": 0.0}
    bar, owned = open_bar(progress, n_steps, "simulate")
    first_step = int(state.step)  # the gap schedule counts the swarm's steps, across calls
    if gap_every and first_step % gap_every == 0:
        gaps.append((0,) + _bulk_gap(state.tess))
    opening, pending = _begin_step(params, state), []
    dtype = state.positions.dtype
    defer = not reads_tiers(params, observe)
    # How to compute the graph's tiers where its build left them out (`deferred_tiers`): neither
    # the steps nor the observables read them, so only the state returned gets them.
    tiers = None
    done = (state, tiers, 0, 0)  # the last consistent state, its tiers, steps, chunks: what Ctrl-C keeps
    try:
        for start in range(0, n_steps, rebuild_every):
            raise_if_interrupted()
            t0 = time.perf_counter()
            entering = state
            moved, obs, cells, moved_health = _run_chunk(
                fitness, params, entering, opening, jnp.asarray(start, jnp.int32), n_total, rebuild_every, observe
            )
            # Dispatched now, computed by XLA while the host runs Qhull below: none needs the new graph.
            state, opening = _finish_and_begin(fitness, params, moved)
            end = min(start + rebuild_every, n_steps)
            progress = _jit_progress(jnp.asarray(start, jnp.int32), n_total, dtype)
            first = _measure_first(fitness, params, entering, cells, progress, observe)
            pending.append((obs, first, end - start))
            jax.block_until_ready(moved.positions)
            codes = [*np.asarray(obs["_health"])[: end - start], int(moved_health)]
            if any(codes):  # let the dispatched graph-free work finish before raising (XLA aborted otherwise)
                jax.block_until_ready((state, opening, first))
            check_health(fitness, params, codes, start, entering)
            t1 = time.perf_counter()
            with deferred_tiers() if defer else contextlib.nullcontext([]) as later:
                moved, grew, n_moved = update_host(moved, k)  # the positions are final in `moved`
            tiers = later[0] if later else None
            if n_moved:  # walkers were moved apart: redo the graph-free work at their new positions
                state, opening = _finish_and_begin(fitness, params, moved)
            state = eqx.tree_at(
                lambda s: (s.tess, s.n_triangulator_fallbacks), state, (moved.tess, moved.n_triangulator_fallbacks)
            )
            if grew:  # a wider graph: the scutoid trace's rows widen with it
                state = prepare_scutoid_trace(state, observe)
            reallocations += grew
            seconds["steps"] += t1 - t0
            seconds["rebuild"] += time.perf_counter() - t1
            if gap_every and (first_step + end) % gap_every == 0:
                gaps.append((end,) + _bulk_gap(state.tess))
            done = (state, tiers, end, len(pending))
            if bar is not None:
                bar.update(end - start)
    except KeyboardInterrupt:
        close_bar(bar, owned)
        kept, kept_tiers, steps, n_chunks = done
        kept, history = _host_history(
            fitness,
            params,
            _resolved(kept, kept_tiers),
            pending[:n_chunks],
            observe,
            [g for g in gaps if g[0] <= steps],
            reallocations,
            seconds,
        )
        raise SimulationInterrupted(kept, history, steps, n_steps) from None
    close_bar(bar, owned)
    state = _resolved(state, tiers)
    return _host_history(fitness, params, state, pending, observe, gaps, reallocations, seconds, (n_steps, entering))


_jit_progress = jax.jit(_progress, static_argnums=2)  # one program (eagerly: three)


def _resolved(state, tiers):
    """`state` with its graph's real tiers, where its build left them out (`tiers` not None)."""
    return state if tiers is None else eqx.tree_at(lambda s: s.tess.tier, state, tiers(state.tess))


def _host_history(fitness, params, state, pending, observe, gaps, reallocations, seconds, check=None):
    """(state with its final observables, history) from the chunks' pending observables;
    `check` = (step, last sound state): the final state's health is checked too."""
    chunks = [
        {name: np.concatenate([np.asarray(first[name])[None], np.asarray(obs[name])[1:size]]) for name in observe}
        for obs, first, size in pending
    ]
    state, final = _observe_final(fitness, params, state, observe)
    if check is not None:
        check_health(fitness, params, [_health(state)], *check)
    series = {name: np.concatenate([c[name] for c in chunks] + [np.asarray(final[name])[None]]) for name in observe}
    return state, _history(series, gaps, reallocations, seconds, state, -1)


def _split_walkers(state: SwarmState, params, mesh, rebuild: str, checkpoint) -> SwarmState:
    """One swarm's state placed with its walker axis split over `mesh` (checked)."""
    if isinstance(mesh, Mesh) and BATCH_AXIS in mesh.axis_names and WALKER_AXIS not in mesh.axis_names:
        raise ValueError(
            "a mesh with a 'batch' axis splits a batch of swarms (jaxgeom.stack_swarms); this state "
            "is one swarm (positions (N, d)): split its walkers with mesh=jaxgeom.walker_mesh()."
        )
    check_mesh(mesh, state.positions.shape[0], "the number of walkers N", WALKER_AXIS)
    if rebuild != "device":
        raise ValueError(
            "splitting one swarm's walkers over devices needs the device rebuild: use "
            f"rebuild='device' with mesh=jaxgeom.walker_mesh() (got rebuild={rebuild!r}, which "
            "rebuilds the whole graph with Qhull in one place)."
        )
    if checkpoint or _is_traced(state, params):
        raise TypeError(
            "simulate(..., mesh=walker_mesh()) drives the split swarm from Python (graphs the device "
            "rebuild cannot certify are rebuilt by Qhull on the host), so it cannot run under jax.jit, "
            "jax.grad or checkpoint=True; differentiate ensembles (batch_mesh) or one device instead."
        )
    return shard_walkers(state, mesh, state.positions.shape[0])


def _simulate_split(fitness, state, params, n_steps, rebuild_every, observe, k, mesh):
    """`simulate` of one swarm with its walkers split over `mesh`: `_split_scan` from the first
    step not yet run, and a Qhull rebuild on the host (counted in `n_fallbacks`) wherever it stopped."""
    n, total = state.positions.shape[0], jnp.asarray(n_steps, jnp.int32)
    done, chunks, fallbacks, reallocations = 0, [], 0, 0
    while done < n_steps:
        entering = state
        state, stopped, obs = _run_split(
            fitness, params, state, total, jnp.asarray(done, jnp.int32), n_steps, observe, rebuild_every, k, mesh
        )
        ran = int(np.sum(np.asarray(obs["_live"])))
        chunks.append({name: np.asarray(values)[:ran] for name, values in obs.items()})
        check_health(fitness, params, [*chunks[-1]["_health"], int(_health(state))], done, entering)
        done += ran
        if bool(stopped):
            state, grew, _ = update_host(state, k)
            state = prepare_scutoid_trace(state, observe)
            state = shard_walkers(state, mesh, n)
            fallbacks, reallocations = fallbacks + 1, reallocations + grew
    state, last = _observe_final(fitness, params, state, observe)
    series = {name: np.concatenate([c[name] for c in chunks] + [np.asarray(last[name])[None]]) for name in observe}
    nan = {"rebuild": jnp.nan, "steps": jnp.nan}
    return state, _history(series, [], reallocations, nan, state, -1, fallbacks)


def _simulate_callback(fitness, state, params, n_steps, rebuild_every, observe, k, mode, checkpoint=False):
    traced = _is_traced(state, params)
    total, reallocations = jnp.asarray(n_steps, jnp.int32), 0
    while True:
        final, obs = _run_callback(fitness, params, state, total, n_steps, observe, rebuild_every, k, mode, checkpoint)
        final, last = _observe_final(fitness, params, final, observe)
        if traced or not bool(final.tess.overflow):  # traced: recorded in `diverged_step` (health)
            break
        state = prepare_scutoid_trace(eqx.tree_at(lambda s: s.tess, state, grown(state.tess)), observe)
        reallocations += 1
    codes, series, diverged, fallbacks = _callback_summary(obs, last, final, observe)
    if not traced:
        check_health(fitness, params, codes, 0, state)
    nan = {"rebuild": jnp.nan, "steps": jnp.nan}
    return final, _history(series, [], reallocations, nan, final, diverged, fallbacks)


@eqx.filter_jit
def _callback_summary(obs: dict, last: dict, final: SwarmState, observe: tuple):
    """(health codes, observable series, first diverged step or -1, Qhull fallbacks) of a
    callback-mode run: under a trace nothing can be raised, so divergence is the first step
    whose state failed `health`."""
    codes = jnp.concatenate([obs["_health"], _health(final)[None]])
    series = {name: jnp.concatenate([obs[name], last[name][None]]) for name in observe}
    diverged = jnp.where(jnp.any(codes != 0), jnp.argmax(codes != 0), -1)
    return codes, series, diverged, jnp.sum(obs["_fallback"], dtype=jnp.int32)
