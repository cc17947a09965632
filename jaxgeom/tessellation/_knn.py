"""Exact k-nearest-neighbour graphs in any dimension."""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int
from scipy.spatial import cKDTree

from ..base._checks import check_choice, host_box, host_points
from ._graph import Tessellation, neighbor_any, split_spatial_dims

KNN_METHODS = ("auto", "kdtree", "brute")
# Elements of one (block, N) distance tile in the brute-force path.
TILE_ELEMENTS = 2**22


def knn_graph(
    points, k: int, *, box=None, periodic: bool = False, method: str = "auto", spatial_dims: int | None = None
) -> Tessellation:
    """Graph of the exact k nearest neighbours of every walker, in any dimension.

    **Arguments:**

    - `points`: (N, d) float array; may be a tracer (inside `jax.jit`).
    - `k`: neighbours per walker, a Python int with 1 <= k < N (static).
    - `box`: `(lower, upper)`; with `periodic=False` walkers whose k-NN ball
      reaches outside the box are tier 0 and their neighbours tier 1. Without a
      box a k-NN graph has no boundary and every walker is tier 2.
    - `periodic`: minimum-image distances in `box`; each neighbour's integer
      image shift is stored. The flag `overflow` is set where a k-th neighbour is
      farther than half the shortest box side (the nearest image is then ambiguous).
    - `method`: `"brute"` is jittable: blocked all-pairs distances with
      `lax.top_k`, memory O(N * TILE_ELEMENTS / N) and time O(N^2 d);
      `"kdtree"` uses scipy's cKDTree on the host (O(N log N), not jittable);
      `"auto"` takes `"kdtree"` for concrete inputs and `"brute"` under a trace.
      Under a trace inputs cannot be checked: a walker with NaN or inf coordinates
      gets no neighbours (its row is all at the sentinel N, degree 0) and is nobody's
      neighbour; periodic walkers outside the box count as their image inside it.

    **Returns:**

    A `Tessellation` with (N, k) neighbours, nearest first, and no simplices.
    """
    check_choice(method, "method", KNN_METHODS)
    traced = isinstance(points, jax.core.Tracer)
    if method == "auto":
        method = "brute" if traced else "kdtree"
    if not traced:
        points = host_points(points, "points", func="jaxgeom.knn_graph")
    points, carried, box = split_spatial_dims(points, box, spatial_dims, "jaxgeom.knn_graph")
    if traced:
        x, box_arr = _traced_points(points, box, periodic, method)
    else:
        x = points
        box_arr = host_box(box, x, periodic=periodic)
    k = _check_k(k, x.shape[0])
    lengths = None if box_arr is None or not periodic else box_arr[1] - box_arr[0]
    if method == "kdtree":
        nbrs = jnp.asarray(_kdtree_neighbors(x, k, box_arr, periodic))
    else:
        nbrs = _brute_neighbors(jnp.asarray(x), k, lengths)
    tess = _knn_tessellation(jnp.asarray(x), nbrs, None if box_arr is None else jnp.asarray(box_arr), periodic)
    if carried is None:
        return tess
    return eqx.tree_at(
        lambda t: t.carried, tess, jnp.asarray(carried, tess.points.dtype), is_leaf=lambda leaf: leaf is None
    )


def _traced_points(points, box, periodic, method):
    if method == "kdtree":
        raise TypeError(
            "knn_graph(method='kdtree') runs on the host and cannot be traced; use method='brute' inside jit."
        )
    if points.ndim != 2 or not jnp.issubdtype(points.dtype, jnp.floating):
        raise TypeError(f"`points` must be an (N, d) float array; got shape {points.shape}, dtype {points.dtype}.")
    if box is None and periodic:
        raise ValueError("`periodic=True` needs `box=(lower, upper)`: the periodic cell is not known otherwise.")
    box_arr = (
        None if box is None else jnp.broadcast_to(jnp.asarray(box, points.dtype).reshape(2, -1), (2, points.shape[1]))
    )
    return points, box_arr


def _check_k(k, n: int) -> int:
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise TypeError(f"`k` must be a Python int (it sets an array shape); got {type(k).__name__}.")
    if not 1 <= k < n:
        raise ValueError(f"`k` must satisfy 1 <= k < N = {n}; got k={k}. Use fewer neighbours or more walkers.")
    return int(k)


def _kdtree_neighbors(x: np.ndarray, k: int, box, periodic: bool) -> np.ndarray:
    if periodic:
        lengths = box[1] - box[0]
        tree = cKDTree(np.mod(x - box[0], lengths), boxsize=lengths)
    else:
        tree = cKDTree(x)
    _, idx = tree.query(tree.data, k=k + 1)
    is_self = idx == np.arange(len(x))[:, None]
    is_self[:, -1] |= ~is_self.any(axis=1)  # duplicates may push self out: drop the farthest
    order = np.argsort(is_self, axis=1, kind="stable")
    return np.take_along_axis(idx, order, axis=1)[:, :k].astype(np.int32)


@functools.partial(jax.jit, static_argnums=1)
def _brute_neighbors(x: Float[Array, "N d"], k: int, lengths) -> Int[Array, "N k"]:
    n = x.shape[0]
    block = max(1, min(n, TILE_ELEMENTS // n))
    n_blocks = math.ceil(n / block)
    queries = jnp.arange(n_blocks * block).reshape(n_blocks, block)

    def one_block(q):
        d2 = _sq_distances(x, x.at[q].get(mode="fill", fill_value=0.0), lengths)
        d2 = jnp.where((q[:, None] == jnp.arange(n)[None, :]) | jnp.isnan(d2), jnp.inf, d2)
        neg_d2, idx = jax.lax.top_k(-d2, k)
        return jnp.where(jnp.isfinite(neg_d2), idx, n)  # non-finite walkers: no neighbours, nobody's neighbour

    return jax.lax.map(one_block, queries).reshape(-1, k)[:n].astype(jnp.int32)


def _sq_distances(x, q, lengths):
    """(B, N) squared (minimum-image) distances, accumulated one coordinate at a time."""

    def add_coordinate(acc, cols):
        xc, qc, length = cols
        diff = xc[None, :] - qc[:, None]
        if lengths is not None:
            diff = diff - length * jnp.round(diff / length)
        return acc + diff * diff, None

    per_coord = jnp.ones(x.shape[1], x.dtype) if lengths is None else jnp.asarray(lengths, x.dtype)
    acc0 = jnp.zeros((q.shape[0], x.shape[0]), x.dtype)
    return jax.lax.scan(add_coordinate, acc0, (x.T, q.T, per_coord))[0]


@functools.partial(jax.jit, static_argnums=3)
def _knn_tessellation(x, nbrs, box, periodic: bool) -> Tessellation:
    n, d = x.shape
    dx = x.at[nbrs].get(mode="fill", fill_value=0.0) - x[:, None, :]  # padding (NaN walkers) at the sentinel N
    shifts, overflow = None, jnp.asarray(False)
    if periodic:
        lengths = box[1] - box[0]
        image = -jnp.round(dx / lengths)
        shifts = image.astype(jnp.int8)
        dx = dx + image * lengths
        overflow = jnp.any(jnp.linalg.norm(dx, axis=-1) > 0.5 * jnp.min(lengths))
    tess = Tessellation(
        points=x,
        neighbors=nbrs,
        tier=jnp.full((n,), 2, jnp.int8),
        hull=jnp.zeros((n,), bool),
        simplices=None,
        neighbor_shifts=shifts,
        simplex_shifts=None,
        box=box,
        overflow=overflow,
        periodic=periodic,
    )
    if box is None or periodic:
        return tess
    radius = jnp.sqrt(jnp.max(jnp.where(nbrs < n, jnp.sum(dx * dx, axis=-1), 0.0), axis=1))[:, None]
    tier0 = jnp.any((x - radius < box[0]) | (x + radius > box[1]), axis=1)
    tier1 = neighbor_any(tess, tier0) & ~tier0
    tier = jnp.where(tier0, 0, jnp.where(tier1, 1, 2)).astype(jnp.int8)
    return eqx.tree_at(lambda t: t.tier, tess, tier)
