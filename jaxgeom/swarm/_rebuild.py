"""The graph lifecycle of a moving swarm: allocate a graph with headroom, update it for
moved walkers, and grow its capacity by one rule (after jax-md's neighbour lists:
allocation on the host, updates that keep the shapes, an overflow flag).

- `allocate_graph(x, graph, k, capacity)`: host; the first graph, or a rebuild that may
  grow the capacity to a larger bucket (`capacity_with_headroom`, the one growth rule).
- `update_host(state, k)`: host, between jitted chunks; `state.triangulator` (or the k-d tree) on the
  final positions, capacity grown when needed.
- `update_in_trace(state, k)`: inside a trace, through `jax.pure_callback` (a device
  triangulator: `jax.experimental.buffer_callback` on the device buffers); the shapes
  cannot change, so a graph that does not fit sets `tess.overflow` and keeps the old one.
- `update_on_device(state, k)`: inside a trace, `jaxgeom.rebuild` (no host round trip);
  a rebuild it cannot certify falls back to `update_in_trace` for that step.
- `grown(tess)`: the next capacity after an overflow.

Walkers that coincide for the triangulator (cloning puts them there) are moved apart first
(`separate_coincident`) and counted.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base._checks import mean_spacing
from ..tessellation._cellclip import rebuild_unchecked
from ..tessellation._delaunay import (
    CapacityError,
    GrowingCapacity,
    as_capacity,
    build_delaunay,
    planar_graph_on_device,
    planar_tessellation,
    planar_triangles,
)
from ..tessellation._device_check import OK as DEVICE_OK
from ..tessellation._device_check import planar_summary
from ..tessellation._graph import Capacity, Tessellation, bucket_neighbors, bucket_simplices
from ..tessellation._knn import knn_graph
from ..tessellation._triangulators import (
    DEVICE_BACKENDS,
    FALLBACK,
    REFUSED,
    TOO_MANY,
    CoincidentPointsError,
    traced_device_triangles,
)
from ._dynamics import REBUILD_FAILED, SwarmState

GRAPHS = ("delaunay", "knn")
NEIGHBOR_HEADROOM = 8  # cloning puts walkers next to their companions: max degree drifts up by several
SIMPLEX_HEADROOM = 1.1  # 3D simplex counts drift by a few percent


def capacity_with_headroom(tess: Tessellation, previous: Capacity | None = None) -> Capacity:
    """Capacities with room for a moving swarm, for the graph `tess` (at least `previous`)."""
    n = tess.n_points  # on the host: the masks as jnp operations compile a program per shape
    need = Capacity(
        int(np.count_nonzero(np.asarray(tess.simplices)[:, 0] < n)),
        int(np.count_nonzero(np.asarray(tess.neighbors) < n, axis=1).max()),
    )
    return _with_headroom(need, tess.dim, tess.capacity.simplices, previous)


def _with_headroom(need: Capacity, dim: int, planar_simplices: int, previous: Capacity | None) -> Capacity:
    """THE growth rule: max degree + NEIGHBOR_HEADROOM and SIMPLEX_HEADROOM x the simplex count,
    rounded up to their buckets (in 2D the simplex capacity is already the exact bound 2N,
    `planar_simplices`)."""
    simplices = planar_simplices if dim == 2 else bucket_simplices(math.ceil(SIMPLEX_HEADROOM * need.simplices))
    cap = Capacity(simplices, bucket_neighbors(need.neighbors + NEIGHBOR_HEADROOM))
    return cap if previous is None else Capacity(*(max(a, b) for a, b in zip(cap, previous, strict=True)))


def grown(tess: Tessellation) -> Tessellation:
    """`tess` padded to the next capacity after an overflow: its need is unknown but above its
    capacity, so the growth rule is applied to the capacity itself."""
    bigger = _with_headroom(tess.capacity, tess.dim, tess.capacity.simplices, tess.capacity)
    return pad_to_capacity(eqx.tree_at(lambda t: t.overflow, tess, jnp.asarray(False)), bigger)


def pad_to_capacity(tess: Tessellation, cap: Capacity) -> Tessellation:
    """The same graph with sentinel padding (and zero image shifts) up to `cap`."""
    n = tess.n_points

    def pad(a, axis: int, size: int, fill):
        if a is None:
            return None
        widths = [(0, 0)] * a.ndim
        widths[axis] = (0, size - a.shape[axis])
        return jnp.asarray(np.pad(np.asarray(a), widths, constant_values=fill))

    fields = (
        pad(tess.neighbors, 1, cap.neighbors, n),
        pad(tess.neighbor_shifts, 1, cap.neighbors, 0),
        pad(tess.simplices, 0, cap.simplices, n),
        pad(tess.simplex_shifts, 0, cap.simplices, 0),
    )
    return eqx.tree_at(
        lambda t: (t.neighbors, t.neighbor_shifts, t.simplices, t.simplex_shifts),
        tess,
        fields,
        is_leaf=lambda x: x is None,
    )


# Walkers that coincide for Qhull are moved apart by this many mean spacings (at least 1000
# times the dtype's resolution at the swarm's coordinates), 4x more on each further attempt.
SEPARATION = 1e-3
SEPARATION_ATTEMPTS = 4


def separate_coincident(x: np.ndarray, rows: np.ndarray, partners: np.ndarray, attempt: int = 0) -> np.ndarray:
    """`x` with walkers `rows` moved away from the walkers `partners` they coincide with (a
    deterministic direction where they are identical)."""
    spacing = mean_spacing(x)
    resolution = 1e3 * np.finfo(x.dtype).eps * float(np.max(np.abs(x)))
    step = max(SEPARATION * spacing, resolution) * 4.0**attempt
    direction = (x[rows] - x[partners]).astype(np.float64)
    norm = np.linalg.norm(direction, axis=1, keepdims=True)
    fallback = np.random.default_rng(rows).normal(size=direction.shape)
    direction = np.where(norm > 0, direction, fallback)
    out = x.copy()
    out[rows] = x[rows] + (step * direction / np.linalg.norm(direction, axis=1, keepdims=True)).astype(x.dtype)
    return out


def _separated(build, x: np.ndarray):
    """(build(x), x, n_moved), after moving apart walkers that coincide for Qhull
    (`separate_coincident`; the dynamics create them, so they are never fatal there)."""
    moved = 0
    for attempt in range(SEPARATION_ATTEMPTS + 1):
        try:
            return build(x), x, moved
        except CoincidentPointsError as err:
            if attempt == SEPARATION_ATTEMPTS:
                raise
            x = separate_coincident(x, err.rows, err.partners, attempt)
            moved += len(err.rows)


class Allocated(NamedTuple):
    """A host graph build: the graph, whether its capacity grew, the positions (coinciding
    walkers moved apart), how many were moved, and how many triangulations fell back to Qhull."""

    tess: Tessellation
    grew: bool
    positions: np.ndarray
    moved: int
    fallbacks: int


def delaunay_separating(
    x: np.ndarray, capacity=None, triangulator: str = "qhull"
) -> tuple[Tessellation, np.ndarray, int, int]:
    """(graph, positions, n_moved, n_fallbacks): `delaunay(x)` of `x` with coinciding walkers
    moved apart, and the triangulator's fallbacks to Qhull in the build that succeeded."""
    (tess, fallbacks), x, moved = _separated(
        lambda y: build_delaunay(y, capacity=capacity, triangulator=triangulator), x
    )
    return tess, x, moved, len(fallbacks)


def allocate_graph(x: np.ndarray, graph: str, k: int, capacity=None, triangulator: str = "qhull") -> Allocated:
    """Delaunay at `capacity` (grown to a larger bucket if too small; coinciding walkers moved
    apart) by the resolved host `triangulator`, or k-NN."""
    if graph == "knn":
        return Allocated(knn_graph(x, k), False, x, 0, 0)
    if capacity is not None:
        floor = growing_capacity(capacity, x.shape[1], len(x))
        tess, x_new, moved, fallbacks = delaunay_separating(x, floor, triangulator)
        return Allocated(tess, tess.capacity != floor.floor, x_new, moved, fallbacks)
    fresh, x, moved, fallbacks = delaunay_separating(x, None, triangulator)
    return Allocated(pad_to_capacity(fresh, capacity_with_headroom(fresh)), False, x, moved, fallbacks)


def growing_capacity(capacity, d: int, n: int) -> GrowingCapacity:
    """`capacity` (a `Capacity`, a tuple or a graph) for a rebuild of `n` walkers in `d`
    dimensions that grows it by the growth rule where the new graph does not fit (one
    triangulation, where a `CapacityError` and a second build would take two)."""
    floor = as_capacity(capacity)
    return GrowingCapacity(floor, lambda need: _with_headroom(need, d, 2 * n, floor))


def update_host(state: SwarmState, k: int) -> tuple[SwarmState, bool, int]:
    """(state, grew, n_moved): the state with a new graph at its positions (coinciding walkers
    moved apart; triangulator fallbacks to Qhull counted), whether the capacity grew, and how
    many walkers were moved. A 2D graph whose triangulator runs on the device (CuPy) is built
    there (`planar_graph_on_device`: the positions stay on the device); where that build fails,
    the host builds it with the backend's fallback, counted."""
    graph, triangulator, failed = _graph_kind(state.tess), state.triangulator, 0
    try:
        if graph == "delaunay" and _on_device(state.tess, triangulator):
            tess, grew, reason = _allocate_on_device(state.positions, state.tess, triangulator)
            if tess is not None:
                return eqx.tree_at(lambda s: s.tess, state, tess), grew, 0
            triangulator, failed = FALLBACK[triangulator], int(reason is not None)
        x = np.asarray(state.positions)
        tess, grew, x_new, moved, fallbacks = allocate_graph(
            x, graph, k, None if graph == "knn" else state.tess, triangulator
        )
    except ValueError as err:
        raise ValueError(f"simulate: the graph could not be rebuilt after step {int(state.step)}: {err}") from None
    fallbacks += failed
    if moved:
        xj = jnp.asarray(x_new, state.positions.dtype)
        state = eqx.tree_at(lambda s: (s.positions, s.n_separated), state, (xj, state.n_separated + moved))
        tess = eqx.tree_at(lambda t: t.points, tess, xj)
    if fallbacks:
        state = eqx.tree_at(lambda s: s.n_triangulator_fallbacks, state, state.n_triangulator_fallbacks + fallbacks)
    return eqx.tree_at(lambda s: s.tess, state, tess), grew, moved


def _on_device(tess: Tessellation, triangulator: str) -> bool:
    return tess.dim == 2 and not tess.periodic and triangulator in DEVICE_BACKENDS


def _allocate_on_device(
    positions: jax.Array, tess: Tessellation, triangulator: str
) -> tuple[Tessellation | None, bool, str | None]:
    """`allocate_graph` by `planar_graph_on_device` at `tess`'s capacity, grown by the growth rule
    when the graph does not fit: (graph, grew, None), or (None, False, why the device build failed;
    None where the host path must raise the reason)."""
    try:
        new, reason = planar_graph_on_device(positions, None, tess, triangulator)
        return new, False, reason
    except CapacityError:
        new, reason = planar_graph_on_device(positions, None, None, triangulator)
        if new is None:
            return None, False, reason
        return pad_to_capacity(new, capacity_with_headroom(new, tess.capacity)), True, None


def _graph_kind(tess: Tessellation) -> str:
    return "knn" if tess.simplices is None else "delaunay"


# Outcome codes of a rebuild inside `jax.pure_callback`.
REBUILT, OVERFLOWED, FAILED = 0, 1, 2


def _attempt(build, x):
    """(arrays, positions, code, n_moved, n_fallbacks) of a host rebuild that never raises: an
    overflow or a failure (non-finite or degenerate walkers) is returned as a code, the old
    graph kept. `build(x)` returns (arrays, fallback reasons)."""
    try:
        (arrays, fallbacks), x, moved = _separated(build, x)
        return arrays, x, REBUILT, moved, len(fallbacks)
    except CapacityError:
        return None, x, OVERFLOWED, 0, 0
    except ValueError:
        return None, x, FAILED, 0, 0


def _apply_rebuild(state: SwarmState, new: Tessellation, positions, code, moved, fallbacks) -> SwarmState:
    """The state with the rebuilt graph (the old one unless `code == REBUILT`), the positions
    the callback may have moved apart (gradients pass through unchanged), and the flags."""
    x = state.positions + jax.lax.stop_gradient(positions.astype(state.positions.dtype) - state.positions)
    tess = jax.tree_util.tree_map(lambda a, b: jnp.where(code == REBUILT, b, a), state.tess, new)
    tess = eqx.tree_at(lambda t: (t.points, t.overflow), tess, (x, state.tess.overflow | (code == OVERFLOWED)))
    status = state.status | jnp.where(code == FAILED, REBUILD_FAILED, 0)
    return eqx.tree_at(
        lambda s: (s.positions, s.tess, s.status, s.n_separated, s.n_triangulator_fallbacks),
        state,
        (x, tess, status.astype(jnp.int32), state.n_separated + moved, state.n_triangulator_fallbacks + fallbacks),
    )


def update_in_trace(state: SwarmState, k: int) -> SwarmState:
    """Rebuild inside a trace with `jax.pure_callback` (`vmap_method="sequential"`). A graph
    that does not fit keeps the old arrays and sets `tess.overflow`; walkers the triangulator cannot
    triangulate keep the old graph and set `REBUILD_FAILED` in `state.status`. In 2D the
    callback runs the triangulator alone and the neighbour rows are derived in the trace."""
    tess = state.tess
    if tess.simplices is not None and tess.dim == 2 and not tess.periodic:
        if state.triangulator in DEVICE_BACKENDS:
            return _device_planar_rebuild_in_trace(state)
        return _callback_planar_rebuild(state, state.triangulator)
    graph, cap = _graph_kind(tess), tess.capacity
    old = (tess.neighbors, tess.tier, tess.hull) + (() if tess.simplices is None else (tess.simplices,))

    def build(x):
        new, fallbacks = (
            (knn_graph(x, k), ())
            if graph == "knn"
            else build_delaunay(x, capacity=cap, triangulator=state.triangulator)
        )
        return (new.neighbors, new.tier, new.hull) + (() if new.simplices is None else (new.simplices,)), fallbacks

    def host(x, *arrays):
        new, x, code, moved, fallbacks = _attempt(build, np.asarray(x))
        return tuple(np.asarray(a) for a in (arrays if new is None else new)) + (
            x,
            np.int32(code),
            np.int32(moved),
            np.int32(fallbacks),
        )

    shapes = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in old + (state.positions,))
    shapes += (jax.ShapeDtypeStruct((), jnp.int32),) * 3
    *arrays, x, code, moved, fallbacks = jax.pure_callback(
        host, shapes, jax.lax.stop_gradient(state.positions), *old, vmap_method="sequential"
    )
    new = eqx.tree_at(lambda t: (t.neighbors, t.tier, t.hull), tess, tuple(arrays[:3]))
    if len(arrays) == 4:
        new = eqx.tree_at(lambda t: t.simplices, new, arrays[3])
    return _apply_rebuild(state, new, x, code, moved, fallbacks)


def update_on_device(
    state: SwarmState, k: int, *, mesh=None, qhull_in_trace: bool = True
) -> tuple[SwarmState, jax.Array]:
    """(state, fell_back): the graph rebuilt on the device (`jaxgeom.rebuild`, 2D; the cells
    split over `mesh`'s walker axis when given), or, where that rebuild is not certified
    (`fell_back`), by Qhull through `update_in_trace`, or (`qhull_in_trace=False`) not at all:
    the state keeps its graph for the caller to rebuild on the host.
    The topology is discrete: no gradient flows into the rebuild, the positions pass through."""
    new = rebuild_unchecked(state.tess, jax.lax.stop_gradient(state.positions), mesh)
    new = eqx.tree_at(lambda t: t.points, new, state.positions)
    certified = ~new.overflow
    fallback = (lambda s: update_in_trace(s, k)) if qhull_in_trace else (lambda s: s)
    state = jax.lax.cond(certified, lambda s: eqx.tree_at(lambda q: q.tess, s, new), fallback, state)
    return state, ~certified


def _device_planar_rebuild_in_trace(state: SwarmState) -> SwarmState:
    """2D rebuild in a trace by a device backend (CuPy): its triangles written into a device
    buffer (`traced_device_triangles`: the positions stay on the device), checked, and their
    adjacency, rows and tiers derived here. A graph the backend fails (or whose triangles fail
    the check) is built on the host by its fallback (`_callback_planar_rebuild`), counted; under
    vmap that callback is entered for every swarm but works only for those that need it."""
    tess, cap = state.tess, state.tess.capacity
    x = jax.lax.stop_gradient(state.positions)
    n = x.shape[0]
    triangles, code = traced_device_triangles(x, cap.simplices, n, state.triangulator)
    (counts, _), adjacency = planar_summary(x, triangles, jnp.maximum(code, 0), n)
    overflowed = code == TOO_MANY
    needs_host = ~overflowed & ((code < 0) | (counts[0] != DEVICE_OK))

    def on_device(s):  # the fan walk and tiers only in this branch: skipped where the host builds
        new = planar_tessellation(x, triangles, adjacency, tess.box, k_cap=cap.neighbors)
        outcome = jnp.where(overflowed | new.overflow, OVERFLOWED, REBUILT)
        zero = jnp.asarray(0, jnp.int32)
        return _apply_rebuild(s, new, x, outcome, zero, zero)

    fallback = FALLBACK[state.triangulator]
    state = jax.lax.cond(needs_host, lambda s: _callback_planar_rebuild(s, fallback, needs_host), on_device, state)
    counted = (needs_host & (code != REFUSED)).astype(jnp.int32)  # refused positions fail on the host too
    return eqx.tree_at(lambda s: s.n_triangulator_fallbacks, state, state.n_triangulator_fallbacks + counted)


def _callback_planar_rebuild(state: SwarmState, triangulator: str, needed=None) -> SwarmState:
    """2D rebuild in a trace: the callback returns `triangulator`'s triangles, the rows are built
    here. `needed` (traced bool): where False the callback returns at once (the caller discards
    its result)."""
    tess = state.tess
    cap = tess.capacity

    def triangles_and_fallbacks(y):
        simplices, adjacency, _, fallbacks = planar_triangles(y, cap, triangulator)
        return (simplices, adjacency), fallbacks

    def host(x, needed):
        if not needed:
            return (np.full((cap.simplices, 3), -1, np.int32),) * 2 + (
                np.asarray(x),
                np.int32(REBUILT),
                np.int32(0),
                np.int32(0),
            )
        triangles, x, code, moved, fallbacks = _attempt(triangles_and_fallbacks, np.asarray(x))
        if triangles is None:
            triangles = (np.full((cap.simplices, 3), -1, np.int32),) * 2  # discarded in the trace
        return triangles + (x, np.int32(code), np.int32(moved), np.int32(fallbacks))

    triangles = jax.ShapeDtypeStruct((cap.simplices, 3), jnp.int32)
    shapes = (
        triangles,
        triangles,
        jax.ShapeDtypeStruct(state.positions.shape, state.positions.dtype),
        *(jax.ShapeDtypeStruct((), jnp.int32),) * 3,
    )
    needed = jnp.asarray(True) if needed is None else needed
    simplices, adjacency, x, code, moved, fallbacks = jax.pure_callback(
        host, shapes, jax.lax.stop_gradient(state.positions), needed, vmap_method="sequential"
    )
    new = planar_tessellation(x.astype(state.positions.dtype), simplices, adjacency, tess.box, k_cap=cap.neighbors)
    code = jnp.where((code == REBUILT) & new.overflow, OVERFLOWED, code)
    return _apply_rebuild(state, new, x, code, moved, fallbacks)
