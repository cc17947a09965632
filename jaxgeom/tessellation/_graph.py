"""The neighbour-graph pytree shared by every kernel, and its gather helpers."""

from __future__ import annotations

import functools
import inspect
import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
from jaxtyping import Array, Bool, Float, Int

from ..base._checks import check_metric_array, check_walker_array, real_array
from ..base._simplex import WRITTEN_OUT_MAX_DIM, safe_sqrt


class Capacity(NamedTuple):
    """Static array capacities of a [`jaxgeom.Tessellation`][].

    **Fields:**

    - `simplices`: rows of `Tessellation.simplices` (0 for a k-NN graph).
    - `neighbors`: columns of `Tessellation.neighbors`.
    """

    simplices: int
    neighbors: int


class Tessellation(eqx.Module):
    """A swarm's neighbour graph as fixed-shape padded arrays.

    Padding uses the sentinel index `N` (the number of walkers); every mask is
    derived from it. Capacities are the array shapes, so they are static under
    `jax.jit`, and graphs built with the same capacities share compiled kernels.

    **Fields:**

    - `points`: (N, d) walker positions, as given.
    - `neighbors`: (N, K) int32 neighbour indices, padding = N. Delaunay graphs
      list, in ascending index order, the cells that share a Voronoi face of positive
      measure: on degenerate input (lattices) the diagonals Qhull adds to split
      co-circular cells stay in `simplices` but are not neighbours (contacts between
      two hull walkers are all kept). k-NN graphs list neighbours nearest first.
    - `tier`: (N,) int8 boundary tier: 0 = unbounded cell or cell touching the
      box, 1 = neighbour of tier 0, 2 = interior. Periodic graphs are all tier 2.
    - `hull`: (N,) bool, the walker's Voronoi cell is unbounded (convex-hull
      vertex of a non-periodic Delaunay graph).
    - `simplices`: (S, d + 1) int32 Delaunay simplices, padding rows = N;
      `None` for a k-NN graph.
    - `neighbor_shifts`: (N, K, d) int8 periodic image of each neighbour:
      the displacement to neighbour `j` is `x[j] + shift * L - x[i]`;
      `None` unless periodic.
    - `simplex_shifts`: (S, d + 1, d) int8 image of each simplex vertex, same
      convention; `None` unless periodic or without simplices.
    - `box`: (2, d) rows `lower`, `upper`, or `None`.
    - `overflow`: () bool, True when the graph did not fit its capacities (it
      is then incomplete) or a periodic k-NN neighbour lies farther than half
      the box. Host builders raise instead; jitted rebuilds set this flag.
    - `periodic`: static bool.
    - `carried`: (N, d_all - d) the walkers' coordinates past the first `spatial_dims`,
      carried along untessellated (`delaunay(..., spatial_dims=k)`, `knn_graph`); `None`
      when every coordinate was tessellated. Geometry uses `points` only.
    """

    points: Float[Array, "N d"]
    neighbors: Int[Array, "N K"]
    tier: Int[Array, " N"]
    hull: Bool[Array, " N"]
    simplices: Int[Array, "S d1"] | None
    neighbor_shifts: Int[Array, "N K d"] | None
    simplex_shifts: Int[Array, "S d1 d"] | None
    box: Float[Array, "2 d"] | None
    overflow: Bool[Array, ""]
    periodic: bool = eqx.field(static=True, default=False)
    carried: Float[Array, "N m"] | None = None

    @property
    def all_coordinates(self) -> Float[Array, "N d_all"]:
        """(N, d_all) the walkers' full positions: `points`, then the `carried` coordinates."""
        return self.points if self.carried is None else jnp.concatenate([self.points, self.carried], axis=1)

    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def dim(self) -> int:
        return self.points.shape[1]

    @property
    def capacity(self) -> Capacity:
        n_simplices = 0 if self.simplices is None else self.simplices.shape[0]
        return Capacity(simplices=n_simplices, neighbors=self.neighbors.shape[1])

    @property
    def neighbor_mask(self) -> Bool[Array, "N K"]:
        return self.neighbors < self.n_points

    @property
    def simplex_mask(self) -> Bool[Array, " S"]:
        if self.simplices is None:
            raise ValueError("this Tessellation has no simplices (a k-NN graph); use jaxgeom.delaunay")
        return self.simplices[:, 0] < self.n_points

    @property
    def degree(self) -> Int[Array, " N"]:
        return jnp.sum(self.neighbor_mask, axis=1)

    @property
    def interior(self) -> Bool[Array, " N"]:
        """Tier-2 walkers, on which observables are reported."""
        return self.tier == 2

    @property
    def box_lengths(self) -> Float[Array, " d"] | None:
        return None if self.box is None else self.box[1] - self.box[0]


def take_or_zero(values: Array, index: Int[Array, ...]) -> Array:
    """`values[index]` along the first axis, zero where `index` is the sentinel `len(values)`.

    A gather in mode "fill", never `values` with a zero row concatenated: jaxlib 0.8 and 0.9
    miscompile that concatenation on x86 CPUs for float64 rows of 4 (4D points): the last
    row is stored 96 bytes past the buffer, a heap overflow that aborted `delaunay` of 6 to
    8 walkers in 4D (issue 61; tests/test_smallest_inputs.py checks every compiled kernel).
    """
    return values.at[index].get(mode="fill", fill_value=0)


def neighbor_displacements(tess: Tessellation) -> Float[Array, "N K d"]:
    """x_j - x_i for every neighbour slot (periodic images applied); zero on padding."""
    if tess.dim <= WRITTEN_OUT_MAX_DIM:
        return jnp.stack(neighbor_coord_displacements(tess), axis=-1)
    dx = take_or_zero(tess.points, tess.neighbors) - tess.points[:, None, :]  # rows: one gather in any d
    if tess.neighbor_shifts is not None and tess.box_lengths is not None:
        dx = dx + tess.neighbor_shifts.astype(dx.dtype) * tess.box_lengths
    return jnp.where(tess.neighbor_mask[..., None], dx, 0.0)


def neighbor_displacements_for_sums(tess: Tessellation):
    """The neighbours' displacements in the layout of per-walker sums over them: d arrays
    (N, K) up to d = WRITTEN_OUT_MAX_DIM (`neighbor_coord_displacements`, for sums written out
    entry by entry), one (N, K, d) array above (`neighbor_displacements`, for einsums)."""
    if tess.dim > WRITTEN_OUT_MAX_DIM:
        return neighbor_displacements(tess)
    return neighbor_coord_displacements(tess)


def neighbor_coord_displacements(tess: Tessellation) -> list:
    """`neighbor_displacements` coordinate-major: d arrays (N, K), the fast layout on CPU."""
    mask = tess.neighbor_mask
    out = []
    for k in range(tess.dim):
        dx = take_or_zero(tess.points[:, k], tess.neighbors) - tess.points[:, k, None]
        if tess.neighbor_shifts is not None:
            dx = dx + tess.neighbor_shifts[..., k].astype(dx.dtype) * tess.box_lengths[k]
        out.append(jnp.where(mask, dx, 0.0))
    return out


def neighbor_distances(tess: Tessellation) -> Float[Array, "N K"]:
    """Euclidean |x_j - x_i| for every neighbour slot; zero on padding."""
    return safe_sqrt(sum(dx * dx for dx in neighbor_coord_displacements(tess)))


def nearest_neighbor_distances(tess: Tessellation) -> Float[Array, " N"]:
    """Distance from each walker to its nearest neighbour (inf without neighbours)."""
    return row_minimum(neighbor_distances(tess), tess.neighbor_mask)


def row_minimum(lengths, mask) -> Float[Array, " N"]:
    """Smallest edge length of each row over its real slots (inf for a row without any)."""
    return minimum_along_rows(jnp.where(mask, lengths, jnp.inf))


def minimum_along_rows(values) -> Array:
    """`jnp.min(values, axis=-1)` by halving the rows with elementwise minima. XLA on the CPU
    turns a min-reduction over more than 32 slots into a reduce-window that costs ~2.5x the
    whole halving (3D step, (1e4, 48) slots: ~1.2 ms against ~0.35 ms). The same values, and
    the same gradient where a row's minimum is unique; at a tie of three or more the gradient
    is shared out by halves (`jnp.min` shares it equally), with the same sum. Rows of none: inf."""
    return _halving(values, jnp.minimum, jnp.inf)


def maximum_along_rows(values) -> Array:
    """`jnp.max(values, axis=-1)` as `minimum_along_rows` takes the minimum. Rows of none: -inf."""
    return _halving(values, jnp.maximum, -jnp.inf)


def any_along_rows(flags) -> Array:
    """`jnp.any(flags, axis=-1)` by halving, as `minimum_along_rows` (no reduce-window)."""
    return _halving(flags, jnp.logical_or, False)


def _halving(values, combine, empty) -> Array:
    if values.shape[-1] == 0:
        return jnp.full(values.shape[:-1], empty, values.dtype)
    while values.shape[-1] > 1:
        half = values.shape[-1] // 2
        paired = combine(values[..., :half], values[..., half : 2 * half])
        values = jnp.concatenate([paired, values[..., 2 * half :]], axis=-1) if values.shape[-1] % 2 else paired
    return values[..., 0]


def mean_row_minimum(lengths, mask) -> Float[Array, ""]:
    """Mean over walkers with a neighbour of their smallest edge length (0 if none has one)."""
    nearest = row_minimum(lengths, mask)
    ok = jnp.isfinite(nearest)
    return jnp.sum(jnp.where(ok, nearest, 0.0)) / jnp.maximum(jnp.sum(ok), 1).astype(lengths.dtype)


def padded_to_csr(neighbors, values, n: int):
    """Host: a scipy CSR matrix with entry (i, neighbors[i, k]) = values[i, k] on real slots."""
    nbrs, vals = np.asarray(neighbors), np.asarray(values, dtype=np.float64)
    rows, slots = np.nonzero(nbrs < n)
    return scipy.sparse.csr_matrix((vals[rows, slots], (rows, nbrs[rows, slots])), shape=(n, n))


def simplex_coords(tess: Tessellation) -> tuple:
    """Simplex vertex coordinates, coordinate-major: d arrays (S, d + 1), periodic images applied.

    The layout the simplex kernels are vmapped over (one 1-D gather per coordinate).
    """
    if tess.simplices is None:
        raise ValueError("this Tessellation has no simplices (a k-NN graph); use jaxgeom.delaunay")
    coords = [take_or_zero(tess.points[:, k], tess.simplices) for k in range(tess.dim)]
    if tess.simplex_shifts is not None:
        lengths = tess.box_lengths
        coords = [c + tess.simplex_shifts[..., k].astype(c.dtype) * lengths[k] for k, c in enumerate(coords)]
    return tuple(coords)


def simplex_vertices(tess: Tessellation) -> Float[Array, "S d1 d"]:
    """Vertex coordinates of every simplex (periodic images applied); `simplex_coords` stacked."""
    return jnp.stack(simplex_coords(tess), axis=-1)


def neighbor_any(tess: Tessellation, flags: Bool[Array, " N"]) -> Bool[Array, " N"]:
    """For each walker, whether any of its neighbours has `flags` set."""
    padded = jnp.concatenate([flags, jnp.zeros((1,), bool)])
    return jnp.any(padded[tess.neighbors], axis=1)


def bucket_neighbors(k_max: int) -> int:
    """Neighbour capacity: the next multiple of 8 (at least 8)."""
    return max(8, 8 * math.ceil(k_max / 8))


def bucket_simplices(n: int) -> int:
    """Simplex capacity: the next step of a ladder with 8 steps per octave (at most 12.5% waste)."""
    if n <= 16:
        return 16
    octave = 2 ** (math.ceil(math.log2(n)) - 4)  # ladder values are multiples of this
    return octave * math.ceil(n / octave)


def bucket_walkers(n: int) -> int:
    """Walkers a host build pads to before its jitted part, so that swarms of nearby sizes
    share one compiled program: the simplex ladder (at most 12.5% padding)."""
    return bucket_simplices(n)


# A periodic walker may neighbour several images of the same walker (tiny boxes);
# slot lookup scans this many consecutive columns for the matching image shift.
MAX_IMAGES_PER_NEIGHBOR = 8


def lower_bound_in_rows(table, rows, values):
    """Binary search in rows sorted ascending: the first column k with
    `table[rows, k] >= values` (K, the width, where there is none), as the count of entries
    below, by steps of halving powers of two with one value carried, one flat gather per step.
    A loop keeps each step a fusion of its own (3D `voronoi_facets` at N = 1e5: 16% faster than
    unrolled (lower, upper) halvings, which also fused worse into 2D's: 30% slower there)."""
    k_cap = table.shape[1]
    flat = table.ravel()
    base = rows * k_cap

    def halve(i, below_count):
        step = jnp.right_shift(1 << (k_cap.bit_length() - 1), i)
        probe = below_count + (step - 1)
        below = (probe < k_cap) & (flat[base + jnp.minimum(probe, k_cap - 1)] < values)
        return jnp.where(below, below_count + step, below_count)

    return jax.lax.fori_loop(0, k_cap.bit_length(), halve, jnp.zeros_like(values))


def edge_slots(tess: Tessellation, src, dst, shift=None):
    """Column k with `neighbors[src, k] == dst` (and `neighbor_shifts[src, k] == shift`).

    Binary search over Delaunay rows, which the builder keeps sorted by neighbour
    index. Returns K (the capacity, an out-of-range id) where the edge is absent.
    """
    k_cap = tess.neighbors.shape[1]
    flat = tess.neighbors.ravel()
    lo = lower_bound_in_rows(tess.neighbors, src, dst)
    if tess.neighbor_shifts is None:
        found = (lo < k_cap) & (flat[src * k_cap + jnp.minimum(lo, k_cap - 1)] == dst)
        return jnp.where(found, lo, k_cap)
    flat_shifts = tess.neighbor_shifts.reshape(-1, tess.dim)
    slot = jnp.full_like(src, k_cap)
    for t in reversed(range(MAX_IMAGES_PER_NEIGHBOR)):
        k = lo + t
        at = src * k_cap + jnp.minimum(k, k_cap - 1)
        match = (k < k_cap) & (flat[at] == dst) & jnp.all(flat_shifts[at] == shift, axis=-1)
        slot = jnp.where(match, k, slot)
    return slot


def takes_tessellation(fn):
    """Decorator for public kernels: checked outside any jit, on concrete values only, that the
    first argument is a `jaxgeom.Tessellation` and that `metric`, `values`, `velocities`,
    `volumes` and `volume_weights` (where the kernel has them) are real arrays of the right
    shape, volumes >= 0; a metric array must also be symmetric positive definite."""
    signature = inspect.signature(fn)

    @functools.wraps(fn)
    def call(tess, *args, **kwargs):
        if not isinstance(tess, Tessellation):
            raise TypeError(
                f"jaxgeom.{fn.__name__} takes a jaxgeom.Tessellation as `tess`; got {type(tess).__name__}. "
                "Build one first: tess = jaxgeom.delaunay(points) or jaxgeom.knn_graph(points, k)."
            )
        call_args = signature.bind_partial(tess, *args, **kwargs)
        bound = call_args.arguments
        for name in ("values", "velocities", "volumes", "volume_weights"):  # plain lists: arrays (jit would
            if isinstance(bound.get(name), (list, tuple)):  # take them as pytrees)
                bound[name] = real_array(bound[name], name)
        n, d = tess.points.shape
        if bound.get("mode", "full") != "none":
            check_metric_array(bound.get("metric"), n, d)
        for name, shape in (("values", (n,)), ("velocities", (n, d))):
            check_walker_array(bound.get(name), name, shape)
        for name in ("volumes", "volume_weights"):  # cell volumes: >= 0 where finite
            check_walker_array(bound.get(name), name, (n,), nonnegative=True)
        return fn(*call_args.args, **call_args.kwargs)

    return call


def split_spatial_dims(points, box, spatial_dims, func: str):
    """The first `spatial_dims` coordinates of `points` (host or traced), the rest, and `box`
    restricted to the tessellated coordinates (a box of d_all-vectors is cut to its first k)."""
    if spatial_dims is None:
        return points, None, box
    d_all = np.shape(points)[-1] if np.ndim(points) == 2 else None
    if isinstance(spatial_dims, bool) or not isinstance(spatial_dims, (int, np.integer)):
        raise TypeError(
            f"{func}: `spatial_dims` must be a Python int k (tessellate the first k coordinates); "
            f"got {type(spatial_dims).__name__}."
        )
    if d_all is None:
        return points, None, box  # the shape error is the builder's
    if not 2 <= spatial_dims <= d_all:
        raise ValueError(
            f"{func}: `spatial_dims` must lie in [2, {d_all}] for {d_all}-dimensional points; "
            f"got {spatial_dims}. Pass spatial_dims=None to tessellate every coordinate."
        )
    k = int(spatial_dims)
    if box is not None and not isinstance(box, str):
        box = _cut_box(box, d_all, k)
    if k == d_all:
        return points, None, box
    return points[:, :k], points[:, k:], box


def _cut_box(box, d_all: int, k: int):
    """A (2, d_all) box cut to its first k columns; anything else is left to the box checks."""
    try:
        arr = box if isinstance(box, jax.Array) else np.asarray(box)
    except ValueError:
        return box
    return arr[:, :k] if arr.ndim == 2 and arr.shape[-1] == d_all else box
