"""Geodesic distances on the metric-weighted neighbour graph.

The distance between two walkers is the shortest path along neighbour edges, each edge
as long as its metric length sqrt(dx^T g_edge dx) (`jaxgeom.edge_lengths`)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.sparse.csgraph import dijkstra

from ._checks import check_choice, takes_tessellation
from ._graph import Tessellation, padded_to_csr
from ._metric import edge_lengths

GEODESIC_METHODS = ("dijkstra", "bellman_ford")


@takes_tessellation
def geodesic_distances(tess: Tessellation, sources, *, metric=None, mode: str = "full",
                       method: str = "dijkstra") -> Float[Array, "M N"]:
    """Shortest-path distances along graph edges weighted by metric edge lengths.

    **Arguments:**

    - `tess`: Delaunay or k-NN graph (k-NN edges are used in both directions).
    - `sources`: int or sequence of walker indices.
    - `metric`, `mode`: as in [`jaxgeom.edge_lengths`][].
    - `method`: "dijkstra" runs `scipy.sparse.csgraph.dijkstra` on the host.
      "bellman_ford" is jittable: parallel min-plus relaxation over the padded
      neighbours in a `lax.while_loop` until nothing changes, and differentiable
      in the edge lengths (hence the metric): the gradient of each distance flows
      along its shortest-path tree (a subgradient where shortest paths tie).

    **Returns:**

    (len(sources), N) distances; unreachable walkers are inf. Concrete sources outside
    [0, N) are a ValueError; traced ones (Bellman-Ford under jit) give a row of inf.
    """
    check_choice(method, "method", GEODESIC_METHODS)
    src = _check_sources(sources, tess.n_points)
    lengths = edge_lengths(tess, metric=metric, mode=mode)
    if method == "dijkstra":
        return jnp.asarray(_dijkstra(tess, lengths, np.asarray(src)), dtype=lengths.dtype)
    symmetric = tess.simplices is not None
    return jax.vmap(lambda s: _bellman_ford(lengths, tess.neighbors, s, symmetric))(jnp.atleast_1d(src).astype(jnp.int32))


def _check_sources(sources, n: int):
    if isinstance(sources, jax.core.Tracer):
        if not jnp.issubdtype(sources.dtype, jnp.integer):
            raise ValueError(f"`sources` must be integer walker indices; got dtype {sources.dtype}.")
        return jnp.atleast_1d(sources)
    arr = np.atleast_1d(np.asarray(sources))
    if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer)) or arr.size == 0:
        raise ValueError(f"`sources` must be an int or a 1-D sequence of walker indices; got {sources!r}.")
    if arr.min() < 0 or arr.max() >= n:
        raise ValueError(f"`sources` must lie in [0, N) = [0, {n}); got values from {arr.min()} to {arr.max()}.")
    return jnp.asarray(arr, dtype=jnp.int32)


def _dijkstra(tess: Tessellation, lengths, sources: np.ndarray) -> np.ndarray:
    return dijkstra(padded_to_csr(tess.neighbors, lengths, tess.n_points), directed=False, indices=sources)


def _candidates(dist, lengths, neighbors, symmetric: bool):
    """Best relaxation of every walker: (value, predecessor walker, flat edge index)."""
    n, k_cap = neighbors.shape
    pad = jnp.concatenate([dist, jnp.full((1,), jnp.inf, dist.dtype)])
    pull = pad[neighbors] + lengths  # path to j, then edge (i, k) with j = neighbors[i, k]
    best_k = jnp.argmin(pull, axis=1).astype(jnp.int32)
    walkers = jnp.arange(n, dtype=jnp.int32)
    value = jnp.take_along_axis(pull, best_k[:, None], axis=1)[:, 0]
    pred = jnp.take_along_axis(neighbors, best_k[:, None], axis=1)[:, 0]
    edge = walkers * k_cap + best_k
    if symmetric:
        return value, pred, edge
    # k-NN lists are one-sided: also push along (i, k) from i to neighbors[i, k]
    push = (dist[:, None] + lengths).ravel()
    targets = neighbors.ravel()
    push_min = jax.ops.segment_min(push, targets, num_segments=n)
    push_min_pad = jnp.concatenate([push_min, jnp.full((1,), jnp.inf, dist.dtype)])
    is_best = push == push_min_pad[targets]
    push_edge = jax.ops.segment_max(jnp.where(is_best, jnp.arange(n * k_cap, dtype=jnp.int32), -1), targets,
                                    num_segments=n)
    use_push = push_min < value
    safe_edge = jnp.maximum(push_edge, 0)
    return (jnp.where(use_push, push_min, value), jnp.where(use_push, safe_edge // k_cap, pred),
            jnp.where(use_push, safe_edge, edge))


@functools.partial(jax.custom_vjp, nondiff_argnums=(3,))
def _bellman_ford(lengths, neighbors, source, symmetric: bool):
    return _bellman_ford_forward(lengths, neighbors, source, symmetric)[0]


def _bellman_ford_forward(lengths, neighbors, source, symmetric: bool):
    n = neighbors.shape[0]
    inside = (source >= 0) & (source < n)  # traced sources are not checked: outside [0, N) is a row of inf
    dist0 = jnp.full((n,), jnp.inf, lengths.dtype).at[jnp.where(inside, source, n)].set(0.0, mode="drop")

    def body(state):
        dist, _, count = state
        new = jnp.minimum(dist, _candidates(dist, lengths, neighbors, symmetric)[0])
        return new, jnp.any(new < dist), count + 1

    dist, _, _ = jax.lax.while_loop(lambda s: s[1] & (s[2] < n), body, (dist0, jnp.asarray(True), 0))
    _, pred, edge = _candidates(dist, lengths, neighbors, symmetric)
    has_pred = jnp.isfinite(dist) & (jnp.arange(n, dtype=jnp.int32) != source)
    return dist, (jnp.where(has_pred, pred, n), jnp.where(has_pred, edge, lengths.size))


def _bellman_ford_fwd(lengths, neighbors, source, symmetric):
    dist, residuals = _bellman_ford_forward(lengths, neighbors, source, symmetric)
    return dist, (residuals, neighbors, source)


def _bellman_ford_bwd(symmetric, saved, cotangent):
    (pred, edge), neighbors, source = saved
    shape = neighbors.shape  # the shape of `lengths`
    n = pred.shape[0]
    g = jnp.where(jnp.isfinite(cotangent), cotangent, 0.0)

    def body(state):  # adjoint: a_t = g_t + sum of a over walkers whose predecessor is t
        adjoint, _, count = state
        new = g + jax.ops.segment_sum(adjoint, pred, num_segments=n)
        return new, jnp.any(new != adjoint), count + 1

    adjoint, _, _ = jax.lax.while_loop(lambda s: s[1] & (s[2] < n), body, (g, jnp.asarray(True), 0))
    grad = jax.ops.segment_sum(adjoint, edge, num_segments=int(np.prod(shape))).reshape(shape)
    return grad, None, None


_bellman_ford.defvjp(_bellman_ford_fwd, _bellman_ford_bwd)
