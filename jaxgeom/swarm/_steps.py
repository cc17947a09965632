"""The step bodies every driver shares, jitted: a host chunk of `rebuild_every` steps between
two host rebuilds (`_host_chunk`), the traced step with its in-trace rebuild (`_traced_step`,
scanned by `_callback_scan`, nested-checkpointed by `checkpointed_scan`), the split swarm's
scan (`_split_scan`), and the graph-free work run while the host triangulates."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from ._dynamics import (
    StepStart,
    SwarmParams,
    SwarmState,
    begin_step,
    finish_step,
    health,
    move_on_graph,
)
from ._observables import cell_fields, measure, observe_state, refresh_cells
from ._rebuild import update_in_trace, update_on_device


def _host_chunk(
    fitness, params: SwarmParams, state: SwarmState, first: StepStart, start, n_total, length: int, observe: tuple
):
    """`length` (= rebuild_every) steps on one graph from global step `start`, between two host
    rebuilds; steps >= n_total are skipped. `first` is `begin_step` of the first step,
    computed ahead. Two pieces of work need no new graph and are left to the host loop, for
    XLA to run while Qhull runs: the first state's observables (NaN here, `_measure_first`)
    and the last step's closing kick (`_finish_and_begin`).
    Returns `(state, observables, cells, health)`, `cells` the first state's refreshed
    `cell_fields`, `health` the final state's: computed here, not in a call of its own after
    the graph-free work is queued, which XLA would run first and so delay the host rebuild."""
    dtype = state.positions.dtype
    entering = refresh_cells(params, state, observe)
    nan = {name: jnp.asarray(jnp.nan, dtype) for name in observe}

    def body(st, i):
        s = start + i
        progress = _progress(s, n_total, dtype)
        if length == 1:  # rebuild every step: compile only the branches taken
            return move_on_graph(fitness, params, st, first, progress, True), dict(nan, _health=health(st))
        last = (i == length - 1) | (s == n_total - 1)  # clone only before a rebuild
        st, obs = jax.lax.cond(
            i == 0, lambda q: (q, nan), lambda q: observe_state(fitness, params, q, progress, observe), st
        )

        def advance(q):
            opening = jax.lax.cond(i == 0, lambda r: first, lambda r: begin_step(params, r), q)
            q = move_on_graph(fitness, params, q, opening, progress, last)
            return jax.lax.cond(last, lambda r: r, lambda r: finish_step(fitness, params, r), q)

        return jax.lax.cond(s < n_total, advance, lambda q: q, st), dict(obs, _health=health(st))

    final, obs = jax.lax.scan(body, entering, jnp.arange(length, dtype=jnp.int32))
    return final, obs, cell_fields(entering), health(final)


def _callback_scan(
    fitness,
    params: SwarmParams,
    state: SwarmState,
    n_total,
    n_steps: int,
    observe: tuple,
    rebuild_every: int,
    k: int,
    mode: str = "callback",
    checkpoint: bool = False,
):
    """All `n_steps` steps in one scan, observing the state entering each, the graph rebuilt
    in the trace every `rebuild_every` steps (`update_in_trace`, or `update_on_device` for
    mode "device", which records its fallbacks as `_fallback`). Returns `(state, observables)`.
    `n_total` is `n_steps` as a traced array, so that the schedules' clock is computed exactly
    as in the host chunks (a constant divisor could be folded differently). `checkpoint`:
    nested rematerialisation (`checkpointed_scan`), for gradients through long runs."""
    if mode == "device":
        update = lambda r: update_on_device(r, k)
    else:
        update = lambda r: (update_in_trace(r, k), jnp.asarray(False))
    body = lambda st, i: _traced_step(fitness, params, st, i, n_total, observe, rebuild_every, update)
    if checkpoint:
        return checkpointed_scan(body, state, n_steps)
    return jax.lax.scan(body, state, jnp.arange(n_steps, dtype=jnp.int32))


def _traced_step(fitness, params: SwarmParams, st: SwarmState, i, n_total, observe: tuple, rebuild_every: int, update):
    """Step `i` of a traced run: the observables of the state entering it, the step, and the
    graph rebuilt by `update(state) -> (state, fell_back)` when the schedule says so. Returns
    `(state, observables)` with `_health` (of the entering state) and `_fallback`."""
    progress = _progress(i, n_total, st.positions.dtype)
    st, obs = observe_state(fitness, params, st, progress, observe)
    rebuild = ((i + 1) % rebuild_every == 0) | (i == n_total - 1)  # clone only before a rebuild
    q = finish_step(fitness, params, move_on_graph(fitness, params, st, begin_step(params, st), progress, rebuild))
    q, fell_back = jax.lax.cond(rebuild, update, lambda r: (r, jnp.asarray(False)), q)
    return q, dict(obs, _health=health(st), _fallback=fell_back)


def checkpointed_scan(body, carry, n_steps: int):
    """`jax.lax.scan(body, carry, arange(n_steps))` with two levels of rematerialisation:
    chunks of ceil(sqrt(n_steps)) steps, each step checkpointed inside its chunk, so the
    backward pass stores O(sqrt(n_steps)) carries instead of every step's intermediates
    (Griewank's sqrt(T) checkpointing). Steps past `n_steps` in the last chunk are skipped."""
    size = max(1, math.isqrt(max(n_steps - 1, 0)) + 1)
    n_chunks = -(-n_steps // size)
    step = jax.checkpoint(body)
    out = jax.eval_shape(body, carry, jnp.asarray(0, jnp.int32))[1]

    def guarded(st, i):
        skip = lambda s, _: (s, jax.tree_util.tree_map(lambda o: jnp.zeros(o.shape, o.dtype), out))
        return jax.lax.cond(i < n_steps, step, skip, st, i)

    chunk = jax.checkpoint(lambda st, ids: jax.lax.scan(guarded, st, ids))
    ids = jnp.arange(n_chunks * size, dtype=jnp.int32).reshape(n_chunks, size)
    final, obs = jax.lax.scan(chunk, carry, ids)
    return final, jax.tree_util.tree_map(lambda o: o.reshape((n_chunks * size,) + o.shape[2:])[:n_steps], obs)


def _progress(step, n_total, dtype):
    """Fraction of the run done when `step` starts (0 ... 1), the schedules' clock."""
    return jnp.asarray(step).astype(dtype) / jnp.maximum(jnp.asarray(n_total) - 1, 1).astype(dtype)


# jax.jit, not eqx.filter_jit: every leaf is an array, and jax.jit's call returns at once
# (eqx.filter_jit's blocks until the chunk is done), which the overlap of graph-free work
# with Qhull relies on; fitness and the loop shape are static.
_run_chunk = jax.jit(_host_chunk, static_argnames=("fitness", "length", "observe"))
_run_callback = jax.jit(
    _callback_scan, static_argnames=("fitness", "n_steps", "observe", "rebuild_every", "k", "mode", "checkpoint")
)
_begin_step = jax.jit(begin_step)


@functools.partial(jax.jit, static_argnums=(0, 5))
def _measure_first(fitness, params: SwarmParams, state: SwarmState, cells, progress, observe: tuple):
    """The observables of a host chunk's first state (`state` as it entered the chunk, `cells`
    its refreshed `cell_fields` from `_host_chunk`)."""
    new = eqx.tree_at(cell_fields, state, cells)
    return measure(fitness, params, new, progress, observe)


@functools.partial(jax.jit, static_argnums=0)
def _finish_and_begin(fitness, params: SwarmParams, moved: SwarmState) -> tuple[SwarmState, StepStart]:
    """The graph-free work between two chunks: the last step's closing kick and the next
    step's opening. The host runs Qhull meanwhile (XLA executes this asynchronously)."""
    state = finish_step(fitness, params, moved)
    return state, begin_step(params, state)


@eqx.filter_jit
def _observe_final(fitness, params, state, observe):
    return observe_state(fitness, params, state, jnp.asarray(1.0, state.positions.dtype), observe)


def _is_traced(*trees) -> bool:
    """Whether any leaf is a tracer (simulate called under jax.jit, jax.grad or jax.vmap)."""
    return any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree_util.tree_leaves(trees))


def _split_scan(
    fitness,
    params: SwarmParams,
    state: SwarmState,
    n_total,
    first,
    n_steps: int,
    observe: tuple,
    rebuild_every: int,
    k: int,
    mesh,
):
    """Steps first, first + 1, ... (< n_total) of one swarm with its walkers split over `mesh`,
    each rebuild on the device with the cells split. A rebuild that is not certified stops the
    run after its step, for the host to rebuild with Qhull: a callback inside a program split
    over devices would leave the devices waiting on each other (on CPU it deadlocks). Returns
    `(state, stopped, observables)`, `_live` marking the steps run."""
    update = lambda r: update_on_device(r, k, mesh=mesh, qhull_in_trace=False)
    step = lambda st, i: _traced_step(fitness, params, st, i, n_total, observe, rebuild_every, update)
    shapes = jax.eval_shape(step, state, first)[1]
    skip = lambda st, _: (st, jax.tree_util.tree_map(lambda o: jnp.zeros(o.shape, o.dtype), shapes))

    def body(carry, j):
        st, stopped = carry
        live = (first + j < n_total) & ~stopped
        st, obs = jax.lax.cond(live, step, skip, st, first + j)
        return (st, stopped | obs["_fallback"]), dict(obs, _live=live)

    (final, stopped), obs = jax.lax.scan(body, (state, jnp.asarray(False)), jnp.arange(n_steps, dtype=jnp.int32))
    return final, stopped, obs


_run_split = jax.jit(_split_scan, static_argnames=("fitness", "n_steps", "observe", "rebuild_every", "k", "mesh"))
