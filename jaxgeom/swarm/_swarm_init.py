"""A swarm's initial state: `init_swarm` (host: the first graph, checks of the fitness and the arrays)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base._checks import check_choice, check_min_points, host_points, real_array
from ..geometry._weights import mean_nearest_neighbor_distance
from ..tessellation._delaunay import build_delaunay
from ..tessellation._triangulators import resolve_triangulator
from ._dynamics import SwarmState, empty_scutoid_trace, fitness_and_force
from ._rebuild import GRAPHS, allocate_graph


def check_callable_fitness(fitness) -> None:
    if not callable(fitness):
        raise TypeError(f"`fitness` must be a JAX function x (d,) -> scalar V(x); got {type(fitness).__name__}.")


def check_fitness(fitness, x: np.ndarray):
    """`fitness` must map one walker (d,) to a finite scalar at every initial walker. Returns
    V and -grad V there (`fitness_and_force`, one compiled program)."""
    check_callable_fitness(fitness)
    xj = jnp.asarray(x)
    try:
        out = jax.eval_shape(jax.vmap(fitness), xj)
    except Exception as err:  # noqa: BLE001 - re-raised with the fix
        raise TypeError(
            f"`fitness` must map one walker x of shape (d,) = ({x.shape[1]},) to a scalar with "
            f"jax.numpy operations; calling it failed: {err}"
        ) from err
    shape = getattr(out, "shape", None)
    if shape != (len(x),):
        raise TypeError(
            "`fitness` must return a scalar per walker (shape ()); it returned "
            + (f"shape {shape[1:]}" if shape is not None else type(out).__name__)
            + " for one walker."
        )
    check_fitness_dtype(out.dtype)
    values, force = _fitness_and_force(fitness, xj)
    bad = np.flatnonzero(~np.isfinite(np.asarray(values)))
    if bad.size:
        raise ValueError(
            f"`fitness` is NaN or inf at {bad.size} initial walker(s), first rows "
            f"{bad[:5].tolist()}; move them into the landscape's domain."
        )
    return values, force


# One program each (per fitness and shape) instead of op by op: called eagerly, every primitive
# of the fitness, its gradient and the spacing compiles on its own (~60 programs per new swarm size).
_fitness_and_force = eqx.filter_jit(fitness_and_force)
_mean_spacing = eqx.filter_jit(mean_nearest_neighbor_distance)


def check_fitness_dtype(dtype) -> None:
    """The force is -grad V: V must be real and floating."""
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            f"`fitness` must return a real floating-point scalar (the force is -grad V); it returned "
            f"{jnp.dtype(dtype).name}. Use float arithmetic (e.g. 1.0 * ...), and the real part of a "
            "complex value."
        )


def check_traceable_fitness(fitness, d: int, dtype) -> None:
    """`fitness` traced on one abstract walker (no evaluation): jax.numpy operations only, a real
    floating scalar out. (init_swarm evaluates it; simulate may get another function.)"""
    try:
        out = jax.eval_shape(fitness, jax.ShapeDtypeStruct((d,), dtype))
    except Exception as err:  # noqa: BLE001 - re-raised with the fix
        raise TypeError(
            f"`fitness` must be a JAX-traceable function x (d,) = ({d},) -> scalar (jax.numpy, no numpy "
            f"calls, float() or Python branches on x); tracing it failed: "
            f"{type(err).__name__}: {str(err).splitlines()[0]}"
        ) from err
    if getattr(out, "shape", None) != ():
        raise TypeError(f"`fitness` must return a scalar (shape ()); it returned {out}.")
    check_fitness_dtype(out.dtype)


def _as_key(key):
    """An int seed or a JAX PRNG key (typed, or the legacy uint32 (2,) array)."""
    if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
        return jax.random.PRNGKey(key)
    arr = key if isinstance(key, jax.Array) else None
    if arr is not None and (
        jnp.issubdtype(arr.dtype, jax.dtypes.prng_key) or (arr.dtype == jnp.uint32 and arr.shape == (2,))
    ):
        return key
    raise TypeError(f"`key` must be an int seed or a jax.random key (jax.random.PRNGKey(seed)); got {key!r}.")


def init_swarm(
    fitness,
    positions,
    velocities=None,
    *,
    key=0,
    graph: str = "delaunay",
    k: int = 12,
    capacity=None,
    triangulator: str = "auto",
) -> SwarmState:
    """The initial [`jaxgeom.SwarmState`][] of a swarm (host: builds its first graph).

    **Arguments:**

    - `fitness`: JAX function x (d,) -> V(x), finite at every walker.
    - `positions`: (N, d) float array (float32 or float64: the simulation's dtype).
    - `velocities`: (N, d), default zeros.
    - `key`: int seed or `jax.random` key.
    - `graph`: "delaunay" (d = 2, 3) or "knn" (any d; `k` neighbours).
    - `capacity`: pin Delaunay capacities (`CapacityError` if the first graph does not
      fit; later rebuilds in `simulate` grow them); default: buckets with headroom.
    - `triangulator`: the host triangulator of this graph and of every rebuild in
      `simulate` (`jaxgeom.delaunay`'s option; "auto" is resolved here and stored in
      `SwarmState.triangulator`). Its fallbacks to Qhull are counted, not warned.
    """
    x = host_points(positions, "positions", func="jaxgeom.init_swarm")
    check_choice(graph, "graph", GRAPHS)
    check_min_points(len(x), x.shape[1] + 2, "positions", "a swarm")
    v = np.zeros_like(x) if velocities is None else real_array(velocities, "velocities")
    if v.shape != x.shape or not np.issubdtype(v.dtype, np.floating):
        raise ValueError(
            f"`velocities` must be a float array of shape (N, d) = {x.shape} like `positions`; got {v.dtype} {v.shape}."
        )
    if not np.isfinite(v).all():
        raise ValueError(
            f"`velocities` has NaN or inf entries in {int((~np.isfinite(v).all(axis=1)).sum())} "
            "row(s). Repair them or start from velocities=None (zeros)."
        )
    key = _as_key(key)
    backend = resolve_triangulator(triangulator, x.shape[1])
    values, force = check_fitness(fitness, x)
    if capacity is not None and graph == "delaunay":  # pinned: raises CapacityError when the graph does not fit
        tess, reasons = build_delaunay(x, capacity=capacity, triangulator=backend)
        fallbacks, moved = len(reasons), 0
    else:
        tess, _, x, moved, fallbacks = allocate_graph(x, graph, k, None, backend)
    xj = jnp.asarray(x)  # float64 input becomes float32 unless jax_enable_x64 is set
    dtype = xj.dtype
    if moved:  # coinciding walkers were moved apart
        values, force = _fitness_and_force(fitness, xj)
    return fresh_state(xj, jnp.asarray(v, dtype), values, force, key, tess, fallbacks, backend)


def fresh_state(xj, v, values, force, key, tess, fallbacks: int = 0, backend: str = "qhull") -> SwarmState:
    """A state at step 0 on its first graph: alive where the fitness is finite, nothing cloned
    or measured yet, the viscous length scale from the graph."""
    n, dtype = xj.shape[0], xj.dtype
    zero = jnp.asarray(0, jnp.int32)
    none = jnp.asarray(np.zeros(n, bool))  # host-made constants: no program compiled per size
    unmeasured = jnp.asarray(np.full(n, np.inf), dtype)  # no finite volume known (`SwarmState`)
    return SwarmState(
        xj,
        v,
        values,
        force,
        jnp.asarray(np.isfinite(np.asarray(values))),
        none,
        unmeasured,
        none,
        unmeasured,
        none,
        jnp.asarray(-1, jnp.int32),
        key,
        tess,
        zero,
        jnp.asarray(_mean_spacing(tess), dtype),
        jnp.asarray(1.0, dtype),
        zero,
        zero,
        jnp.asarray(fallbacks, jnp.int32),
        empty_scutoid_trace(n),
        triangulator=backend,
    )
