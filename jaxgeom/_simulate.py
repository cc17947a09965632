"""`jaxgeom.simulate`: jax.lax.scan over swarm steps, with the tessellation rebuilt as walkers move.

Three rebuild strategies (why, with the measurements: bench/README.md):

- `rebuild="host"` (default) runs `rebuild_every` steps in one jitted `lax.scan` chunk
  (`_host_chunk`) and rebuilds the graph with Qhull on the host between chunks
  (`jaxgeom._rebuild.update_host`). Between chunks the host first dispatches the work
  that needs no new graph (the last step's closing kick, the next step's opening with
  its random draws and clone decisions, the observables of the chunk's first state),
  so XLA computes it while Qhull runs. Only this loop can grow a too-small capacity
  (a new bucket, one recompilation) instead of truncating, compute the spectral gap
  every M steps and show a progress bar; it compiles per chunk length, not per `n_steps`.
- `rebuild="callback"` (`_callback_scan`) rebuilds inside the scan through
  `jax.pure_callback` (`jaxgeom._rebuild.update_in_trace`): the whole simulation is
  one jittable, differentiable function of the parameters (tuning nu and eps_Sigma
  with optimistix). Its capacity cannot grow inside the scan, so an overflow re-runs
  the simulation with larger capacities when called eagerly; under a trace it is recorded
  like a divergence (`diverged_step`, so a `simulation_loss` is +inf there).
- `rebuild="device"` is the same scan with the graph rebuilt in JAX (`jaxgeom.rebuild`,
  2D non-periodic Delaunay swarms): no host round trip on the steps it certifies; a step
  it cannot certify falls back to the callback's Qhull and is counted (`n_fallbacks`).
  On CPU it is slower than the callback today (bench/README.md); it is the route to GPUs.
"""

from __future__ import annotations

import functools
import math
import time
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg
from jax.sharding import Mesh

from ._cellclip import describe_graph, rebuilds_on_device
from ._checks import check_choice, check_min_points, host_points, real_array
from ._delaunay import delaunay
from ._dynamics import (ALL_DEAD, NONFINITE, OVERFLOWED_GRAPH, REBUILD_FAILED, RUNAWAY, RUNAWAY_RADII, StepStart,
                        SwarmParams, SwarmState, begin_step, finish_step, fitness_and_force, health, metric_field,
                        move_on_graph, runaway_radius)
from ._graph import Tessellation
from ._metric import eigh
from ._observables import OBSERVABLES, cell_fields, measure, observe_state, refresh_cells
from ._progress import check_progress, close_bar, open_bar
from ._rebuild import GRAPHS, allocate_graph, grown, update_host, update_in_trace, update_on_device
from ._sharding import BATCH_AXIS, WALKER_AXIS, check_mesh, over_batch, shard_walkers
from ._spectral import bulk_spectral_gap, gap_rounding_level
from ._weights import mean_nearest_neighbor_distance

REBUILD_MODES = ("host", "callback", "device")


def check_callable_fitness(fitness) -> None:
    if not callable(fitness):
        raise TypeError(f"`fitness` must be a JAX function x (d,) -> scalar V(x); got {type(fitness).__name__}.")


def check_fitness(fitness, x: np.ndarray) -> None:
    """`fitness` must map one walker (d,) to a finite scalar at every initial walker."""
    check_callable_fitness(fitness)
    try:
        values = jax.vmap(fitness)(jnp.asarray(x))
    except Exception as err:  # noqa: BLE001 - re-raised with the fix
        raise TypeError(f"`fitness` must map one walker x of shape (d,) = ({x.shape[1]},) to a scalar with "
                        f"jax.numpy operations; calling it failed: {err}") from err
    if jnp.shape(values) != (len(x),):
        raise TypeError(f"`fitness` must return a scalar per walker (shape ()); it returned shape "
                        f"{jnp.shape(values)[1:]} for one walker.")
    bad = np.flatnonzero(~np.isfinite(np.asarray(values)))
    if bad.size:
        raise ValueError(f"`fitness` is NaN or inf at {bad.size} initial walker(s), first rows "
                         f"{bad[:5].tolist()}; move them into the landscape's domain.")


class SimulationDiverged(FloatingPointError):
    """The swarm left the representable or plausible range (`simulate` names the step and cause)."""


def _as_key(key):
    """An int seed or a JAX PRNG key (typed, or the legacy uint32 (2,) array)."""
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        return jax.random.PRNGKey(key)
    arr = key if isinstance(key, jax.Array) else None
    if arr is not None and (jnp.issubdtype(arr.dtype, jax.dtypes.prng_key) or (arr.dtype == jnp.uint32 and arr.shape == (2,))):
        return key
    raise TypeError(f"`key` must be an int seed or a jax.random key (jax.random.PRNGKey(seed)); got {key!r}.")


def init_swarm(fitness, positions, velocities=None, *, key=0, graph: str = "delaunay", k: int = 12,
               capacity=None) -> SwarmState:
    """The initial [`jaxgeom.SwarmState`][] of a swarm (host: builds its first graph).

    **Arguments:**

    - `fitness`: JAX function x (d,) -> V(x), finite at every walker.
    - `positions`: (N, d) float array (float32 or float64: the simulation's dtype).
    - `velocities`: (N, d), default zeros.
    - `key`: int seed or `jax.random` key.
    - `graph`: "delaunay" (d = 2, 3) or "knn" (any d; `k` neighbours).
    - `capacity`: pin Delaunay capacities (`CapacityError` if the first graph does not
      fit; later rebuilds in `simulate` grow them); default: buckets with headroom.
    """
    x = host_points(positions, "positions", func="jaxgeom.init_swarm")
    check_choice(graph, "graph", GRAPHS)
    check_min_points(len(x), x.shape[1] + 2, "positions", "a swarm")
    v = np.zeros_like(x) if velocities is None else real_array(velocities, "velocities")
    if v.shape != x.shape or not np.issubdtype(v.dtype, np.floating):
        raise ValueError(f"`velocities` must be a float array of shape (N, d) = {x.shape} like `positions`; "
                         f"got {v.dtype} {v.shape}.")
    if not np.isfinite(v).all():
        raise ValueError(f"`velocities` has NaN or inf entries in {int((~np.isfinite(v).all(axis=1)).sum())} "
                         "row(s). Repair them or start from velocities=None (zeros).")
    key = _as_key(key)
    check_fitness(fitness, x)
    if capacity is not None and graph == "delaunay":
        tess = delaunay(x, capacity=capacity)  # pinned: raises CapacityError when the graph does not fit
    else:
        tess, _, x, _ = allocate_graph(x, graph, k, None)
    xj = jnp.asarray(x)  # float64 input becomes float32 unless jax_enable_x64 is set
    dtype = xj.dtype
    values, force = fitness_and_force(fitness, xj)
    n = len(x)
    zero = jnp.asarray(0, jnp.int32)
    unmeasured = jnp.full(n, jnp.nan, dtype)
    return SwarmState(xj, jnp.asarray(v, dtype), values, force, jnp.isfinite(values), jnp.zeros(n, bool),
                      unmeasured, jnp.zeros(n, bool), unmeasured, jnp.zeros(n, bool), jnp.asarray(-1, jnp.int32),
                      key, tess, zero,
                      jnp.asarray(mean_nearest_neighbor_distance(tess), dtype), jnp.asarray(1.0, dtype), zero, zero)


def _host_chunk(fitness, params: SwarmParams, state: SwarmState, first: StepStart, start, n_total, length: int,
                observe: tuple):
    """`length` (= rebuild_every) steps on one graph from global step `start`, between two host
    rebuilds; steps >= n_total are skipped. `first` is `begin_step` of the first step,
    computed ahead. Two pieces of work need no new graph and are left to the host loop, for
    XLA to run while Qhull runs: the first state's observables (NaN here, `_measure_first`)
    and the last step's closing kick (`_finish_and_begin`).
    Returns `(state, observables, cells)`, `cells` the first state's refreshed `cell_fields`."""
    dtype = state.positions.dtype
    entering = refresh_cells(params, state, observe)
    nan = {name: jnp.asarray(jnp.nan, dtype) for name in observe}

    def body(st, i):
        s = start + i
        progress = _progress(s, n_total, dtype)
        if length == 1:  # rebuild every step: compile only the branches taken
            return move_on_graph(fitness, params, st, first, progress, True), dict(nan, _health=health(st))
        last = (i == length - 1) | (s == n_total - 1)  # clone only before a rebuild
        st, obs = jax.lax.cond(i == 0, lambda q: (q, nan), lambda q: observe_state(fitness, params, q, progress, observe), st)

        def advance(q):
            opening = jax.lax.cond(i == 0, lambda r: first, lambda r: begin_step(params, r), q)
            q = move_on_graph(fitness, params, q, opening, progress, last)
            return jax.lax.cond(last, lambda r: r, lambda r: finish_step(fitness, params, r), q)

        return jax.lax.cond(s < n_total, advance, lambda q: q, st), dict(obs, _health=health(st))

    final, obs = jax.lax.scan(body, entering, jnp.arange(length, dtype=jnp.int32))
    return final, obs, cell_fields(entering)


def _callback_scan(fitness, params: SwarmParams, state: SwarmState, n_total, n_steps: int, observe: tuple,
                   rebuild_every: int, k: int, mode: str = "callback", checkpoint: bool = False):
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


def _traced_step(fitness, params: SwarmParams, st: SwarmState, i, n_total, observe: tuple, rebuild_every: int,
                 update):
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
_run_callback = jax.jit(_callback_scan, static_argnames=("fitness", "n_steps", "observe", "rebuild_every", "k", "mode",
                                                         "checkpoint"))
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


def _check_simulate_args(fitness, state, params, n_steps, rebuild_every, observe, rebuild, spectral_gap_every):
    check_callable_fitness(fitness)
    if not isinstance(state, SwarmState):
        raise TypeError("`state` must be a jaxgeom.SwarmState; build one with jaxgeom.init_swarm(fitness, positions).")
    if not isinstance(params, SwarmParams):
        raise TypeError("`params` must be a jaxgeom.SwarmParams.")
    for name, value in (("n_steps", n_steps), ("rebuild_every", rebuild_every)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"`{name}` must be an integer >= 1; got {value!r}.")
    for name in observe:
        check_choice(name, "observable", OBSERVABLES)
    check_choice(rebuild, "rebuild", REBUILD_MODES)
    if rebuild == "host" and _is_traced(state, params):
        raise TypeError("simulate(rebuild='host') rebuilds the graph with Qhull on the host between jitted chunks, "
                        "so it cannot run under jax.jit, jax.grad or jax.vmap. Use rebuild='callback' for a "
                        "traceable, differentiable simulation.")
    if rebuild == "device" and not rebuilds_on_device(state.tess):
        raise ValueError("simulate(rebuild='device') rebuilds 2D Delaunay swarms on the device so far; this swarm's "
                         f"graph is {describe_graph(state.tess)}. Use rebuild='callback' (traceable) or 'host'.")
    if params.volume_weighting and state.tess.simplices is None:
        raise ValueError("`volume_weighting=True` needs Voronoi volumes, which a k-NN swarm does not have; "
                         "use init_swarm(..., graph='delaunay') or volume_weighting=False.")
    if spectral_gap_every and (spectral_gap_every % rebuild_every or rebuild != "host"):
        raise ValueError("`spectral_gap_every` must be a multiple of `rebuild_every` and needs rebuild='host' "
                         f"(the gap is computed on the host after a rebuild); got {spectral_gap_every}.")


def simulate(fitness, state: SwarmState, params: SwarmParams, *, n_steps: int, rebuild_every: int = 1,
             observe: tuple[str, ...] = OBSERVABLES, rebuild: str = "host", spectral_gap_every: int = 0,
             progress=False, checkpoint: bool = False, mesh=None):
    """Run `n_steps` swarm steps (`jax.lax.scan`), rebuilding the tessellation as walkers move.

    **Arguments:**

    - `fitness`: the landscape V used to build `state` (same function object: it
      is a static argument of the compiled step).
    - `state`, `params`: [`jaxgeom.SwarmState`][] (from `init_swarm`) and [`jaxgeom.SwarmParams`][].
    - `n_steps`: number of steps; `rebuild_every`: steps between graph rebuilds
      (between rebuilds the graph keeps its topology and follows the walkers;
      cloning happens on the last step before each rebuild).
    - `observe`: names from `OBSERVABLES`, recorded for the state entering every
      step and for the final state (n_steps + 1 values, times 0, dt, ...).
    - `rebuild`: "host" (default: fastest on CPU), "callback" (jittable and differentiable
      end to end, vmap runs the lanes' Qhull calls one after another) or "device" (the
      same, with the 2D graph rebuilt in JAX and Qhull only on the steps the device rebuild
      cannot certify; module docstring).
    - `spectral_gap_every`: M > 0 records the spectral gap of the largest connected
      component (`bulk_spectral_gap`) and the number of components at every step whose
      count `state.step` is a multiple of M (host, rebuild="host"; a continued call keeps
      the schedule); a gap that fails to converge is NaN with a warning.
    - `progress`: a `tqdm.auto` progress bar (rebuild="host"): False (default), True,
      "auto" (shown in a terminal or a notebook, silent otherwise) or a tqdm bar of the
      caller's, advanced by `n_steps` and left open (one bar over several calls).
    - `checkpoint`: with rebuild="callback" or "device", rematerialise the steps in the
      backward pass (nested sqrt(n_steps) checkpointing), so the memory of `jax.grad`
      through the run grows like sqrt(n_steps) instead of n_steps, for about two more
      forward passes of time; the forward result is unchanged (`jaxgeom.simulation_loss`
      turns it on).
    - `mesh`: for a batch of swarms (`jaxgeom.stack_swarms`: every array with a leading
      (B,) axis; rebuild="callback" or "device"), a `jax.sharding.Mesh` with a "batch" axis
      (`jaxgeom.batch_mesh()`) splits the B swarms over its devices with `jax.shard_map`;
      None runs them under `vmap` on one device. Both give the same results (bitwise on CPU).
      For one swarm (rebuild="device", 2D), a mesh with a "walkers" axis
      (`jaxgeom.walker_mesh()`, N a multiple of its devices) splits the walkers: each device
      clips its share of the cells in every rebuild and runs the step's per-walker kernels
      for its walkers; the same graphs as one device, positions equal to rounding. Graphs the
      device rebuild cannot certify are rebuilt by Qhull on the host between scans, so this
      mode cannot run under jax.jit / jax.grad.

    **Returns:**

    `(final_state, history)`, history a dict of JAX arrays with the same keys in both
    rebuild modes: each observable (n_steps + 1,); `spectral_gap_step` (index into the
    observables), `spectral_gap`, `spectral_components` and `spectral_gap_rounding` (the
    gap is below float64 resolution, `gap_rounding_level`: read it as "< that level") (one
    entry per gap computed; empty with rebuild="callback");
    `n_reallocations` (capacity growths); `n_fallbacks` (rebuild="device": steps rebuilt
    by Qhull because the device rebuild was not certified; 0 otherwise); wall-clock `seconds_rebuild` / `seconds_steps`
    (NaN with rebuild="callback"); `n_separated` (walkers moved apart for Qhull);
    `diverged_step` (-1, or under a trace the first step whose state failed: non-finite,
    runaway, all dead, a failed rebuild, or a graph that outgrew its capacity).
    For a batch: the same with a leading (B,) axis on every array of both.
    """
    observe = tuple(observe)
    if is_batch(state):
        return _simulate_batch(fitness, state, params, n_steps=n_steps, rebuild_every=rebuild_every,
                               observe=observe, rebuild=rebuild, checkpoint=checkpoint, mesh=mesh,
                               spectral_gap_every=spectral_gap_every)
    check_progress(progress)
    _check_simulate_args(fitness, state, params, n_steps, rebuild_every, observe, rebuild, spectral_gap_every)
    if not isinstance(checkpoint, bool):
        raise TypeError(f"`checkpoint` must be True or False; got {checkpoint!r}.")
    if checkpoint and rebuild == "host":
        raise ValueError("`checkpoint=True` serves gradients through a traced run: use it with rebuild='callback' "
                         "or 'device' (rebuild='host' cannot be differentiated).")
    k = state.tess.neighbors.shape[1]  # a k-NN swarm keeps its k (unused by Delaunay rebuilds)
    if mesh is not None:
        state = _split_walkers(state, params, mesh, rebuild, checkpoint)
        return _simulate_split(fitness, state, params, n_steps, rebuild_every, observe, k, mesh)
    if rebuild in ("callback", "device"):
        return _simulate_callback(fitness, state, params, n_steps, rebuild_every, observe, k, rebuild, checkpoint)
    return _simulate_host(fitness, state, params, n_steps, rebuild_every, observe, spectral_gap_every, k, progress)


def is_batch(state) -> bool:
    """Whether `state` is a stack of swarms (positions (B, N, d))."""
    return isinstance(state, SwarmState) and state.positions.ndim == 3


def stack_swarms(states) -> SwarmState:
    """One `SwarmState` holding several swarms of the same shape along a leading (B,) axis, for
    `simulate(..., rebuild="callback")` and `mesh=`. The swarms need equal capacities: build
    them with `init_swarm(..., capacity=jaxgeom.Capacity(...))` (Delaunay) or the same k."""
    states = list(states)
    if not states or not all(isinstance(s, SwarmState) and not is_batch(s) for s in states):
        raise TypeError("`states` must be a non-empty sequence of single-swarm jaxgeom.SwarmState (init_swarm).")
    structures = {jax.tree_util.tree_structure(s) for s in states}
    shapes = {tuple(leaf.shape for leaf in jax.tree_util.tree_leaves(s)) for s in states}
    if len(structures) > 1 or len(shapes) > 1:
        raise ValueError("the swarms differ in walkers, dimension or graph capacity; build every one with the same "
                         "N and init_swarm(..., capacity=jaxgeom.Capacity(simplices=S, neighbors=K)).")
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *states)


def _simulate_batch(fitness, state, params, *, n_steps, rebuild_every, observe, rebuild, checkpoint, mesh,
                    spectral_gap_every):
    """`simulate` of every swarm of a batch: vmap, split over `mesh` when given (no progress bar:
    one traced program)."""
    if rebuild == "host":
        raise ValueError("a batch of swarms runs inside one traced program: use rebuild='callback' or 'device' "
                         "(rebuild='host' drives one swarm from Python).")
    lane = jax.tree_util.tree_map(lambda leaf: leaf[0], state)
    _check_simulate_args(fitness, lane, params, n_steps, rebuild_every, observe, rebuild, spectral_gap_every)
    check_mesh(mesh, state.positions.shape[0], "the number of swarms B")
    options = (("n_steps", n_steps), ("rebuild_every", rebuild_every), ("observe", observe), ("rebuild", rebuild),
               ("checkpoint", checkpoint))
    return _run_lanes(fitness, state, params, mesh, options)


@eqx.filter_jit
def _run_lanes(fitness, state, params, mesh, options):
    return over_batch(lambda st, p: simulate(fitness, st, p, **dict(options)), mesh)(state, params)


_health = jax.jit(health)


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
        what.append(f"walkers lie farther than {float(runaway_radius(before)):.3g} ({RUNAWAY_RADII:g} initial "
                    "swarm radii) from the swarm's centre")
    if code & ALL_DEAD:
        what.append("no walker has a finite fitness")
    if code & OVERFLOWED_GRAPH:
        what.append("the graph outgrew its capacity (build the state with init_swarm(..., capacity=a larger "
                    "jaxgeom.Capacity))")
    if code & REBUILD_FAILED:
        what.append("Qhull could not triangulate the walkers (degenerate or non-finite positions)")
    return (f"simulate: the swarm diverged by step {step} (t = {step * float(params.dt):.4g}): "
            f"{'; '.join(what)}. {_likely_cause(fitness, params, before)}")


def _likely_cause(fitness, params: SwarmParams, state: SwarmState) -> str:
    x = np.asarray(state.positions)
    x = jnp.asarray(x[np.isfinite(x).all(axis=1)])
    if params.anisotropic:
        g = np.asarray(metric_field(fitness, params, params.eps_sigma * state.eps_factor, x))
        lam = np.linalg.eigvalsh(np.where(np.isfinite(g), g, 0.0))[:, 0]
        if not np.isfinite(g).all() or lam.min() <= 0:
            return (f"Likely cause: the Hessian metric is singular or not positive definite at "
                    f"{int(np.sum(lam <= 0) + np.sum(~np.isfinite(g).all(axis=(1, 2))))} walker(s) "
                    f"(smallest eigenvalue {lam.min():.3g}), so the anisotropic noise D = g^-1 is undefined; "
                    "raise eps_sigma or use floor='softabs'.")
    curvature = np.asarray(jax.vmap(lambda p: eigh(jax.hessian(fitness)(p))[0][-1])(x))  # no batched LAPACK
    curvature = float(np.max(curvature[np.isfinite(curvature)], initial=0.0))
    omega_dt = float(params.dt) * np.sqrt(max(curvature, 0.0))
    if omega_dt > 2.0:
        return (f"Likely cause: dt = {float(params.dt):.3g} is too large for this landscape: dt * sqrt(largest "
                f"Hessian eigenvalue) = {omega_dt:.3g} at step {int(state.step)}, and the kicks are stable only "
                f"below 2; reduce dt below {2.0 / np.sqrt(curvature):.3g}.")
    return ("Likely cause: the forces grew faster than the step resolves (the landscape is steep or unbounded "
            f"below where the walkers went; dt = {float(params.dt):.3g}); reduce dt, or bound the landscape.")


def _simulate_host(fitness, state, params, n_steps, rebuild_every, observe, gap_every, k, progress):
    n_total = jnp.asarray(n_steps, jnp.int32)
    gaps, reallocations, seconds = [], 0, {"rebuild": 0.0, "steps": 0.0}
    bar, owned = open_bar(progress, n_steps, "simulate")
    first_step = int(state.step)  # the gap schedule counts the swarm's steps, across calls
    if gap_every and first_step % gap_every == 0:
        gaps.append((0,) + _bulk_gap(state.tess))
    opening, pending = _begin_step(params, state), []
    dtype = state.positions.dtype
    for start in range(0, n_steps, rebuild_every):
        t0 = time.perf_counter()
        entering = state
        moved, obs, cells = _run_chunk(fitness, params, entering, opening, jnp.asarray(start, jnp.int32), n_total,
                                       rebuild_every, observe)
        # Dispatched now, computed by XLA while the host runs Qhull below: none needs the new graph.
        state, opening = _finish_and_begin(fitness, params, moved)
        end = min(start + rebuild_every, n_steps)
        first = _measure_first(fitness, params, entering, cells, _progress(start, n_total, dtype), observe)
        pending.append((obs, first, end - start))
        jax.block_until_ready(moved.positions)
        codes = [*np.asarray(obs["_health"])[: end - start], int(_health(moved))]
        if any(codes):  # let the dispatched graph-free work finish before raising (XLA aborted otherwise)
            jax.block_until_ready((state, opening, first))
        check_health(fitness, params, codes, start, entering)
        t1 = time.perf_counter()
        moved, grew, n_moved = update_host(moved, k)  # the positions are final in `moved`
        if n_moved:  # walkers were moved apart: redo the graph-free work at their new positions
            state, opening = _finish_and_begin(fitness, params, moved)
        state = eqx.tree_at(lambda s: s.tess, state, moved.tess)
        reallocations += grew
        seconds["steps"] += t1 - t0
        seconds["rebuild"] += time.perf_counter() - t1
        if gap_every and (first_step + end) % gap_every == 0:
            gaps.append((end,) + _bulk_gap(state.tess))
        if bar is not None:
            bar.update(end - start)
    close_bar(bar, owned)
    chunks = [{name: np.concatenate([np.asarray(first[name])[None], np.asarray(obs[name])[1:size]])
               for name in observe} for obs, first, size in pending]
    state, final = _observe_final(fitness, params, state, observe)
    check_health(fitness, params, [health(state)], n_steps, entering)
    series = {name: np.concatenate([c[name] for c in chunks] + [np.asarray(final[name])[None]]) for name in observe}
    return state, _history(series, gaps, reallocations, seconds, state.n_separated, -1, state.positions.dtype)


def _history(series: dict, gaps: list, reallocations, seconds: dict, n_separated, diverged_step, dtype,
             n_fallbacks=0) -> dict:
    """The history `simulate` returns, with the same keys and JAX array types in both rebuild
    modes (the callback mode computes no spectral gaps and measures no wall-clock times: empty
    arrays and NaN)."""
    history = {name: jnp.asarray(values, dtype) for name, values in series.items()}
    history.update(
        spectral_gap_step=jnp.asarray([g[0] for g in gaps], jnp.int32).reshape(-1),
        spectral_gap=jnp.asarray([g[1] for g in gaps], dtype).reshape(-1),
        spectral_components=jnp.asarray([g[2] for g in gaps], jnp.int32).reshape(-1),
        spectral_gap_rounding=jnp.asarray([g[3] for g in gaps], bool).reshape(-1),
        n_reallocations=jnp.asarray(reallocations, jnp.int32), n_fallbacks=jnp.asarray(n_fallbacks, jnp.int32),
        seconds_rebuild=jnp.asarray(seconds["rebuild"], dtype), seconds_steps=jnp.asarray(seconds["steps"], dtype),
        n_separated=jnp.asarray(n_separated, jnp.int32), diverged_step=jnp.asarray(diverged_step, jnp.int32))
    return history


def _bulk_gap(tess: Tessellation) -> tuple[float, int, bool]:
    """(gap, components, whether the gap is at rounding level) of `bulk_spectral_gap`;
    a diagnostic never ends a run: a failure
    (no convergence) is NaN with a warning."""
    try:
        gap, n_comp, outside = bulk_spectral_gap(tess)
        return gap, n_comp, bool(gap < gap_rounding_level(tess.n_points - outside))
    except (ArithmeticError, RuntimeError, ValueError, scipy.sparse.linalg.ArpackError) as err:
        warnings.warn(f"simulate: the spectral gap failed ({type(err).__name__}: {err}); recorded as NaN.",
                      RuntimeWarning, stacklevel=3)
        return float("nan"), -1, False


def _split_walkers(state: SwarmState, params, mesh, rebuild: str, checkpoint) -> SwarmState:
    """One swarm's state placed with its walker axis split over `mesh` (checked)."""
    if isinstance(mesh, Mesh) and BATCH_AXIS in mesh.axis_names and WALKER_AXIS not in mesh.axis_names:
        raise ValueError("a mesh with a 'batch' axis splits a batch of swarms (jaxgeom.stack_swarms); this state "
                         "is one swarm (positions (N, d)): split its walkers with mesh=jaxgeom.walker_mesh().")
    check_mesh(mesh, state.positions.shape[0], "the number of walkers N", WALKER_AXIS)
    if rebuild != "device":
        raise ValueError("splitting one swarm's walkers over devices needs the device rebuild: use "
                         f"rebuild='device' with mesh=jaxgeom.walker_mesh() (got rebuild={rebuild!r}, which "
                         "rebuilds the whole graph with Qhull in one place).")
    if checkpoint or _is_traced(state, params):
        raise TypeError("simulate(..., mesh=walker_mesh()) drives the split swarm from Python (graphs the device "
                        "rebuild cannot certify are rebuilt by Qhull on the host), so it cannot run under jax.jit, "
                        "jax.grad or checkpoint=True; differentiate ensembles (batch_mesh) or one device instead.")
    return shard_walkers(state, mesh, state.positions.shape[0])


def _split_scan(fitness, params: SwarmParams, state: SwarmState, n_total, first, n_steps: int, observe: tuple,
                rebuild_every: int, k: int, mesh):
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


def _simulate_split(fitness, state, params, n_steps, rebuild_every, observe, k, mesh):
    """`simulate` of one swarm with its walkers split over `mesh`: `_split_scan` from the first
    step not yet run, and a Qhull rebuild on the host (counted in `n_fallbacks`) wherever it stopped."""
    n, total = state.positions.shape[0], jnp.asarray(n_steps, jnp.int32)
    done, chunks, fallbacks, reallocations = 0, [], 0, 0
    while done < n_steps:
        entering = state
        state, stopped, obs = _run_split(fitness, params, state, total, jnp.asarray(done, jnp.int32), n_steps,
                                         observe, rebuild_every, k, mesh)
        ran = int(np.sum(np.asarray(obs["_live"])))
        chunks.append({name: np.asarray(values)[:ran] for name, values in obs.items()})
        check_health(fitness, params, [*chunks[-1]["_health"], int(_health(state))], done, entering)
        done += ran
        if bool(stopped):
            state, grew, _ = update_host(state, k)
            state = shard_walkers(state, mesh, n)
            fallbacks, reallocations = fallbacks + 1, reallocations + grew
    state, last = _observe_final(fitness, params, state, observe)
    series = {name: np.concatenate([c[name] for c in chunks] + [np.asarray(last[name])[None]]) for name in observe}
    nan = {"rebuild": jnp.nan, "steps": jnp.nan}
    return state, _history(series, [], reallocations, nan, state.n_separated, -1, state.positions.dtype, fallbacks)


def _simulate_callback(fitness, state, params, n_steps, rebuild_every, observe, k, mode, checkpoint=False):
    traced = _is_traced(state, params)
    total, reallocations = jnp.asarray(n_steps, jnp.int32), 0
    while True:
        final, obs = _run_callback(fitness, params, state, total, n_steps, observe, rebuild_every, k, mode, checkpoint)
        final, last = _observe_final(fitness, params, final, observe)
        if traced or not bool(final.tess.overflow):  # traced: recorded in `diverged_step` (health)
            break
        state = eqx.tree_at(lambda s: s.tess, state, grown(state.tess))
        reallocations += 1
    codes = jnp.concatenate([obs["_health"], health(final)[None]])
    if not traced:
        check_health(fitness, params, codes, 0, state)
    series = {name: jnp.concatenate([obs[name], last[name][None]]) for name in observe}
    # Under a trace nothing can be raised: the first step whose state failed `health`, or -1.
    diverged = jnp.where(jnp.any(codes != 0), jnp.argmax(codes != 0), -1)
    nan = {"rebuild": jnp.nan, "steps": jnp.nan}
    fallbacks = jnp.sum(obs["_fallback"], dtype=jnp.int32)
    return final, _history(series, [], reallocations, nan, final.n_separated, diverged, final.positions.dtype, fallbacks)
