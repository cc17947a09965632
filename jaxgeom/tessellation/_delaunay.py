"""Delaunay builder: a host triangulator (`_triangulators`: Qhull, CDT, shull), the graph
derived from its simplices.

In 2D (not periodic) the host hands Qhull's triangles and their edge neighbours to
JAX, which derives neighbour rows, hull flags and tiers (`_planar`, jittable: the
same code serves rebuilds inside `jax.pure_callback`); a backend whose triangles stay
on the device (CuPy) has the whole 2D graph built there (`planar_graph_on_device`).
In 3D/4D and on the torus the neighbour rows come from numpy index bookkeeping.
Geometry derived from the simplices (tiers from circumcentres, volumes, angles) is
computed in JAX; the one geometric test done on the host is the periodic skin check,
which decides whether Qhull must be run again.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import functools
import itertools
import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ..base._checks import (
    check_full_rank,
    check_min_points,
    check_representable_spacing,
    check_resolved_positions,
    host_box,
    host_points,
    mean_spacing,
    refuse_unrepresentable_spacing,
    refuse_unresolved_positions,
    spacing_of_box,
    warn_at_caller,
)
from ..base._simplex import det_entries, simplex_circumcenter
from ._contacts import (
    circumcenters_and_flat,
    planar_degenerate_corners,
    positive_measure_contacts,
)
from ._device_check import REASONS as DEVICE_REASONS
from ._device_check import planar_summary
from ._graph import (
    Capacity,
    Tessellation,
    bucket_neighbors,
    bucket_simplices,
    bucket_walkers,
    neighbor_any,
    simplex_coords,
    split_spatial_dims,
    take_or_zero,
)
from ._planar import fan_neighbors
from ._slabs import slab_count, slab_triangulation
from ._triangulators import (
    DEVICE_BACKENDS,
    FALLBACK,
    circumballs_and_determinants,
    device_triangles,
    host_chunks,
    resolve_triangulator,
    simplex_edges,
    triangulate,
)

MAX_DELAUNAY_DIM = 4
# Initial periodic skin, in mean walker spacings, at N <= 1e4; the skin check widens it when
# needed (the slab then triangulates again). In 3D it grows with N as a uniform sample's widest
# empty ball, (ln N)^(1/3): 2.8 at 1e5, 3.0 at 1e6. Uniform walkers, periodic `delaunay`: Qhull
# at 1e4 324 -> 283 ms against 3.0 (2.3: 268 ms, but 6 of 20 slabs triangulated twice); shull
# at 1e5 a skin of 2.4 retried 8 of 12 slabs, 2.6 one, 2.8 none (bench/README.md). 2D and 4D:
# not measured beyond 1e4.
SKIN_SPACINGS = {2: 3.0, 3: 2.6, 4: 3.0}
SKIN_GROWS_WITH_N = (3,)
# After a failed check the skin grows at least 1.6x (12 attempts reach 280x the initial skin:
# voids as wide as the box, sparse samples), and at least to the diameter, plus 5%, of the widest
# circumball the check saw inside the region: a ball through an owned walker reaches at most that
# far beyond the slab. Clustered swarms (20 clusters at N = 1e4, 8 seeds) then triangulate a slab
# twice, not four times: median 3.5 -> 2.5 s (bench/README.md).
SKIN_GROWTH = 1.6
SKIN_MARGIN = 0.05
MAX_SLABS = 4
# (slabs per core, a slab's least thickness in skins), per dimension
SLABS = {3: (1, 2)}
SLABS_ELSE = (2, 4)
SKIN_ATTEMPTS = 12
# periodic symbolic perturbation, in mean spacings; the next if the box is not tiled or a
# walker's star is not its kept simplices
TIE_BREAKS = (1e-9, 1e-8, 1e-7)


class CapacityError(ValueError):
    """A graph does not fit the capacities it was pinned to (grow them and rebuild)."""


class GrowingCapacity(NamedTuple):
    """A capacity that grows where the graph does not fit it, in place of `CapacityError`:
    `floor` where the graph fits, else `grow(need)` (at least the need), so that a moving
    swarm's rebuild that outgrows its capacity runs the triangulator once, not twice."""

    floor: Capacity
    grow: Callable[[Capacity], Capacity]


# While a list is set here, `_open_graph` builds its graph with every tier 2 and appends the
# function that computes its tiers (`deferred_tiers`).
_DEFERRED_TIERS: contextvars.ContextVar[list | None] = contextvars.ContextVar("deferred_tiers", default=None)


@contextlib.contextmanager
def deferred_tiers():
    """Within: an open graph in d >= 3 is built with every tier 2, and the function that
    returns its real (N,) tiers, given the finished graph, is appended to the yielded list
    (none for other graphs). XLA runs a backend's programs in the order they were
    dispatched, so the hull walk behind the tiers (3D, N = 1e4: ~11 ms) would delay the
    next step; `simulate` leaves it out where no step or observable reads the tiers, and
    computes them for the state it returns."""
    pending: list = []
    token = _DEFERRED_TIERS.set(pending)
    try:
        yield pending
    finally:
        _DEFERRED_TIERS.reset(token)


class RawGraph(NamedTuple):
    """A periodic graph as its slabs give it, in original walker indices (host numpy arrays)."""

    simplices: np.ndarray  # (S, d + 1)
    simplex_shifts: np.ndarray | None  # (S, d + 1, d)
    nbr_rows: np.ndarray  # (E,) walker of each directed edge
    nbr_cols: np.ndarray  # (E,) its neighbour
    nbr_shifts: np.ndarray | None  # (E, d)
    hull: np.ndarray  # (N,) bool
    fallbacks: tuple[str, ...] = ()  # why the asked-for triangulator was replaced, and by which, per call


def delaunay(
    points,
    *,
    box=None,
    periodic: bool = False,
    capacity=None,
    triangulator: str = "auto",
    spatial_dims: int | None = None,
) -> Tessellation:
    """Delaunay graph of a swarm as a padded [`jaxgeom.Tessellation`][].

    Not jittable: a triangulator builds the graph, on the host or (2D, CuPy) on the GPU.
    The default (`triangulator="auto"`) per dimension: in 2D CuPy's gDel2D when JAX runs on a
    CUDA GPU and the `cuda12`/`cuda13` extra is installed, else shull (the GPL extra), else
    CDT; in 3D shull (GPL extra), else Qhull; in 4D Qhull. Qhull gets the points in Morton
    order, which makes it faster; all indices refer to the original order. From 3e4 walkers in
    3D (open or boxed) Qhull runs in slabs, one per core, in parallel threads, whose union is
    checked to be the one triangulation (else one call builds it). In 2D (not
    periodic) the neighbour rows, hull flags and tiers are derived from the triangles by the
    jitted `planar_tessellation` (tessellation/_delaunay.py).

    **Arguments:**

    - `points`: (N, d) float array, d = 2 or 3 (4 allowed), N >= d + 2, no
      duplicates, not all on a hyperplane.
    - `box`: `(lower, upper)` scalars or (d,) vectors. Every walker must lie
      inside; cells reaching outside the box are tier 0.
    - `periodic`: wrap the box (needs `box`). Periodic images in a skin around
      the box are triangulated and mapped back to original indices with the
      integer image shift of each neighbour and simplex vertex. The skin starts
      at 3 mean spacings (in 3D 2.6 up to N = 1e4, then growing as
      (ln N)^(1/3)) and grows until every circumsphere of
      a simplex with an original vertex lies inside it, so the result is exact.
      Ties (co-circular walkers, lattices) are broken by a fixed perturbation of
      1e-9 mean spacings, the same for every image of a walker, so all translates
      of a periodic simplex are split alike (checked: where the triangulator did
      not resolve it, a larger one, up to 1e-7, is tried).
    - `capacity`: `Capacity(simplices, neighbors)`, a `(simplices, neighbors)`
      tuple or another `Tessellation` to reuse its capacities. `None` buckets
      them (neighbours to a multiple of 8, simplices on an 8-steps-per-octave
      ladder; in 2D the exact bound 2N), so rebuilt graphs of a moving swarm
      reuse compiled kernels. A graph that does not fit raises `ValueError`.
    - `triangulator`: the backend. "auto" (default) takes the fastest installed for d:
      "cupy" (2D, JAX on a CUDA GPU, the `cuda12`/`cuda13` extra), else "shull" (2D, 3D;
      the GPL extra `jaxgeom[gpl]`), else "cdt" (2D, pythoncdt), else "qhull" (scipy, the
      reference, 2D-4D). Every backend gives the same graph on points in general position;
      a backend that fails (or returns a triangulation that fails a cheap check) is
      replaced for this call, CuPy by CDT and the others by Qhull, with a `RuntimeWarning`.
    - `spatial_dims`: k in [2, d] to tessellate the first k coordinates only (space, when
      the rest are, say, a time or fitness coordinate). The graph and all its geometry are
      k-dimensional; the other coordinates ride along in `Tessellation.carried`
      (`all_coordinates` gives the full rows). A `box` of length-d vectors is cut to its
      first k entries. `None` (default): every coordinate.

    **Returns:**

    A `Tessellation` with simplices, neighbours (ascending index; cells sharing a
    face of positive measure, see `Tessellation.neighbors`), tiers and hull flags.
    """
    if spatial_dims is not None:
        points = host_points(points, "points", func="jaxgeom.delaunay")
    points, carried, box = split_spatial_dims(points, box, spatial_dims, "jaxgeom.delaunay")
    tess, fallbacks = build_delaunay(points, box=box, periodic=periodic, capacity=capacity, triangulator=triangulator)
    if carried is not None:
        tess = eqx.tree_at(
            lambda t: t.carried, tess, jnp.asarray(carried, tess.points.dtype), is_leaf=lambda leaf: leaf is None
        )
    for reason in fallbacks:
        warn_at_caller(f"jaxgeom.delaunay: {reason}.", RuntimeWarning)
    return tess


def build_delaunay(
    points, *, box=None, periodic: bool = False, capacity=None, triangulator: str = "auto"
) -> tuple[Tessellation, tuple[str, ...]]:
    """`delaunay`, and why its triangulator was replaced by Qhull in each call where it was
    (empty: never); `simulate` counts these instead of warning."""
    x = host_points(points, "points", func="jaxgeom.delaunay")
    n, d = x.shape
    _check_delaunay_dim(d)
    backend = resolve_triangulator(triangulator, d)
    check_min_points(n, d + 2, "points", f"a {d}D Delaunay tessellation")
    box_arr = host_box(box, x, periodic=periodic)
    check_full_rank(x)
    check_representable_spacing(x, jnp.asarray(x[:1]).dtype)
    check_resolved_positions(x, jnp.asarray(x[:1]).dtype)
    device_failure: tuple[str, ...] = ()
    if d == 2 and not periodic and backend in DEVICE_BACKENDS:
        tess, reason = planar_graph_on_device(x, box_arr, capacity, backend)
        if tess is not None:
            return tess, ()
        replaced = "CDT" if FALLBACK[backend] == "cdt" else FALLBACK[backend]
        backend, device_failure = (
            FALLBACK[backend],
            () if reason is None else (f"{reason}; {replaced} built this graph instead",),
        )
    if d == 2 and not periodic:
        simplices, adjacency, cap, fallbacks = planar_triangles(x, capacity, backend)
        return _planar_from_host(x, simplices, adjacency, box_arr, cap.neighbors), device_failure + fallbacks
    if not periodic:
        return _open_graph(x, backend, capacity, box_arr)
    assert box_arr is not None  # a periodic graph without a box is refused at the boundary
    raw = _periodic_graph(x, box_arr, backend)
    if n >= TRIM_WALKERS:
        _return_freed_memory()
    need = Capacity(len(raw.simplices), int(np.bincount(raw.nbr_rows, minlength=n).max()))
    return _assemble_periodic(x, raw, _fit_capacity(need, n, d, capacity), box_arr), raw.fallbacks


# From this many walkers a build hands the memory its triangulator freed back to the system
# (glibc's `malloc_trim`): Qhull's many small blocks, freed in its threads' arenas, otherwise
# stay in the process (3D periodic, N = 1e6: 3.5 GiB held after the slabs, bench/README.md).
TRIM_WALKERS = 100_000


@functools.cache
def _malloc_trim():
    """glibc's `malloc_trim`, or None where the C library has none (macOS, musl)."""
    try:
        return ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError):
        return None


def _return_freed_memory() -> None:
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _check_delaunay_dim(d: int) -> None:
    if d < 2 or d > MAX_DELAUNAY_DIM:
        raise ValueError(
            f"`points` has dimension d={d}; jaxgeom.delaunay supports d = 2, 3 and 4 "
            "(beyond 3D only Qhull triangulates, and its cost explodes: at d=5, N=1e4 it takes 13 s and "
            "155 simplices per point). "
            "Use jaxgeom.knn_graph(points, k) instead, which works in any dimension."
        )


def planar_triangles(
    x: np.ndarray, capacity=None, triangulator: str = "qhull"
) -> tuple[np.ndarray, np.ndarray, Capacity, tuple[str, ...]]:
    """Host, 2D: counter-clockwise triangles (S, 3) and the triangle across the edge opposite
    each vertex (-1 on the hull), padded to the capacities (padding rows N and -1), and the
    fallback reasons (`build_delaunay`) of the resolved backend `triangulator`.
    Raises `CapacityError` when the graph does not fit a pinned `capacity`."""
    tri, perm, fallback, _ = triangulate(x, triangulator)
    simplices = tri.simplices if perm is None else perm[tri.simplices]  # triangle ids are unchanged
    n = len(x)
    triangles_at = np.bincount(simplices.ravel(), minlength=n)
    bound = int(triangles_at.max()) + 1  # a vertex has one neighbour more than triangles on the hull, else as many
    if capacity is None or as_capacity(capacity).neighbors < bound:
        bound = _planar_max_degree(triangles_at, simplices, tri.neighbors)
    cap = _fit_capacity(Capacity(len(simplices), bound), n, 2, capacity)
    padded = np.full((cap.simplices, 3), n, np.int32)
    padded[: len(simplices)] = simplices
    return padded, _pad_adjacency(tri.neighbors, cap.simplices), cap, () if fallback is None else (fallback,)


def _planar_max_degree(triangles_at: np.ndarray, simplices: np.ndarray, adjacency: np.ndarray) -> int:
    """Largest vertex degree: the triangles at a vertex, plus one on the hull (an open fan).
    A hull edge (t[a + 1], t[a + 2]) lies opposite a corner without a neighbour; every hull
    vertex starts exactly one of them."""
    triangle, corner = np.nonzero(adjacency < 0)
    hull = np.zeros(len(triangles_at), np.int64)
    hull[simplices[triangle, (corner + 1) % 3]] = 1
    return int((triangles_at + hull).max())


@functools.partial(jax.jit, static_argnames="k_cap")
def planar_tessellation(points, simplices, adjacency, box, *, k_cap: int) -> Tessellation:
    """Jittable: the 2D `Tessellation` from `planar_triangles`' arrays (neighbour rows by
    walking each vertex's fan, hull flags, tiers); `overflow` if a row needs more than `k_cap`."""
    return _planar_tessellation(points, simplices, adjacency, box, k_cap)[0]


def _planar_tessellation(points, simplices, adjacency, box, k_cap: int) -> tuple[Tessellation, jax.Array]:
    """`planar_tessellation`, with whether each walker's row fitted (False for a walker in no triangle)."""
    n = points.shape[0]
    degenerate = planar_degenerate_corners(points, simplices, adjacency)
    neighbors, hull, complete = fan_neighbors(simplices, adjacency, n, k_cap, degenerate)
    tess = Tessellation(
        points=points,
        neighbors=neighbors,
        tier=jnp.full((n,), 2, jnp.int8),
        hull=hull,
        simplices=simplices,
        neighbor_shifts=None,
        simplex_shifts=None,
        box=box,
        overflow=~jnp.all(complete),
        periodic=False,
    )
    return eqx.tree_at(lambda t: t.tier, tess, boundary_tiers(tess, adjacency)), complete


@functools.partial(jax.jit, static_argnames="k_cap")
def _planar_rows(points, simplices, adjacency, box, n_walkers, *, k_cap: int):
    """(neighbors, hull, tier, overflow) of `planar_tessellation` over walkers padded past
    `n_walkers` (traced) with walkers in no triangle, whose rows are left out of `overflow`."""
    tess, complete = _planar_tessellation(points, simplices, adjacency, box, k_cap)
    padding = jnp.arange(points.shape[0], dtype=n_walkers.dtype) >= n_walkers
    return tess.neighbors, tess.hull, tess.tier, ~jnp.all(complete | padding)


def _planar_from_host(x: np.ndarray, simplices: np.ndarray, adjacency: np.ndarray, box, k_cap: int) -> Tessellation:
    """`planar_tessellation` of host arrays, compiled once per bucket of walker counts
    (`bucket_walkers`) instead of once per N: the walkers are padded with copies of the
    first that lie in no triangle (so they change no row, flag or tier), the triangles with
    two padding rows per padding walker (2D's bound of 2N triangles), and the rows cut back
    to the N walkers on the host."""
    n, m = len(x), bucket_walkers(len(x))
    points = jnp.asarray(x)
    padded = jnp.asarray(np.concatenate([x, np.repeat(x[:1], m - n, axis=0)]))
    extra = 2 * (m - n)
    triangles = np.concatenate([np.where(simplices == n, m, simplices), np.full((extra, 3), m, simplices.dtype)])
    across = np.concatenate([adjacency, np.full((extra, 3), -1, adjacency.dtype)])
    box = None if box is None else jnp.asarray(box, points.dtype)
    neighbors, hull, tier, overflow = _planar_rows(
        padded, jnp.asarray(triangles), jnp.asarray(across), box, jnp.asarray(n, jnp.int32), k_cap=k_cap
    )
    neighbors = np.asarray(neighbors)[:n]
    return Tessellation(
        points=points,
        neighbors=jnp.asarray(np.where(neighbors == m, n, neighbors)),
        tier=jnp.asarray(np.asarray(tier)[:n]),
        hull=jnp.asarray(np.asarray(hull)[:n]),
        simplices=jnp.asarray(simplices),
        neighbor_shifts=None,
        simplex_shifts=None,
        box=box,
        overflow=overflow,
        periodic=False,
    )


def planar_graph_on_device(points, box, capacity, backend: str) -> tuple[Tessellation | None, str | None]:
    """The 2D graph of `points` (a JAX array, or a host array copied in once as float64) built
    on the device by a backend whose triangles stay there (`DEVICE_BACKENDS`: CuPy): its
    triangles, their check, adjacency and largest degree (`planar_summary`), the fan walk and
    tiers (`_planar_rows`), all on the device; what reaches the host is one read of a few
    scalars (the check, the counts, the bounding box) and the backend's own reads. Walkers are
    padded to `bucket_walkers(N)` as on the host path.

    Returns `(graph, None)`; `(None, why)` when the backend failed or its triangles failed the
    check (the caller builds this graph on the host and counts the fallback); `(None, None)` when
    the backend refused the positions (non-finite: the host path raises the reason). Raises
    `CapacityError` for a pinned `capacity` the graph does not fit, and the host path's
    `ValueError`s for a mean spacing or a resolution the positions' dtype cannot represent."""
    n = points.shape[0]
    m = bucket_walkers(n)
    try:
        triangles, flat = device_triangles(points, 2 * m, m, backend)
    except ValueError:
        return None, None
    except Exception as err:  # noqa: BLE001 - any failure of the backend: the host builds this call
        return None, f"{backend} raised {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    points = jnp.asarray(points)
    padded, n_walkers = _pad_walkers(points, m), jnp.asarray(n, jnp.int32)
    (counts, corners), adjacency = planar_summary(padded, triangles, flat, n_walkers)
    (status, count, degree), corners = jax.device_get((counts, corners))
    spacing = spacing_of_box(corners[:2], corners[2:4], n)
    refuse_unrepresentable_spacing(spacing, points.dtype)
    refuse_unresolved_positions(spacing, float(corners[4]), points.dtype)
    if status:
        return None, f"{backend}'s triangulation failed its check: {DEVICE_REASONS[int(status)]}"
    cap = _fit_capacity(Capacity(int(count), int(degree)), n, 2, capacity)
    box = None if box is None else jnp.asarray(box, points.dtype)
    rows = _planar_rows(padded, triangles, adjacency, box, n_walkers, k_cap=cap.neighbors)
    return _cut_to_walkers(points, triangles, box, *rows, s_cap=cap.simplices), None


@functools.partial(jax.jit, static_argnums=1)
def _pad_walkers(points, m: int):
    """`points` with copies of the first up to `m` walkers (they are put in no triangle)."""
    return jnp.concatenate([points, jnp.broadcast_to(points[:1], (m - points.shape[0], points.shape[1]))])


@functools.partial(jax.jit, static_argnames="s_cap")
def _cut_to_walkers(points, triangles, box, neighbors, hull, tier, overflow, *, s_cap: int) -> Tessellation:
    """The `Tessellation` of the N = len(points) walkers from rows over M padded walkers
    (sentinel M -> N) and triangles padded to 2M rows (cut or padded to `s_cap`)."""
    n, m = points.shape[0], neighbors.shape[0]
    triangles = jnp.where(triangles == m, n, triangles)
    if s_cap <= triangles.shape[0]:
        triangles = triangles[:s_cap]  # the real triangles come first, and fit (`_fit_capacity`)
    else:
        triangles = jnp.concatenate([triangles, jnp.full((s_cap - triangles.shape[0], 3), n, triangles.dtype)])
    neighbors = neighbors[:n]
    return Tessellation(
        points=points,
        neighbors=jnp.where(neighbors == m, n, neighbors),
        tier=tier[:n],
        hull=hull[:n],
        simplices=triangles,
        neighbor_shifts=None,
        simplex_shifts=None,
        box=box,
        overflow=overflow,
        periodic=False,
    )


def _open_graph(x: np.ndarray, triangulator: str, capacity, box) -> tuple[Tessellation, tuple[str, ...]]:
    """`build_delaunay` without a torus, d >= 3 (Qhull in 3D from 3e4 walkers in slabs,
    `_slabs`). The simplices' checks (circumcentres and flat
    simplices, then cells reaching out of the domain) run on the device while the host builds
    the neighbour rows from the simplices (3D, N = 1e4: 2.9 ms against 11 ms for scipy's
    `vertex_neighbor_vertices`, which would also need a sort per row)."""
    n, d = x.shape
    slabs = slab_count(n, x) if triangulator == "qhull" else 1
    tri = slab_triangulation(x, slabs) if slabs > 1 else None
    if tri is None:  # no slabs, or their union failed a check: all walkers at once
        tri, perm, fallback, edge_keys = triangulate(x, triangulator)
    else:
        perm = fallback = edge_keys = None
    simplices, hull_ids = tri.simplices, tri.convex_hull.ravel()
    if perm is not None:  # map sorted indices back
        simplices, hull_ids = perm[simplices], perm[hull_ids]
    if n >= TRIM_WALKERS:
        _return_freed_memory()
    hull = np.zeros(n, bool)
    hull[hull_ids] = True
    s_cap = _simplex_capacity(len(simplices), n, d, capacity)
    graph = _checked_walkers(x, simplices, hull, box, s_cap)
    center, flat = circumcenters_and_flat(graph)
    deferred = _DEFERRED_TIERS.get()
    neighbors = tri.neighbors  # the simplex adjacency, padded only where read (not where the tiers are deferred)
    adjacency = lambda: jnp.asarray(_pad_adjacency(neighbors, s_cap))  # noqa: E731
    # the longest check (its hull walk), dispatched to run while the host builds the rows
    reaching_out = None if deferred is not None else _cells_reaching_out(graph, adjacency(), center)
    rows, cols = simplex_edges(simplices, n, edge_keys)  # a checked triangulation is unsorted: its keys fit
    cap = _fit_capacity(Capacity(len(simplices), _longest_run(rows, n)), n, d, capacity)
    nbrs = _pad_sorted_rows(rows, cols, n, cap.neighbors)
    padded_simplices = np.full((cap.simplices, d + 1), n, np.int32)
    padded_simplices[: len(simplices)] = simplices
    tess = Tessellation(
        points=jnp.asarray(x),
        neighbors=jnp.asarray(nbrs),
        tier=jnp.asarray(np.full(n, 2, np.int8)),
        hull=jnp.asarray(hull),
        simplices=jnp.asarray(padded_simplices),
        neighbor_shifts=None,
        simplex_shifts=None,
        box=None if box is None else jnp.asarray(box, dtype=jnp.asarray(x).dtype),
        overflow=jnp.asarray(False),
        periodic=False,
    )
    suspects = _cospherical_suspects(tess, *(np.asarray(a)[: len(simplices)] for a in (center, flat)))
    if suspects.size:
        tess = _drop_rows(tess, nbrs, None, _contacts_near(tess, _padded_walkers(tess), suspects))
    fallbacks = () if fallback is None else (fallback,)
    if deferred is not None:
        deferred.append(lambda final: tiers_of(_cells_reaching_out(graph, adjacency(), center)[:n], final))
        return tess, fallbacks
    tier = tiers_of(reaching_out[:n], tess)  # the rows without zero-measure contacts
    return eqx.tree_at(lambda t: t.tier, tess, tier), fallbacks


def _simplex_capacity(n_simplices: int, n: int, d: int, capacity) -> int:
    """The simplex capacity `_fit_capacity` gives (it raises later where too small)."""
    if capacity is None:
        return bucket_simplices(n_simplices)
    pinned = as_capacity(capacity).simplices
    if isinstance(capacity, GrowingCapacity) and n_simplices > pinned:
        return capacity.grow(Capacity(n_simplices, 0)).simplices
    return max(pinned, n_simplices)


def _checked_walkers(x, simplices, hull, box, s_cap: int):
    """The graph for the checks of `_open_graph`: the walkers padded to
    `bucket_walkers(N)` as in `_padded_walkers` (so that the checks compile once per bucket),
    the simplices to `s_cap`; the graph has no neighbour rows (one padding slot each), which
    the checks do not read."""
    n, d = x.shape
    m = bucket_walkers(n)
    simplices_m = np.full((s_cap, d + 1), m, np.int32)
    simplices_m[: len(simplices)] = simplices
    return Tessellation(
        points=jnp.asarray(_padded_points(x, m)),
        neighbors=jnp.full((m, 1), m, jnp.int32),
        tier=jnp.full((m,), 2, jnp.int8),
        hull=jnp.asarray(_grow(hull, m, False)),
        simplices=jnp.asarray(simplices_m),
        neighbor_shifts=None,
        simplex_shifts=None,
        box=None if box is None else jnp.asarray(box, dtype=jnp.asarray(x[:1]).dtype),
        overflow=jnp.asarray(False),
        periodic=False,
    )


def _longest_run(rows: np.ndarray, n: int) -> int:
    return int(np.bincount(rows, minlength=n).max())


def _pad_sorted_rows(rows: np.ndarray, cols: np.ndarray, n: int, k_cap: int) -> np.ndarray:
    """(N, K) rows from directed edges grouped by row (padding N at each row's end)."""
    nbrs = np.full((n, k_cap), n, np.int32)
    nbrs[rows, _slots_in_groups(rows)] = cols
    return nbrs


def _slots_in_groups(rows: np.ndarray) -> np.ndarray:
    """Each entry's place within its run of equal `rows` (grouped)."""
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    return np.arange(rows.size) - np.repeat(starts, np.diff(np.r_[starts, rows.size]))


def _periodic_graph(x: np.ndarray, box: np.ndarray, triangulator: str) -> RawGraph:
    """Periodic Delaunay graph from slabs of the box triangulated in parallel threads.

    The box is cut along its longest side into slabs; each slab triangulates its own
    walkers plus every periodic image within a skin around it (Qhull releases the GIL,
    so slabs run concurrently). A slab keeps the simplices whose canonical vertex it
    owns, so every periodic simplex is kept exactly once.
    """
    n, d = x.shape
    lengths = box[1] - box[0]
    spacing = (np.prod(lengths) / n) ** (1.0 / d)
    # Symbolic perturbation: a tiny fixed displacement per walker, the same for all its images,
    # makes co-circular input (lattices) generic, so every translate of a periodic simplex is
    # triangulated alike and the canonical-vertex rule keeps each exactly once.
    y0 = x - box[0]
    jitter = np.random.default_rng(0).uniform(-1.0, 1.0, (n, d))
    for tie_break in TIE_BREAKS:  # a larger one where Qhull could not resolve the smaller (tiling and star checks)
        raw, volume, stars = _periodic_raw(y0 + tie_break * spacing * jitter, y0, lengths, spacing, triangulator)
        if _tiles_the_box(volume, lengths) and stars % 2**64 == 0:
            return raw
    raise RuntimeError(
        "periodic Delaunay: the simplices do not tile the box, or a walker's star is not its kept simplices, after the "
        "largest tie-break; please report this input."
    )


def _tiles_the_box(volume: float, lengths: np.ndarray) -> bool:
    """Whether the periodic simplices' `volume` is the box's (to 1e-9): co-spherical walkers
    (an 8^3 cubic lattice) whose tie-break Qhull did not resolve were triangulated unalike in two
    slabs, leaving a gap at the seam. Unalike splits that still tile the box are the star
    check's (`_star_mismatch`)."""
    box_volume = float(np.prod(np.asarray(lengths, np.float64)))
    return bool(abs(volume - box_volume) <= 1e-9 * box_volume)  # numpy gives np.bool_


def _periodic_raw(y, y0, lengths, spacing: float, triangulator: str) -> tuple[RawGraph, float, int]:
    """`_periodic_graph` for one tie-break (`y` the perturbed walkers, `y0` the plain ones),
    its simplices' volume (of the perturbed walkers' images: those of a periodic triangulation
    tile the box as the plain ones do) and the slabs' `_star_mismatch`es summed (0 mod 2^64
    where every walker's star is its kept simplices)."""
    n, d = y.shape
    skin = skin_spacings(n, d) * spacing
    axis = int(np.argmax(lengths))
    # Every slab adds its skin's images. In 3D one slab per core, down to two skins thick, is
    # fastest (periodic `delaunay` with Qhull on 2 cores: N = 1e4 0.51 -> 0.27 s with two slabs
    # instead of one, 1e5 3.7 -> 3.2 s with two instead of four); in 2D CDT still gains from two
    # per core, four skins thick (1e5: 0.33 s against 0.36 s), bench/README.md.
    per_core, skins = SLABS.get(d, SLABS_ELSE)
    n_slabs = max(1, min(per_core * (os.cpu_count() or 1), MAX_SLABS, int(lengths[axis] // (skins * skin))))
    cuts = np.linspace(0.0, lengths[axis], n_slabs + 1)
    jobs = [(y, y0, lengths, axis, cuts[j], cuts[j + 1], skin, triangulator) for j in range(n_slabs)]
    if n_slabs == 1:
        parts = [_periodic_slab(*jobs[0])]
    else:
        with ThreadPoolExecutor(n_slabs) as pool:
            parts = list(pool.map(lambda job: _periodic_slab(*job), jobs))
    cat = lambda k: np.concatenate([p[k] for p in parts])  # noqa: E731
    fallbacks = tuple(reason for p in parts for reason in p[5])
    volume = sum(p[6] for p in parts)
    stars = sum(p[7] for p in parts)
    return RawGraph(cat(0), cat(1), cat(2), cat(3), cat(4), np.zeros(n, bool), fallbacks), volume, stars


def skin_spacings(n: int, d: int) -> float:
    """The initial periodic skin for N = `n` walkers in d dimensions, in mean spacings."""
    if d not in SKIN_GROWS_WITH_N or n <= 1e4:
        return SKIN_SPACINGS[d]
    return SKIN_SPACINGS[d] * (math.log(n) / math.log(1e4)) ** (1.0 / d)


def _periodic_slab(y, y0, lengths, axis: int, start: float, stop: float, skin: float, triangulator: str):
    """Exact periodic Delaunay star of the walkers with start <= y[axis] < stop, the fallback
    reasons of its triangulations, the volume of the simplices it keeps (from the skin check's
    determinants) and their `_star_mismatch`."""
    fallbacks = []
    widest = float(np.linalg.norm(lengths))  # an empty ball is narrower than the box's diagonal: this skin always does
    for _ in range(SKIN_ATTEMPTS):
        lo, hi = np.full(len(lengths), -skin), lengths + skin
        lo[axis], hi[axis] = start - skin, stop + skin
        ext, ids, shifts = _periodic_images(y, lengths, lo, hi)
        guards = _guards(lo, hi, GUARD_REACH * skin)
        guard = np.arange(len(ext) + len(guards)) >= len(ext)
        ext = np.concatenate([ext, guards])
        ids, shifts = np.pad(ids, (0, len(guards))), np.pad(shifts, ((0, len(guards)), (0, 0)))
        tri, perm, fallback, edge_keys = triangulate(ext, triangulator, enclosed=True)
        fallbacks += [] if fallback is None else [fallback]
        if perm is not None:
            ids, shifts, ext, guard = ids[perm], shifts[perm], ext[perm], guard[perm]
        home = y0[ids, axis]  # slabs own walkers by their unperturbed coordinate
        owned = ~guard & ~shifts.any(axis=1) & (home >= start) & (home < stop)
        simp = tri.simplices[owned[tri.simplices].any(axis=1)]
        empty, widest_inside, volumes = _check_circumballs(ext, simp, y, lengths, lo, hi)
        if empty and not guard[simp].any():
            break
        if skin >= widest:  # it holds every image a Delaunay neighbour can be: widening cannot help
            raise RuntimeError(
                "periodic Delaunay: the skin check failed at a skin of the box's diagonal; please report this input."
            )
        skin = min(max(skin * SKIN_GROWTH, 2.0 * (1.0 + SKIN_MARGIN) * widest_inside), widest)
    else:
        raise RuntimeError(
            "periodic Delaunay: the skin check failed after widening the skin; please report this input."
        )
    if edge_keys is None:
        src, dst = simplex_edges(simp, len(ext), sources=owned)  # every edge of an owned walker lies in `simp`
    else:  # the check's keys, of every simplex (ext ids: a checked triangulation is unsorted)
        src, dst = simplex_edges(tri.simplices, len(ext), edge_keys, owned)
    walkers, images, corners_owned = ids[simp], shifts[simp], owned[simp]
    at = _canonical_vertex(walkers, images)
    kept = corners_owned[np.arange(len(simp)), at]
    seam = ~corners_owned.all(axis=1)
    stars = _star_mismatch(walkers[seam], images[seam], at[seam], kept[seam], corners_owned[seam])
    volume = float(volumes[kept].sum())
    return walkers[kept], images[kept], ids[src], ids[dst], shifts[dst], fallbacks, volume, stars


def _star_mismatch(ids: np.ndarray, shifts: np.ndarray, at: np.ndarray, kept: np.ndarray, owned: np.ndarray) -> int:
    """A slab's share of the star check: the sum mod 2^64 of a hash of every (simplex, vertex)
    of the simplices it keeps, minus that of every (simplex, owned walker) of its owned walkers'
    stars, over its seam simplices (`ids`, `shifts` (M, d + 1, d): those with a vertex it does
    not own; `at` (M,) their canonical vertices, `kept` (M,) whether it keeps them, `owned`
    (M, d + 1) which vertices it owns).

    Summed over the slabs it is 0 (to a 2^-64 chance) exactly where every walker's kept
    simplices are its star in the slab that owns it. A simplex whose vertices the slab all owns
    is in their stars and kept (its canonical vertex is owned), so only seam simplices can
    differ: where the triangulator split translates of co-spherical walkers unalike (an 8^3
    lattice at a 2.6-spacing skin), even when the kept simplices still tile the box. The hash
    of a (simplex, vertex) is that of its walkers' ids and shifts relative to its canonical
    vertex (the same in every translate) with the vertex's own."""
    if not len(ids):
        return 0
    d = shifts.shape[-1]
    relative = shifts.astype(np.int64) - shifts[np.arange(len(ids)), at][:, None, :]
    code = np.zeros(ids.shape, np.uint64)  # 16 bits per axis (relative int8 shifts: |s| <= 254)
    for axis in range(d):
        code |= (relative[..., axis] + 2**15).astype(np.uint64) << np.uint64(16 * axis)
    vertex = _mix(_mix(ids.astype(np.uint64)) ^ code)
    simplex = _mix(vertex.sum(axis=1))  # the vertices in any order
    entry = _mix(simplex[:, None] ^ vertex)
    kept_sum = int(entry[kept].sum(dtype=np.uint64))
    star_sum = int(entry[owned].sum(dtype=np.uint64))
    return (kept_sum - star_sum) % 2**64


def _mix(z: np.ndarray) -> np.ndarray:
    """splitmix64's finalizer of uint64 `z` (a bijection that spreads every bit over all)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


GUARD_REACH = 1.0  # the guards' distance outside a slab's region, in skins
# fixed irregular moves of the guards (in units of their reach): 2^d corners of a box are co-spherical
GUARD_WOBBLE = np.random.default_rng(7).uniform(-0.25, 0.25, (16, 4))


def _guards(lo, hi, reach: float) -> np.ndarray:
    """(2^d, d) points that enclose a slab's region (lo, hi): its corners moved `reach` outward,
    each by a fixed irregular amount more. Their hull, a few big simplices, is the whole
    triangulation's, in place of the images' ragged outer layer: exact translates there make
    Qhull merge many co-spherical facets (3D, N = 1e4, images 3 spacings around the box: 463
    -> 367 ms). A walker in a simplex with a guard is on the images' hull: its skin is too thin."""
    d = len(lo)
    corners = np.array(list(itertools.product((0, 1), repeat=d)), bool)
    return (
        np.where(corners, hi + reach, lo - reach)
        + np.where(corners, 1.0, -1.0) * np.abs(GUARD_WOBBLE[: 2**d, :d]) * reach
    )


def _periodic_images(y: np.ndarray, lengths: np.ndarray, lo, hi):
    """Every periodic image of `y` (box-relative) with all coordinates in (lo, hi)."""
    n, d = y.shape
    reach = int(np.ceil(max(np.max(-lo / lengths), np.max((hi - lengths) / lengths), 0)))
    offsets = range(-reach, reach + 1)
    # per axis and offset, the walkers whose coordinate lands inside: an image is inside where
    # all its axes are (N = 1e5, 27 images: 3-6 ms, against 59 ms for shifting every walker)
    inside = [
        {s: (y[:, k] + s * lengths[k] > lo[k]) & (y[:, k] + s * lengths[k] < hi[k]) for s in offsets} for k in range(d)
    ]
    pts, ids, shifts = [], [], []
    for s in itertools.product(offsets, repeat=d):
        keep = np.flatnonzero(np.logical_and.reduce([inside[k][s[k]] for k in range(d)])).astype(np.int32)
        pts.append(y[keep] + np.asarray(s) * lengths)
        ids.append(keep)
        shifts.append(np.broadcast_to(np.asarray(s, np.int8), (keep.size, d)))
    return np.concatenate(pts), np.concatenate(ids), np.concatenate(shifts)


def _check_circumballs(points: np.ndarray, simplices: np.ndarray, y: np.ndarray, lengths: np.ndarray, lo, hi):
    """Whether no periodic image outside the region (lo, hi) lies strictly inside the
    circumball of a simplex (rows of `points`), the widest radius of the balls inside the
    region (0 if none), and the simplices' volumes (S,) (float64, from the same determinants:
    the tiling check's).

    Balls inside the region are empty by construction (Qhull saw every point
    there), so they are true Delaunay balls and the widest is a lower bound on the
    swarm's widest empty ball; the few that poke out are checked against the images
    just outside.
    """
    pokes, widest_inside, finite = [], 0.0, True
    volumes = np.empty(len(simplices))
    for rows in host_chunks(len(simplices)):
        center, radius, det = circumballs_and_determinants(points[simplices[rows]])
        volumes[rows] = np.abs(det) / math.factorial(points.shape[1])
        finite &= bool(np.isfinite(radius).all())
        poke = np.any((center - radius[:, None] < lo) | (center + radius[:, None] > hi), axis=1)
        widest_inside = max(widest_inside, float(radius.max(initial=0.0, where=~poke)))
        pokes.append((center[poke], radius[poke]))
    if not finite:
        return False, widest_inside, volumes
    center, radius = (np.concatenate(parts) for parts in zip(*pokes, strict=True))
    if not len(radius):
        return True, widest_inside, volumes
    if np.any(radius > 0.5 * np.linalg.norm(lengths)):
        # it holds a whole period: an image of every walker, some outside the region
        return False, widest_inside, volumes
    reach_lo = np.minimum((center - radius[:, None]).min(axis=0), lo)
    reach_hi = np.maximum((center + radius[:, None]).max(axis=0), hi)
    outer, _, _ = _periodic_images(y, lengths, reach_lo, reach_hi)
    outer = outer[~np.all((outer > lo) & (outer < hi), axis=1)]
    if len(outer) == 0:
        return True, widest_inside, volumes
    dist, _ = cKDTree(outer).query(center, k=1)
    return bool(np.all(dist >= radius * (1.0 - 1e-10))), widest_inside, volumes


def _circumballs(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Circumcentres (S, d) and radii (S,) of simplices p (S, d + 1, d) (`circumballs_and_determinants`)."""
    center, radius, _ = circumballs_and_determinants(p)
    return center, radius


def _canonical_vertex(ids: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Per simplex, the vertex with the smallest key (original index, then image shift).

    Translating a simplex does not change which vertex that is, so keeping the one
    translate in which that vertex is an owned original (shift zero) keeps every
    periodic simplex exactly once. Returns that vertex's position (0..d) in each simplex.
    """
    span = int(np.abs(shifts).max()) if shifts.size else 0
    key = ids.astype(np.int64)
    for k in range(shifts.shape[-1]):
        key = key * (2 * span + 1) + (shifts[..., k].astype(np.int64) + span)
    return np.argmin(key, axis=1)


def as_capacity(capacity) -> Capacity:
    if isinstance(capacity, Tessellation):
        return capacity.capacity
    if isinstance(capacity, GrowingCapacity):
        return capacity.floor
    try:
        simplices, neighbors = (int(v) for v in capacity)
    except (TypeError, ValueError):
        raise TypeError(
            "`capacity` must be a jaxgeom.Capacity, a (simplices, neighbors) tuple of ints, "
            f"a Tessellation or None; got {capacity!r}."
        ) from None
    return Capacity(simplices, neighbors)


def _fit_capacity(need: Capacity, n: int, d: int, capacity) -> Capacity:
    """`capacity` if the graph needs no more (else `CapacityError`); buckets for None."""
    if capacity is None:
        # In 2D a triangulation has at most 2N triangles (exactly 2N on the torus).
        simplices = 2 * n if d == 2 else bucket_simplices(need.simplices)
        return Capacity(simplices, bucket_neighbors(need.neighbors))
    pinned = as_capacity(capacity)
    if pinned.simplices < need.simplices or pinned.neighbors < need.neighbors:
        if isinstance(capacity, GrowingCapacity):
            return capacity.grow(need)
        raise CapacityError(
            f"`capacity` {tuple(pinned)} is too small for this graph: it needs simplices >= "
            f"{need.simplices} and neighbors >= {need.neighbors}. Pass capacity=None to size it "
            "automatically, or a larger Capacity."
        )
    return pinned


def _pad_periodic_neighbors(raw: RawGraph, n: int, k_cap: int):
    """Scatter grouped directed edges with their images into (N, K) rows, sorted by neighbour
    index, then image."""
    rows, cols, shifts = raw.nbr_rows, raw.nbr_cols, raw.nbr_shifts
    assert shifts is not None
    slot = _slots_in_groups(rows)
    # each slot's (neighbour, image) is one integer key of bit fields, sorted in place: ties of
    # a neighbour seen at two images go by image, as in the dual's row keys (3D, N = 1e6 in a
    # build: 1.5 s against 2.7 s for an argsort and two gathers)
    d = shifts.shape[1]
    span = int(np.abs(shifts).max(initial=0))
    bits = max(1, (2 * span).bit_length())  # per axis
    dtype = np.int32 if (n + 1) << (bits * d) < 2**31 else np.int64
    code = np.zeros(rows.size, dtype)
    for axis in range(d):
        code = np.left_shift(code, bits) | (shifts[:, axis].astype(dtype) + span)
    unshifted = sum(span << (bits * axis) for axis in range(d))
    keys = np.full((n, k_cap), (n << (bits * d)) | unshifted, dtype)  # padding: walker n, no shift
    keys[rows, slot] = (cols.astype(dtype) << (bits * d)) | code
    keys.sort(axis=1)
    image = np.empty((n, k_cap, d), np.int8)
    for axis in range(d):
        image[..., axis] = ((keys >> (bits * (d - 1 - axis))) & ((1 << bits) - 1)) - span
    return (keys >> (bits * d)).astype(np.int32), image


def _pad_simplices(raw: RawGraph, n: int, s_cap: int):
    s, d1 = raw.simplices.shape
    simplices = np.full((s_cap, d1), n, np.int32)
    simplices[:s] = raw.simplices
    if raw.simplex_shifts is None:
        return simplices, None
    shifts = np.zeros((s_cap, d1, d1 - 1), np.int8)
    shifts[:s] = raw.simplex_shifts
    return simplices, shifts


def _assemble_periodic(x: np.ndarray, raw: RawGraph, cap: Capacity, box) -> Tessellation:
    n = len(x)
    nbrs, nbr_shifts = _pad_periodic_neighbors(raw, n, cap.neighbors)
    simplices, simplex_shifts = _pad_simplices(raw, n, cap.simplices)
    tess = Tessellation(
        points=jnp.asarray(x),
        neighbors=jnp.asarray(nbrs),
        tier=jnp.asarray(np.full(n, 2, np.int8)),
        hull=jnp.asarray(raw.hull),
        simplices=jnp.asarray(simplices),
        neighbor_shifts=jnp.asarray(nbr_shifts),
        simplex_shifts=jnp.asarray(simplex_shifts),
        box=jnp.asarray(box, dtype=jnp.asarray(x).dtype),
        overflow=jnp.asarray(False),
        periodic=True,
    )
    padded = _padded_walkers(tess)
    center, flat = (np.asarray(a)[: len(raw.simplices)] for a in circumcenters_and_flat(padded))
    suspects = _cospherical_suspects(tess, center, flat)
    if suspects.size:
        tess = _drop_rows(tess, nbrs, nbr_shifts, _contacts_near(tess, padded, suspects))
    return tess


def _padded_walkers(tess: Tessellation) -> Tessellation:
    """`tess` for the jitted steps of a host build, with walkers added up to
    `bucket_walkers(N)` so that they compile once per bucket instead of once per N: copies of
    the first walker in no simplex and with no neighbour, so every per-simplex result and
    every row of the N walkers is unchanged (and the caller keeps those)."""
    n = tess.n_points
    m = bucket_walkers(n)
    relabel = lambda a: np.where(a == n, m, a)  # noqa: E731  (the sentinel)
    return eqx.tree_at(
        lambda t: (t.points, t.neighbors, t.tier, t.hull, t.simplices, t.neighbor_shifts),
        tess,
        (
            jnp.asarray(_padded_points(np.asarray(tess.points), m)),
            jnp.asarray(_grow(relabel(np.asarray(tess.neighbors)), m, m)),
            jnp.asarray(_grow(np.asarray(tess.tier), m, 2)),
            jnp.asarray(_grow(np.asarray(tess.hull), m, False)),
            jnp.asarray(relabel(np.asarray(tess.simplices))),
            None if tess.neighbor_shifts is None else jnp.asarray(_grow(np.asarray(tess.neighbor_shifts), m, 0)),
        ),
        is_leaf=lambda leaf: leaf is None,
    )


def _grow(a: np.ndarray, m: int, fill) -> np.ndarray:
    """`a` with rows of `fill` appended up to `m` rows."""
    return np.concatenate([a, np.full((m - len(a), *a.shape[1:]), fill, a.dtype)])


def _padded_points(points: np.ndarray, m: int) -> np.ndarray:
    """`points` with copies of the first appended up to `m` rows (walkers in no simplex)."""
    return np.concatenate([points, np.repeat(points[:1], m - len(points), axis=0)])


def _cospherical_suspects(tess: Tessellation, center: np.ndarray, flat: np.ndarray) -> np.ndarray:
    """Host pre-check for `positive_measure_contacts` (a compilation of seconds per shape):
    the simplices (ids) that may hold a zero-measure contact. Such contacts exist only inside
    a Delaunay cell split into several simplices, which then share a circumcentre (or are
    flat). Centres are compared on a grid of 1e-9 mean spacings, modulo the box when periodic.
    In float32 the centres' own rounding makes slivers look flat and near-cospherical centres
    coincide: those few suspects are decided again in float64, where only centres within the
    walkers' float32 rounding still count as shared (3D, N = 1e5 uniform: 5 suspects, of
    which 2 pairs 1e-6 spacings apart remain). `center`, `flat`: `circumcenters_and_flat` of
    the simplices (host, their padding cut)."""
    suspects = flat | _shared_centers(center, tess)
    rows = np.flatnonzero(suspects)
    if not rows.size or tess.points.dtype == np.float64:
        return rows
    coords = np.asarray(tess.points, np.float64)[np.asarray(tess.simplices)[rows]]
    if tess.periodic:
        coords = coords + np.asarray(tess.simplex_shifts)[rows] * np.asarray(tess.box_lengths, np.float64)
    center64, radius = _circumballs(coords)
    # the walkers' own float32 rounding moves truly shared centres apart by ~eps32 |x|
    rounding = 4 * float(np.finfo(np.float32).eps) * float(np.abs(coords).max())
    if not np.isfinite(radius).all():
        return rows
    return rows[_shared_centers(center64, tess, rounding)]  # shared with another suspect's (only they can)


LOCAL_CONTACTS = 0.25  # suspects' simplices up to this fraction of all: the contact test runs on them alone
LOCAL_WALKERS = 1024  # the least walker capacity of that local test (fewer shapes to compile)


def _contacts_near(tess: Tessellation, padded: Tessellation, suspects: np.ndarray) -> np.ndarray:
    """(N, K) host bool: `positive_measure_contacts` where a contact can be degenerate, True
    elsewhere. A degenerate contact is an edge of a suspect simplex, so both its ends are
    walkers of suspects, and every simplex around it holds one of them: the test runs on
    those simplices alone and their walkers, relabelled into a small graph (`_local_graph`;
    a few hundred simplices at N = 1e5 uniform, where the test over all 672k took 3.4 s,
    and at 1e6 the whole graph's (N K, 3, 3) sums took 2.4 GiB), on all of them when they are
    more than `LOCAL_CONTACTS` of the simplices (a lattice)."""
    n = tess.n_points
    simplices = np.asarray(tess.simplices)
    near = np.zeros(n + 1, bool)
    near[simplices[suspects].ravel()] = True
    near[n] = False
    around = np.flatnonzero(near[simplices].any(axis=1))
    if len(around) > LOCAL_CONTACTS * len(simplices):
        return np.asarray(positive_measure_contacts(padded))[:n]
    neighbors = np.asarray(tess.neighbors)
    local, walkers, slots = _local_graph(tess, simplices, neighbors, around)
    found = np.asarray(positive_measure_contacts(local))[: len(walkers)]
    keep = np.ones(neighbors.shape, bool)
    rows = np.broadcast_to(walkers[:, None], slots.shape)
    real = slots < neighbors.shape[1]  # slots of neighbours outside the local graph: not tested
    keep[rows[real], slots[real]] = found[real]
    candidate = near[:n, None] & near[neighbors]
    return np.where(candidate, keep, neighbors < n)


def _local_graph(tess: Tessellation, simplices: np.ndarray, neighbors: np.ndarray, around: np.ndarray):
    """The simplices `around` (ids) and their walkers as a graph of their own (`simplices`,
    `neighbors`: `tess`'s on the host): walkers relabelled in ascending order (so rows stay
    sorted), padded to `bucket_walkers` (at least LOCAL_WALKERS) with copies of the first in no
    simplex, their neighbour rows cut to the walkers kept (`_kept_first`: the others become
    padding at the rows' ends), simplices padded to `bucket_simplices`. Returns (graph, walkers
    (W,) their ids in `tess`, slots (W, K) each local slot's slot in `tess`, K where padding)."""
    n, k = neighbors.shape
    simplices = simplices[around]
    walkers = np.unique(simplices)
    walkers = walkers[walkers < n]
    m = bucket_walkers(max(len(walkers), LOCAL_WALKERS))
    label = np.full(n + 1, m, np.int32)
    label[walkers] = np.arange(len(walkers), dtype=np.int32)
    rows = label[neighbors[walkers]]
    shifts = None if tess.neighbor_shifts is None else np.asarray(tess.neighbor_shifts)[walkers]
    rows, shifts, order = _kept_first(rows, shifts, rows < m, m)
    slots = np.where(rows < m, order, k)
    size = bucket_simplices(max(len(simplices), 64))
    local_simplices = np.full((size, simplices.shape[1]), m, np.int32)
    local_simplices[: len(simplices)] = label[simplices]
    neighbor_shifts = simplex_shifts = None
    if shifts is not None:
        neighbor_shifts = jnp.asarray(_grow(shifts, m, 0))
        simplex_shifts = jnp.asarray(_grow(np.asarray(tess.simplex_shifts)[around], size, 0))
    local = Tessellation(
        points=jnp.asarray(_padded_points(np.asarray(tess.points)[walkers], m)),
        neighbors=jnp.asarray(_grow(rows, m, m)),
        tier=jnp.asarray(np.full(m, 2, np.int8)),
        hull=jnp.asarray(_grow(np.asarray(tess.hull)[walkers], m, False)),
        simplices=jnp.asarray(local_simplices),
        neighbor_shifts=neighbor_shifts,
        simplex_shifts=simplex_shifts,
        box=tess.box,
        overflow=jnp.asarray(False),
        periodic=tess.periodic,
    )
    return local, walkers, slots


def _kept_first(nbrs: np.ndarray, shifts, keep: np.ndarray, fill: int):
    """Each row of `nbrs` (host (R, K)) with its `keep` slots first, in their order, and the
    others `fill` (shifts (R, K, d) or None moved alike, 0 there); and the order (R, K): the
    slot each place came from."""
    order = np.argsort(~keep, axis=1, kind="stable")
    kept = np.take_along_axis(keep, order, axis=1)
    nbrs = np.where(kept, np.take_along_axis(nbrs, order, axis=1), fill)
    if shifts is not None:
        shifts = np.where(kept[..., None], np.take_along_axis(shifts, order[..., None], axis=1), 0)
    return nbrs, shifts, order


def _drop_rows(tess: Tessellation, nbrs: np.ndarray, shifts, keep: np.ndarray) -> Tessellation:
    """`tess` without the neighbour slots where `keep` (host (N, K)) is False, the kept ones in
    their order (rows stay sorted by neighbour index), on the host."""
    n = tess.n_points
    keep = keep & (nbrs < n)
    rows = np.flatnonzero(((nbrs < n) & ~keep).any(axis=1))  # the rows that lose a neighbour
    if not rows.size:
        return tess
    nbrs = nbrs.copy()
    nbrs[rows], moved, _ = _kept_first(nbrs[rows], None if shifts is None else shifts[rows], keep[rows], n)
    if shifts is not None:
        shifts = shifts.copy()
        shifts[rows] = moved
    return eqx.tree_at(
        lambda t: (t.neighbors, t.neighbor_shifts),
        tess,
        (jnp.asarray(nbrs), None if shifts is None else jnp.asarray(shifts)),
        is_leaf=lambda leaf: leaf is None,
    )


def _shared_centers(center: np.ndarray, tess: Tessellation, tolerance: float = 0.0) -> np.ndarray:
    """(S,) bool: centres that another centre shares on a grid of 1e-9 mean spacings (or
    `tolerance`, if coarser); a centre that is not finite (a flat simplex's) counts as shared."""
    if not np.isfinite(center).all():  # the test per row costs 0.8 ms at 66k centres, the global one 0.02
        finite = np.isfinite(center).all(axis=1)
        shared = np.ones(len(center), bool)
        shared[finite] = _shared_centers(center[finite], tess, tolerance)
        return shared
    x = np.asarray(tess.points, np.float64)
    if tess.periodic:
        box = np.asarray(tess.box, np.float64)
        center = np.mod(center - box[0], box[1] - box[0])
    keys = np.round(center / max(1e-9 * mean_spacing(x), tolerance)).astype(np.int64)
    hashed = keys @ np.array(
        [1, 1_000_003, 998_244_353, 1_000_000_007][: x.shape[1]], np.int64
    )  # a collision only costs time
    ordered = np.sort(hashed)  # a value sort (SIMD in numpy 2): 3D, 6.8M centres 0.05 s, np.unique's 0.5-0.8 s
    return np.isin(hashed, ordered[1:][ordered[1:] == ordered[:-1]])


def _pad_adjacency(adjacency: np.ndarray, s_cap: int) -> np.ndarray:
    """Simplex adjacency padded to `s_cap` rows of -1 (host)."""
    out = np.full((s_cap, adjacency.shape[1]), -1, np.int32)
    out[: len(adjacency)] = adjacency
    return out


@jax.jit
def boundary_tiers(tess: Tessellation, adjacency=None):
    """Tier 0: an unbounded cell, or a cell reaching outside the domain (`cells_reaching_out`);
    tier 1: a neighbour of tier 0; tier 2: the rest."""
    centers = jax.vmap(simplex_circumcenter)(simplex_coords(tess))
    return tiers_of(cells_reaching_out(tess, adjacency, centers), tess)


def cells_reaching_out(tess: Tessellation, adjacency, centers):
    """(N,) bool: hull walkers (unbounded cells) and walkers of a simplex whose circumcentre
    `centers` (a Voronoi vertex) lies outside the box, or without a box outside the convex hull
    of the walkers (found by `circumcenters_outside_hull` when the simplex `adjacency` is given:
    such a cell's extent is set by the missing walkers beyond the sample, 400x the mean volume
    next to the edge of a Boltzmann sample)."""
    reaching = tess.hull
    outside = None
    if tess.box is not None:
        outside = jnp.any((centers < tess.box[0]) | (centers > tess.box[1]), axis=-1)
    elif adjacency is not None:
        outside = circumcenters_outside_hull(tess, adjacency, centers)
    if outside is not None:
        votes = jnp.broadcast_to((outside & tess.simplex_mask)[:, None], tess.simplices.shape).astype(jnp.int32)
        at = jax.ops.segment_sum(votes.ravel(), tess.simplices.ravel(), num_segments=tess.n_points)
        reaching = reaching | (at > 0)
    return reaching


_cells_reaching_out = jax.jit(cells_reaching_out)


@jax.jit
def tiers_of(tier0, tess: Tessellation):
    """(N,) int8 tiers from the tier-0 flags and the graph's neighbour rows."""
    tier1 = neighbor_any(tess, tier0) & ~tier0
    return jnp.where(tier0, 0, jnp.where(tier1, 1, 2)).astype(jnp.int8)


HULL_WALK_STEPS = 64  # a walk still going after this many simplices counts as outside
HULL_WALK_ALL = 3  # steps taken by every simplex; the few still walking then go on in lanes


def circumcenters_outside_hull(tess: Tessellation, adjacency, centers):
    """(S,) bool: whether each simplex's circumcentre lies outside the convex hull, by a
    visibility walk: from the simplex, step across the face with the most negative
    barycentric coordinate of the centre until a simplex contains it (inside) or the face
    is on the hull (outside). Flat simplices stop at once (inside: they have no centre).
    Most centres lie in or next to their simplex: after `HULL_WALK_ALL` steps of all
    simplices, the ones still walking (near the hull) go on in `hull_walk_batch` lanes, a
    lane taking the next waiting walk as soon as its own ends, which makes the walk O(S)
    instead of O(S x longest walk) (2D, N = 1e6: 0.2 s instead of 2.3 s), and no lane idles
    until a batch's longest walk ends (3D: a clustered swarm of 1e4 walkers 4.2 ms instead of
    7.4 ms in batches, 1e5 uniform 86 ms instead of 104 ms). The program holds two walk steps
    (all simplices, the lanes)."""
    s_count = tess.simplices.shape[0]
    current = jnp.arange(s_count, dtype=jnp.int32)
    state = jnp.where(tess.simplices[:, 0] < tess.n_points, _WALKING, _INSIDE)
    current, state = _hull_walk(tess, adjacency, centers, current, state, HULL_WALK_ALL)
    waiting = state == _WALKING
    (queue,) = jnp.nonzero(waiting, size=s_count, fill_value=s_count)  # the walks left, in order
    queue = queue.astype(jnp.int32)
    n_waiting = jnp.sum(waiting, dtype=jnp.int32)
    lanes = hull_walk_batch(s_count)
    empty = jnp.full((lanes,), s_count, jnp.int32)
    # carry: state, the queue's next place, each lane's walk (s_count: none), simplex, steps
    carry = (state, jnp.zeros((), jnp.int32), empty, empty, jnp.zeros((lanes,), jnp.int32))

    def busy(carry):
        _, head, walk, _, _ = carry
        return (head < n_waiting) | jnp.any(walk < s_count)

    def step(carry):
        state, head, walk, at, steps = carry
        free = walk == s_count
        place = head + jnp.cumsum(free, dtype=jnp.int32) - 1  # the lanes' next walks from the queue
        taken = jnp.take(queue, place, mode="fill", fill_value=s_count)
        walk = jnp.where(free, taken, walk)
        at = jnp.where(free, jnp.take(current, taken, mode="fill", fill_value=0), at)
        steps = jnp.where(free, HULL_WALK_ALL, steps)
        head = head + jnp.sum(free, dtype=jnp.int32)
        lane_state = jnp.where(walk < s_count, _WALKING, _INSIDE)
        at, lane_state = _walk_step(tess, adjacency, jnp.take(centers, walk, axis=0, mode="clip"), at, lane_state)
        steps = steps + 1
        ended = (walk < s_count) & ((lane_state != _WALKING) | (steps >= HULL_WALK_STEPS))
        state = state.at[jnp.where(ended, walk, s_count)].set(lane_state, mode="drop")  # still walking: outside
        return state, head, jnp.where(ended, s_count, walk), at, steps

    state = jax.lax.while_loop(busy, step, carry)[0]
    return state != _INSIDE


def hull_walk_batch(s_count: int) -> int:
    """Lanes of the long visibility walks (`circumcenters_outside_hull`)."""
    return min(s_count, 64 + 8 * math.isqrt(s_count))


_WALKING, _INSIDE, _OUTSIDE = 0, 1, 2


def _walk_step(tess, adjacency, centers, current, state):
    """One step of the visibility walk of `centers` from simplices `current` (those `_WALKING`)."""
    verts = [take_or_zero(tess.points, tess.simplices[current, a]) for a in range(tess.dim + 1)]
    coords = _barycentric(verts, centers)
    worst = jnp.argmin(coords, axis=0)
    done = jnp.min(coords, axis=0) >= -1e-9
    across = adjacency[current, worst]
    new_state = jnp.where(done, _INSIDE, jnp.where(across < 0, _OUTSIDE, _WALKING))
    state = jnp.where(state == _WALKING, new_state, state)
    return jnp.where(state == _WALKING, across, current), state


def _hull_walk(tess, adjacency, centers, current, state, steps: int):
    """At most `steps` steps of the visibility walk of `centers` from simplices `current`."""

    def step(carry):
        k, current, state = carry
        return k + 1, *_walk_step(tess, adjacency, centers, current, state)

    _, current, state = jax.lax.while_loop(
        lambda c: (c[0] < steps) & jnp.any(c[2] == _WALKING), step, (0, current, state)
    )
    return current, state


def _barycentric(verts, point):
    """(d + 1, S) barycentric coordinates of `point` in simplices with vertices `verts`
    (d + 1 arrays (S, d)); all 1 / (d + 1) for a flat simplex (treated as containing it)."""
    d = point.shape[-1]
    rel = [[verts[a][:, c] - verts[0][:, c] for c in range(d)] for a in range(1, d + 1)]
    total = det_entries(rel)
    scale = functools.reduce(jnp.maximum, [sum(r[c] ** 2 for c in range(d)) for r in rel]) ** (0.5 * d)
    flat = jnp.abs(total) <= 1e-12 * scale
    safe = jnp.where(flat, 1.0, total)
    parts = []
    for a in range(d + 1):
        replaced = [point if b == a else verts[b] for b in range(d + 1)]
        rows = [[replaced[b][:, c] - replaced[0][:, c] for c in range(d)] for b in range(1, d + 1)]
        parts.append(jnp.where(flat, 1.0 / (d + 1), det_entries(rows) / safe))
    return jnp.stack(parts)
