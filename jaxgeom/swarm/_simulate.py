"""`jaxgeom.simulate`: jax.lax.scan over swarm steps, with the tessellation rebuilt as walkers move.

Three rebuild strategies (why, with the measurements: bench/README.md):

- `rebuild="host"` (default) runs `rebuild_every` steps in one jitted `lax.scan` chunk
  (`_steps._host_chunk`, driven by `_drivers._simulate_host`) and rebuilds the graph
  with the swarm's triangulator between chunks (`jaxgeom.swarm._rebuild.update_host`; by default CDT
  in 2D and Qhull in 3D and 4D, shull with the GPL extra: `init_swarm`). Between chunks
  the host first dispatches the work that needs no new graph (the last step's closing
  kick, the next step's opening with its random draws and clone decisions, the
  observables of the chunk's first state), so XLA computes it while the triangulator runs. Only
  this loop can grow a too-small capacity (a new bucket, one recompilation) instead of
  truncating, compute the spectral gap every M steps and show a progress bar; it
  compiles per chunk length, not per `n_steps`.
- `rebuild="callback"` (`_steps._callback_scan`, `_drivers._simulate_callback`) rebuilds
  inside the scan through `jax.pure_callback` (`jaxgeom.swarm._rebuild.update_in_trace`): the
  whole simulation is one jittable, differentiable function of the parameters (tuning nu
  and eps_Sigma with optimistix). Its capacity cannot grow inside the scan, so an
  overflow re-runs the simulation with larger capacities when called eagerly; under a
  trace it is recorded like a divergence (`diverged_step`, so a `simulation_loss` is
  +inf there).
- `rebuild="device"` is the same scan with the graph rebuilt in JAX (`jaxgeom.rebuild`,
  2D non-periodic Delaunay swarms): no host round trip on the steps it certifies; a step
  it cannot certify falls back to the callback's host triangulation and is counted (`n_fallbacks`).
  On CPU it is slower than the callback today (bench/README.md); it is the route to GPUs.

This module is the entry point (argument checks, dispatch, batches of swarms); the drivers
live in `_drivers`, the shared step bodies in `_steps`, the history in `_history`, the
divergence checks in `_divergence` and the initial state in `_swarm_init`.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base._checks import check_choice, check_integer
from ..base._progress import check_progress
from ..base._sharding import check_mesh, over_batch
from ..tessellation._cellclip import describe_graph, rebuilds_on_device
from ._drivers import _simulate_callback, _simulate_host, _simulate_split, _split_walkers
from ._dynamics import SwarmParams, SwarmState
from ._observables import ALL_OBSERVABLES, OBSERVABLES, prepare_scutoid_trace
from ._steps import _is_traced
from ._swarm_init import check_callable_fitness, check_traceable_fitness

REBUILD_MODES = ("host", "callback", "device")


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
        check_choice(name, "observable", ALL_OBSERVABLES)
    check_choice(rebuild, "rebuild", REBUILD_MODES)
    check_integer(spectral_gap_every, "spectral_gap_every")
    if not _is_traced(state, params):
        check_traceable_fitness(fitness, state.positions.shape[-1], state.positions.dtype)
    if rebuild == "host" and _is_traced(state, params):
        raise TypeError(
            "simulate(rebuild='host') rebuilds the graph with a triangulator between jitted chunks, "
            "so it cannot run under jax.jit, jax.grad or jax.vmap. Use rebuild='callback' for a "
            "traceable, differentiable simulation."
        )
    if rebuild == "device" and not rebuilds_on_device(state.tess):
        raise ValueError(
            "simulate(rebuild='device') rebuilds 2D Delaunay swarms on the device so far; this swarm's "
            f"graph is {describe_graph(state.tess)}. Use rebuild='callback' (traceable) or 'host'."
        )
    if params.volume_weighting and state.tess.simplices is None:
        raise ValueError(
            "`volume_weighting=True` needs Voronoi volumes, which a k-NN swarm does not have; "
            "use init_swarm(..., graph='delaunay') or volume_weighting=False."
        )
    if spectral_gap_every and (spectral_gap_every % rebuild_every or rebuild != "host"):
        raise ValueError(
            "`spectral_gap_every` must be a multiple of `rebuild_every` and needs rebuild='host' "
            f"(the gap is computed on the host after a rebuild); got {spectral_gap_every}."
        )


def simulate(
    fitness,
    state: SwarmState,
    params: SwarmParams,
    *,
    n_steps: int,
    rebuild_every: int = 1,
    observe: str | Sequence[str] = OBSERVABLES,
    rebuild: str = "host",
    spectral_gap_every: int = 0,
    progress=False,
    checkpoint: bool = False,
    mesh=None,
):
    """Run `n_steps` swarm steps (`jax.lax.scan`), rebuilding the tessellation as walkers move.

    **Arguments:**

    - `fitness`: the landscape V used to build `state` (same function object: it
      is a static argument of the compiled step).
    - `state`, `params`: [`jaxgeom.SwarmState`][] (from `init_swarm`) and [`jaxgeom.SwarmParams`][].
    - `n_steps`: number of steps; `rebuild_every`: steps between graph rebuilds
      (between rebuilds the graph keeps its topology and follows the walkers;
      cloning happens on the last step before each rebuild).
    - `observe`: names from `OBSERVABLES` (the default: all of them) or `ALL_OBSERVABLES`
      (adds the opt-in "mean_metric_curvature", the exact Ricci scalar of the Hessian metric
      from `metric_curvature`, O(d^4) per walker up to d = 16, stochastic above), recorded
      for the state entering every step and for the final state (n_steps + 1 values).
    - `rebuild`: "host" (default: fastest on CPU), "callback" (jittable and differentiable
      end to end, vmap runs the lanes' triangulations one after another) or "device" (the
      same, with the 2D graph rebuilt in JAX and triangulated only on the steps the device rebuild
      cannot certify; module docstring). Host triangulations (every mode) use the swarm's
      `state.triangulator`, chosen in `init_swarm`.
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
      device rebuild cannot certify are triangulated on the host between scans, so this
      mode cannot run under jax.jit / jax.grad.

    **Returns:**

    `(final_state, history)`, history a dict of JAX arrays with the same keys in both
    rebuild modes: each observable (n_steps + 1,); `spectral_gap_step` (index into the
    observables), `spectral_gap`, `spectral_components` and `spectral_gap_rounding` (the
    gap is below float64 resolution, `gap_rounding_level`: read it as "< that level") (one
    entry per gap computed; empty with rebuild="callback");
    `n_reallocations` (capacity growths); `n_fallbacks` (rebuild="device": steps rebuilt
    by the host triangulator because the device rebuild was not certified; 0 otherwise); wall-clock
    `seconds_rebuild` / `seconds_steps`
    (NaN with rebuild="callback"); `n_separated` (walkers moved apart for the triangulator);
    `n_triangulator_fallbacks` (host triangulations in which `state.triangulator` failed and
    Qhull built the graph; `n_separated` and this count the state's whole life);
    `diverged_step` (-1, or under a trace the first step whose state failed: non-finite,
    runaway, all dead, a failed rebuild, or a graph that outgrew its capacity).
    For a batch: the same with a leading (B,) axis on every array of both.

    Ctrl-C (rebuild="host") raises a `KeyboardInterrupt` that carries the `state`, `history`
    and `steps` of the steps completed before it (`except KeyboardInterrupt as stop:
    stop.history`), as this function would have returned them for that many steps.
    """
    observe = (observe,) if isinstance(observe, str) else tuple(observe)  # one name is one observable
    if is_batch(state):
        return _simulate_batch(
            fitness,
            state,
            params,
            n_steps=n_steps,
            rebuild_every=rebuild_every,
            observe=observe,
            rebuild=rebuild,
            checkpoint=checkpoint,
            mesh=mesh,
            spectral_gap_every=spectral_gap_every,
        )
    check_progress(progress)
    if progress is not False and progress is not None and rebuild != "host":
        raise ValueError(
            f"`progress` shows the host driver's steps; rebuild={rebuild!r} runs them in one traced "
            "program, which a bar cannot follow. Leave progress False."
        )
    _check_simulate_args(fitness, state, params, n_steps, rebuild_every, observe, rebuild, spectral_gap_every)
    if not isinstance(checkpoint, bool):
        raise TypeError(f"`checkpoint` must be True or False; got {checkpoint!r}.")
    if checkpoint and rebuild == "host":
        raise ValueError(
            "`checkpoint=True` serves gradients through a traced run: use it with rebuild='callback' "
            "or 'device' (rebuild='host' cannot be differentiated)."
        )
    k = state.tess.neighbors.shape[1]  # a k-NN swarm keeps its k (unused by Delaunay rebuilds)
    state = prepare_scutoid_trace(state, observe)
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
        raise ValueError(
            "the swarms differ in walkers, dimension or graph capacity; build every one with the same "
            "N and init_swarm(..., capacity=jaxgeom.Capacity(simplices=S, neighbors=K))."
        )
    return _stack_leaves(states)


@jax.jit
def _stack_leaves(states: list):
    """The swarms leaf by leaf on a new leading axis, in one program (eagerly: one per leaf)."""
    return jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *states)


def _simulate_batch(
    fitness, state, params, *, n_steps, rebuild_every, observe, rebuild, checkpoint, mesh, spectral_gap_every
):
    """`simulate` of every swarm of a batch: vmap, split over `mesh` when given (no progress bar:
    one traced program)."""
    if rebuild == "host":
        raise ValueError(
            "a batch of swarms runs inside one traced program: use rebuild='callback' or 'device' "
            "(rebuild='host' drives one swarm from Python)."
        )
    lane = jax.tree_util.tree_map(lambda leaf: leaf[0], state)
    _check_simulate_args(fitness, lane, params, n_steps, rebuild_every, observe, rebuild, spectral_gap_every)
    check_mesh(mesh, state.positions.shape[0], "the number of swarms B")
    options = (
        ("n_steps", n_steps),
        ("rebuild_every", rebuild_every),
        ("observe", observe),
        ("rebuild", rebuild),
        ("checkpoint", checkpoint),
    )
    return _run_lanes(fitness, state, params, mesh, options)


@eqx.filter_jit
def _run_lanes(fitness, state, params, mesh, options):
    return over_batch(lambda st, p: simulate(fitness, st, p, **dict(options)), mesh)(state, params)
