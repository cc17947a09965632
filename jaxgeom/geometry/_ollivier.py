"""Ollivier-Ricci curvature of the neighbour graph, exact transport per edge, in any dimension.

For an edge (x, y), m_x puts mass alpha on x and 1 - alpha on x's neighbours (uniform, a
distance kernel, or GraphRicciCurvature's e^{-w^2}); kappa(x, y) = 1 - W1(m_x, m_y) / d(x, y)
with W1 the exact transport cost under a ground cost d between the two neighbourhoods:

- "graph": the shortest path through the graph with metric edge lengths, over paths of at
  most `HOP_RADIUS` = 3 edges (the smallest radius that always joins the two neighbourhoods:
  u -> x -> y -> v). Distances come from per-walker two-hop tables (every walker's shortest
  paths of <= 2 edges, sorted by id) and one more edge: d(u, v) = min_b D2(u, b) + l(b, v).
- "hops": the same with unit lengths (GraphRicciCurvature on an unweighted graph); here the
  radius is no restriction: d(u, v) <= 3 through the edge, so D2 decides exactly.
- "direct": the metric length of the straight segment u -> v (g at its midpoint), the
  ground cost of the continuum definition on a geometric graph.

A k-NN graph is made undirected first (the union of both directions), as networkx does.
The scalar estimate uses Ollivier's expansion (J. Funct. Anal. 256, 2009, Example 7): for a
measure with second moment E|w|^2 about x, isotropic in a Riemannian n-manifold,
kappa(x, y) = E|w|^2 Ric(v, v) / (2 n) + O(delta^3 + delta^2 d(x, y)), lazy measures scaled by
1 - alpha; for the uniform measure on a ball of radius delta this is delta^2 Ric / (2 (n + 2)).
Averaged over a walker's edges (directions roughly isotropic), Ric(v, v) -> S / n, so
S ~ 2 n^2 mean(kappa) / ((1 - alpha) E|w|^2).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..base._checks import check_choice, check_integer, check_number, check_positive
from ..base._simplex import safe_sqrt
from ..tessellation._graph import (
    Tessellation,
    bucket_neighbors,
    bucket_simplices,
    neighbor_displacements,
    take_or_zero,
    takes_tessellation,
)
from ._metric import (
    _call_metric,
    _quad,
    _with_mode,
    _wrap,
    check_metric,
    edge_sq_lengths,
    warns_on_defective_metric,
)
from ._transport import transport_cost

ORC_MEASURES = ("uniform", "kernel", "grc")
ORC_COSTS = ("graph", "hops", "direct")
ORC_SOLVERS = ("exact",)
HOP_RADIUS = 3
# Edges solved together (one vmapped batch of `lax.map`); with the edges grouped by support
# width, 512 measured fastest of 32/128/512/2048 at N = 1e4 (k = 10, 2D) on a 2-core CPU. An
# accelerator runs each while-loop iteration as a few launches whatever the batch, so there
# fewer, wider batches win (bench/README.md, "Ollivier-Ricci curvature").
EDGE_BATCH = {"cpu": 512}
EDGE_BATCH_ACCELERATOR = 32768
WIDTH_STEP = 4  # edge groups' support widths are multiples of this (or K + 1)


def default_edge_batch() -> int:
    """Edges per vmapped batch on the default backend (module notes above)."""
    return EDGE_BATCH.get(jax.default_backend(), EDGE_BATCH_ACCELERATOR)


class OllivierRicci(eqx.Module):
    """Ollivier-Ricci curvature of every edge of an undirected neighbour graph.

    **Fields:**

    - `neighbors`: (N, K) the undirected graph's neighbour rows (ascending, padding = N);
      a k-NN graph's rows are the union of both directions, so K can exceed its k.
    - `edge_curvature`: (N, K) kappa of each edge, aligned with `neighbors`; NaN on padding.
    - `walker_curvature`: (N,) mean kappa over the walker's edges; NaN where `isolated`.
    - `scalar_curvature`: (N,) the scalar-curvature estimate 2 n^2 mean(kappa_e / m2_e) /
      (1 - alpha), m2_e the mean second moment of the two measures (see the module notes);
      NaN for cost="hops" (hop counts are not a Riemannian distance), alpha = 1 or isolated.
    - `second_moment`: (N,) E|w|^2 of the walker's neighbour measure in metric lengths.
    - `isolated`: (N,) walkers without neighbours (no curvature; excluded from summaries).
    - `interior`: (N,) the graph's tier-2 walkers (all of them for a k-NN graph without box).
    - `not_converged`: (N,) walkers with an edge whose transport hit its iteration cap with
      more than rounding-level mass unplaced (its kappa is then not exact).
    - `overflow`: () the undirected graph did not fit its capacity (edges are missing).
    """

    neighbors: Int[Array, "N K"]
    edge_curvature: Float[Array, "N K"]
    walker_curvature: Float[Array, " N"]
    scalar_curvature: Float[Array, " N"]
    second_moment: Float[Array, " N"]
    isolated: Bool[Array, " N"]
    interior: Bool[Array, " N"]
    not_converged: Bool[Array, " N"]
    overflow: Bool[Array, ""]

    @property
    def edge_mask(self) -> Bool[Array, "N K"]:
        return self.neighbors < self.neighbors.shape[0]

    @property
    def mean_curvature(self) -> Float[Array, ""]:
        """Mean kappa over all edges (each undirected edge once; isolated walkers have none)."""
        kappa = jnp.where(self.edge_mask, self.edge_curvature, 0.0)
        return jnp.sum(kappa) / jnp.maximum(jnp.sum(self.edge_mask), 1).astype(kappa.dtype)

    @property
    def mean_scalar_curvature(self) -> Float[Array, ""]:
        """Plain mean of `scalar_curvature` over interior walkers that have one."""
        ok = self.interior & jnp.isfinite(self.scalar_curvature)
        values = jnp.where(ok, self.scalar_curvature, 0.0)
        return jnp.where(jnp.any(ok), jnp.sum(values) / jnp.maximum(jnp.sum(ok), 1).astype(values.dtype), jnp.nan)


@takes_tessellation
@warns_on_defective_metric
def ollivier_ricci(
    tess: Tessellation,
    *,
    alpha=0.5,
    metric=None,
    mode: str = "full",
    measure: str = "uniform",
    cost: str = "graph",
    kernel_scale=None,
    solver: str = "exact",
    capacity: int | None = None,
    batch_size: int | None = None,
) -> OllivierRicci:
    """Ollivier-Ricci curvature kappa = 1 - W1(m_x, m_y) / d(x, y) of every graph edge.

    **Arguments:**

    - `tess`: a Delaunay or k-NN [`jaxgeom.Tessellation`][] (a k-NN graph is made undirected).
    - `alpha`: laziness in [0, 1], the mass m_x keeps on x (GraphRicciCurvature's default 0.5).
    - `metric`: None (Euclidean), an (N, d, d) array or a callable x -> g; edge lengths,
      the kernel and the scalar estimate are measured in it.
    - `mode`: how much of the metric to use, "none", "diagonal" or "full".
    - `measure`: how x's 1 - alpha spreads over its neighbours: "uniform"; "kernel"
      (exp(-l^2 / (2 h^2)), h = `kernel_scale` or the walker's mean edge length); "grc"
      (exp(-w^2) with w the edge weight, 1 for cost="hops": GraphRicciCurvature's rule).
    - `cost`: the ground cost, "graph" (shortest path of <= 3 edges in metric lengths),
      "hops" (shortest path in edges) or "direct" (metric length of the segment); the
      module notes say what each is.
    - `kernel_scale`: h of measure="kernel", in metric length (> 0); default per walker.
    - `solver`: "exact" (successive shortest paths; exact up to rounding).
    - `capacity`: neighbour columns of the undirected k-NN graph (default: its largest degree
      rounded up to a multiple of 8 for a concrete graph, 2k under a trace).
    - `batch_size`: edges whose transports run side by side (vmapped); memory grows with it,
      the result changes only by rounding. Default 512 on the CPU, 32768 on an accelerator.

    **Returns:**

    An [`jaxgeom.OllivierRicci`][]. Jittable with a traced graph and differentiable with
    respect to positions and metric parameters (envelope gradients of the transport).
    """
    check_number(alpha, "alpha", low=0.0, high=1.0, hint=" (the mass the measure keeps on the walker)")
    check_choice(measure, "measure", ORC_MEASURES)
    check_choice(cost, "cost", ORC_COSTS)
    check_choice(solver, "solver", ORC_SOLVERS)
    check_positive(kernel_scale, "kernel_scale")
    if kernel_scale is not None and measure != "kernel":
        raise ValueError(
            f"`kernel_scale` is the width of measure='kernel'; measure={measure!r} does not use it. "
            "Leave it None, or use measure='kernel'."
        )
    if batch_size is not None:
        check_integer(batch_size, "batch_size", low=1)
    check_metric(tess, metric, mode)
    graph = undirected_graph(tess, capacity)
    ids, dist, used = _two_hop_of(graph, metric, mode, cost)
    if not isinstance(ids, jax.core.Tracer):
        ids, dist = _first_columns(ids, dist, bucket_neighbors(int(used)))
    groups = edge_groups(graph.neighbors)
    return _ollivier_ricci(
        graph, ids, dist, groups, alpha, metric, mode, measure, cost, kernel_scale, batch_size or default_edge_batch()
    )


@eqx.filter_jit
def _two_hop_of(graph: Tessellation, metric, mode: str, cost: str):
    """`two_hop_tables` of the ground cost's edge weights, and the widest row's used columns."""
    ids, dist = two_hop_tables(graph, _edge_weights(graph, metric, mode, cost))
    return ids, dist, jnp.max(jnp.sum(ids < graph.n_points, axis=1))


@functools.partial(jax.jit, static_argnums=2)
def _first_columns(ids, dist, width: int):
    return ids[:, :width], dist[:, :width]


def undirected_graph(tess: Tessellation, capacity: int | None = None) -> Tessellation:
    """The graph with every edge in both rows: Delaunay graphs as they are, k-NN graphs the union
    of both directions (rows ascending). Overflow of `capacity` sets `overflow`."""
    if tess.simplices is not None:
        return tess
    n, k = tess.neighbors.shape
    if capacity is None:
        traced = isinstance(tess.neighbors, jax.core.Tracer)
        if traced:
            capacity = 2 * k
        else:  # concrete rows inside an outer jit too (ops there are staged unless told otherwise)
            with jax.ensure_compile_time_eval():
                capacity = bucket_neighbors(int(jnp.max(_undirected_degree(tess.neighbors))))
    check_integer(capacity, "capacity", low=1)
    rows, shifts, overflow = _symmetrize(tess.neighbors, tess.neighbor_shifts, capacity)
    return Tessellation(
        tess.points, rows, tess.tier, tess.hull, None, shifts, None, tess.box, tess.overflow | overflow, tess.periodic
    )


def _sorted_pairs(neighbors, shifts):
    """Both directions of every edge, sorted by (row, column); duplicates marked."""
    n, k = neighbors.shape
    i = jnp.repeat(jnp.arange(n, dtype=neighbors.dtype), k)
    j = neighbors.reshape(-1)
    real = j < n
    src = jnp.concatenate([jnp.where(real, i, n), jnp.where(real, j, n)])
    dst = jnp.concatenate([jnp.where(real, j, n), jnp.where(real, i, n)])
    extra = [] if shifts is None else [jnp.concatenate([s, -s]) for s in shifts.reshape(n * k, -1).T]
    out = jax.lax.sort([src, dst, *extra], num_keys=2)
    src, dst = out[0], out[1]
    new = jnp.concatenate([jnp.ones((1,), bool), (src[1:] != src[:-1]) | (dst[1:] != dst[:-1])])
    return src, dst, new & (src < n), out[2:]


@jax.jit
def _undirected_degree(neighbors):
    src, _, keep, _ = _sorted_pairs(neighbors, None)
    return jax.ops.segment_sum(keep.astype(jnp.int32), src, neighbors.shape[0] + 1)[:-1]


@eqx.filter_jit
def _symmetrize(neighbors, shifts, capacity: int):
    n = neighbors.shape[0]
    src, dst, keep, extra = _sorted_pairs(neighbors, shifts)
    kept = jnp.cumsum(keep)
    start = jnp.searchsorted(src, jnp.arange(n, dtype=src.dtype), side="left")
    before = jnp.where(start > 0, kept[jnp.maximum(start - 1, 0)], 0)
    rank = kept - 1 - before[jnp.minimum(src, n - 1)]
    row = jnp.where(keep, src, n)
    rows = jnp.full((n, capacity), n, neighbors.dtype).at[row, rank].set(dst, mode="drop")
    degree = jax.ops.segment_sum(keep.astype(jnp.int32), src, n + 1)[:-1]
    out_shifts = None
    if shifts is not None:
        table = jnp.stack(extra, axis=-1).astype(shifts.dtype)
        out_shifts = jnp.zeros((n, capacity, shifts.shape[-1]), shifts.dtype).at[row, rank].set(table, mode="drop")
    return rows, out_shifts, jnp.any(degree > capacity)


def _edge_weights(graph: Tessellation, metric, mode: str, cost: str):
    """Edge lengths of the ground cost: metric lengths, or 1 for hop counts (0 on padding)."""
    if cost == "hops":
        return graph.neighbor_mask.astype(graph.points.dtype)
    return safe_sqrt(edge_sq_lengths(graph, metric, mode=mode))


@jax.jit
def two_hop_tables(graph: Tessellation, weights):
    """Every walker's shortest paths of at most two edges: (N, T) target ids, ascending, padded
    with N, and (N, T) their lengths (inf on padding); T = (K + 1)^2 before trimming."""
    n, k = graph.neighbors.shape
    ids1 = jnp.concatenate([jnp.arange(n, dtype=graph.neighbors.dtype)[:, None], graph.neighbors], axis=1)
    w1 = jnp.concatenate([jnp.zeros((n, 1), weights.dtype), jnp.where(graph.neighbor_mask, weights, 0.0)], axis=1)
    ids1_pad = jnp.concatenate([ids1, jnp.full((1, k + 1), n, ids1.dtype)])
    ids2 = jnp.where(ids1[:, :, None] < n, ids1_pad[ids1], n).reshape(n, -1)
    d2 = jnp.where(ids2 < n, (w1[:, :, None] + take_or_zero(w1, ids1)).reshape(n, -1), jnp.inf)
    ids2, d2 = jax.lax.sort((ids2, d2), dimension=1, num_keys=2)
    first = jnp.concatenate([jnp.ones((n, 1), bool), ids2[:, 1:] != ids2[:, :-1]], axis=1)
    ids2, d2 = jnp.where(first, ids2, n), jnp.where(first, d2, jnp.inf)
    return jax.lax.sort((ids2, d2), dimension=1, num_keys=1)


@eqx.filter_jit
def _ollivier_ricci(
    graph: Tessellation, ids2, dist2, groups, alpha, metric, mode, measure, cost, kernel_scale, batch_size: int
):
    metric = check_metric(graph, metric, mode)
    lengths = safe_sqrt(edge_sq_lengths(graph, metric, mode=mode))
    weights = _edge_weights(graph, metric, mode, cost)
    masses, moment = _walker_measures(graph, lengths, weights, alpha, measure, kernel_scale)
    ctx = _edge_context(graph, ids2, dist2, weights, masses, metric, mode, cost)
    solved = [
        jax.lax.map(lambda e, w=width: _edge_curvature(ctx, e[0], e[1], w), (ends, slots), batch_size=batch_size)
        for ends, slots, width in groups
    ]
    ends, slots = (jnp.concatenate([g[i] for g in groups]) for i in (0, 1))
    kappa, converged = (jnp.concatenate([r[i] for r in solved]) for i in (0, 1))
    edge_kappa = _edge_values_to_slots(graph.neighbors, ends, slots, kappa, jnp.nan)
    edge_ok = _edge_values_to_slots(graph.neighbors, ends, slots, converged, True)
    return _summaries(graph, edge_kappa, edge_ok, moment, alpha, cost)


class _EdgeContext(eqx.Module):
    closed_ids: Array  # (N + 1, K + 1) walker itself, then its neighbours
    closed_weights: Array
    two_hop_ids: Array  # (N + 1, T)
    two_hop_dist: Array
    masses: Array  # (N + 1, K + 1) m_x on the closed row
    displacements: Array | None  # (N + 1, K + 1, d) x_j - x_i on the closed row (cost="direct")
    graph: Tessellation
    metric: object
    mode: str = eqx.field(static=True)
    cost: str = eqx.field(static=True)


def _edge_context(graph: Tessellation, ids2, dist2, weights, masses, metric, mode: str, cost: str) -> _EdgeContext:
    """The per-walker tables every edge reads, each padded with a row for the sentinel N."""
    n = graph.n_points
    return _EdgeContext(
        _pad_rows(_closed_rows(graph.neighbors), n),
        _pad_rows(_closed_rows(weights, 0.0), 0.0),
        _pad_rows(ids2, n),
        _pad_rows(dist2, jnp.inf),
        _pad_rows(masses, 0.0),
        _displacement_table(graph) if cost == "direct" else None,
        graph,
        metric,
        mode,
        cost,
    )


def _closed_rows(values, self_value=None):
    """(N, K) -> (N, K + 1): each row prefixed with the walker itself (or `self_value`)."""
    n = values.shape[0]
    first = jnp.arange(n, dtype=values.dtype) if self_value is None else jnp.full((n,), self_value, values.dtype)
    return jnp.concatenate([first[:, None], values], axis=1)


def _pad_rows(table, fill):
    return jnp.concatenate([table, jnp.full((1,) + table.shape[1:], fill, table.dtype)])


def _walker_measures(graph: Tessellation, lengths, weights, alpha, measure: str, kernel_scale):
    """m_x on the closed row (alpha on x, 1 - alpha over the neighbours) and its second moment."""
    mask = graph.neighbor_mask
    degree = jnp.sum(mask, axis=1, keepdims=True).astype(lengths.dtype)
    if measure == "uniform":
        logits = jnp.zeros_like(lengths)
    elif measure == "grc":
        logits = -(weights**2)
    else:
        scale = (
            jnp.sum(lengths, axis=1, keepdims=True) / jnp.maximum(degree, 1) if kernel_scale is None else kernel_scale
        )
        logits = -(lengths**2) / (2.0 * jnp.where(scale > 0, scale, 1.0) ** 2)
    logits = jnp.where(mask, logits, -jnp.inf)
    top = jnp.max(logits, axis=1, keepdims=True)
    p = jnp.where(mask, jnp.exp(logits - jnp.where(degree > 0, top, 0.0)), 0.0)
    p = p / jnp.where(degree > 0, jnp.sum(p, axis=1, keepdims=True), 1.0)
    moment = jnp.where(degree[:, 0] > 0, jnp.sum(p * lengths**2, axis=1), jnp.nan)
    stay = jnp.where(degree > 0, alpha, 1.0).astype(lengths.dtype)
    return jnp.concatenate([stay, (1.0 - alpha) * p], axis=1), moment


def _displacement_table(graph: Tessellation):
    disp = neighbor_displacements(graph)
    closed = jnp.concatenate([jnp.zeros_like(disp[:, :1]), disp], axis=1)
    return _pad_rows(closed, 0.0)


def edge_groups(neighbors) -> tuple:
    """Each undirected edge once, as (row i, slot k) with neighbors[i, k] > i, in groups
    `(ends, slots, width)` whose closed rows fit `width` columns (a static int): an edge's
    transport problem is width x width, so a K = 24 graph of mean degree 11 solves most of its
    edges at width 16, not 25. Each group is padded with row N to a ladder size (few shapes,
    few compilations). Under a trace: one group of width K + 1 and capacity N K / 2, which
    always suffices (each edge fills two of the N K slots)."""
    n, k = neighbors.shape
    if isinstance(neighbors, jax.core.Tracer):
        upper = (neighbors < n) & (neighbors > jnp.arange(n, dtype=neighbors.dtype)[:, None])
        (flat,) = jnp.nonzero(upper.reshape(-1), size=max(n * k // 2, 1), fill_value=n * k)
        return (((flat // k).astype(neighbors.dtype), (flat % k).astype(neighbors.dtype), k + 1),)
    return _host_edge_groups(np.asarray(neighbors), neighbors.dtype)


def _host_edge_groups(nbrs: np.ndarray, dtype) -> tuple:
    n, k = nbrs.shape
    degree = np.r_[np.sum(nbrs < n, axis=1), 0]
    ends, slots = np.nonzero((nbrs < n) & (nbrs > np.arange(n)[:, None]))
    closed = np.maximum(degree[ends], degree[nbrs[ends, slots]]) + 1
    widths = np.minimum(WIDTH_STEP * -(-closed // WIDTH_STEP), k + 1)
    groups = []
    for width in np.unique(widths):
        pick = np.flatnonzero(widths == width)
        pad = bucket_simplices(len(pick)) - len(pick)
        groups.append(
            (
                jnp.asarray(np.r_[ends[pick], np.full(pad, n)], dtype),
                jnp.asarray(np.r_[slots[pick], np.zeros(pad, int)], dtype),
                int(width),
            )
        )
    return tuple(groups) or ((jnp.full((1,), n, dtype), jnp.zeros((1,), dtype), k + 1),)


def _edge_values_to_slots(neighbors, ends, slots, values, fill):
    """Per-edge values -> (N, K) aligned with `neighbors`, both directions; `fill` on padding."""
    n, k = neighbors.shape
    edge_id = (
        jnp.full((n, k), -1, jnp.int32).at[ends, slots].set(jnp.arange(ends.shape[0], dtype=jnp.int32), mode="drop")
    )
    j = jnp.minimum(neighbors, n - 1)
    query = jnp.broadcast_to(jnp.arange(n, dtype=neighbors.dtype)[:, None], (n, k))
    back = jax.vmap(jax.vmap(jnp.searchsorted))(neighbors[j], query)  # slot of i in row j (rows ascend)
    reverse = edge_id[j, jnp.minimum(back, k - 1)]
    ids = jnp.where(neighbors > jnp.arange(n, dtype=neighbors.dtype)[:, None], edge_id, reverse)
    out = values[jnp.maximum(ids, 0)]
    return jnp.where((neighbors < n) & (ids >= 0), out, fill)


def _edge_curvature(ctx: _EdgeContext, x, slot, width: int):
    """kappa of edge (x, neighbors[x, slot]) and whether its transport converged."""
    cost, a, b, same = _edge_problem(ctx, x, slot, width)
    w1, converged = transport_cost(cost, a, b, same)
    distance = cost[0, 0]
    ok = distance > 0
    return jnp.where(ok, 1.0 - w1 / jnp.where(ok, distance, 1.0), jnp.nan), converged


def _edge_problem(ctx: _EdgeContext, x, slot, width: int):
    """The transport problem of edge (x, neighbors[x, slot]): (width, width) ground costs from
    x's closed row to y's (0 on padding), the two measures, and where both hold the same
    walker. Both closed rows fit in their first `width` columns."""
    n = ctx.graph.n_points
    y = ctx.closed_ids[x, slot + 1]
    support_x, support_y = ctx.closed_ids[x, :width], ctx.closed_ids[y, :width]
    real = (support_x[:, None] < n) & (support_y[None, :] < n)
    cost = jnp.where(real, _ground_cost(ctx, x, y, slot, support_x, support_y), 0.0)
    same = real & (support_x[:, None] == support_y[None, :])
    return cost, ctx.masses[x, :width], ctx.masses[y, :width], same


def _ground_cost(ctx: _EdgeContext, x, y, slot, support_x, support_y):
    if ctx.cost == "direct":
        return _direct_cost(ctx, x, y, slot, support_x, support_y)
    m = support_y.shape[0]
    if ctx.cost == "hops":  # d <= 3 through the edge, so the two-hop table decides exactly
        found, dist = _two_hop_lookup(
            ctx, jnp.broadcast_to(support_x[:, None], (m, m)), jnp.broadcast_to(support_y[None, :], (m, m))
        )
        return jnp.where(found, dist, float(HOP_RADIUS))
    via = ctx.closed_ids[support_y]  # (M, K + 1): every b next to (or equal to) some v, whole rows
    _, dist = _two_hop_lookup(ctx, jnp.broadcast_to(support_x[:, None, None], (m,) + via.shape), via[None])
    paths = dist + ctx.closed_weights[support_y][None]  # [u, v, b]: D2(u, b) + l(b, v)
    return jnp.min(paths, axis=2)


def _two_hop_lookup(ctx: _EdgeContext, sources, targets):
    """Elementwise over the broadcast (sources, targets): whether target is within two edges of
    source, and the length of the shortest such path (inf where not). A binary search by
    lifting that gathers one table entry per query and step (gathering whole (T,) rows per
    query cost 5x more)."""
    ids, t = ctx.two_hop_ids, ctx.two_hop_ids.shape[1]
    sources, targets = jnp.broadcast_arrays(sources, targets)
    below = jnp.zeros(targets.shape, jnp.int32)  # how many of the source's ids are < target
    step = 1 << (t.bit_length() - 1)
    while step:
        probe = below + step
        inside = probe <= t
        value = ids[sources, jnp.minimum(probe, t) - 1]
        below = jnp.where(inside & (value < targets), probe, below)
        step >>= 1
    pos = jnp.minimum(below, t - 1)
    found = (ids[sources, pos] == targets) & (targets < ctx.graph.n_points)
    return found, jnp.where(found, ctx.two_hop_dist[sources, pos], jnp.inf)


def _direct_cost(ctx: _EdgeContext, x, y, slot, support_x, support_y):
    """Metric length of the segment u -> v, positions relative to x (periodic images applied)."""
    m = support_x.shape[0]
    to_u = ctx.displacements[x, :m]  # (M, d)
    to_v = ctx.displacements[x, slot + 1] + ctx.displacements[y, :m]
    dx = to_v[None, :, :] - to_u[:, None, :]  # (M, M, d)
    metric, graph = ctx.metric, ctx.graph
    if metric is None:
        sq = jnp.sum(dx * dx, axis=-1)
    elif callable(metric):
        mid = graph.points[jnp.minimum(x, graph.n_points - 1)] + 0.5 * (to_u[:, None, :] + to_v[None, :, :])
        sq = _quad(_with_mode(_call_metric(metric, _wrap(graph, mid)), ctx.mode), dx)
    else:
        g = _pad_rows(_with_mode(metric, ctx.mode), 0.0)
        sq = 0.5 * (_quad(g[support_x][:, None], dx) + _quad(g[support_y][None, :], dx))
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def _summaries(graph: Tessellation, edge_kappa, edge_ok, moment, alpha, cost: str) -> OllivierRicci:
    mask = graph.neighbor_mask
    degree = jnp.sum(mask, axis=1).astype(edge_kappa.dtype)
    isolated = degree == 0
    kappa0 = jnp.where(mask, edge_kappa, 0.0)
    walker = jnp.where(isolated, jnp.nan, jnp.sum(kappa0, axis=1) / jnp.maximum(degree, 1))
    moment_pad = _pad_rows(moment, jnp.nan)
    pair_moment = 0.5 * (moment[:, None] + moment_pad[graph.neighbors])
    dim = graph.dim
    scale = 2.0 * dim**2 / ((1.0 - alpha) * pair_moment) if cost != "hops" else jnp.nan
    per_edge = jnp.where(mask, kappa0 * scale, 0.0)
    scalar = jnp.where(isolated | (alpha >= 1.0), jnp.nan, jnp.sum(per_edge, axis=1) / jnp.maximum(degree, 1))
    return OllivierRicci(
        graph.neighbors,
        edge_kappa,
        walker,
        scalar,
        moment,
        isolated,
        graph.interior,
        jnp.any(mask & ~edge_ok, axis=1),
        jnp.asarray(graph.overflow),
    )
