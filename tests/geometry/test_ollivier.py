"""Ollivier-Ricci curvature: exact transport against linear programming, the whole kernel
against a dense numpy/scipy reference of the definition and against GraphRicciCurvature."""

import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.sparse
import scipy.sparse.csgraph

import jaxgeom
from jaxgeom.geometry._transport import transport_cost

HAS_GRC = importlib.util.find_spec("GraphRicciCurvature") is not None


def _linprog_w1(cost, a, b):
    m, n = cost.shape
    rows = scipy.sparse.kron(scipy.sparse.eye(m), np.ones((1, n)))
    cols = scipy.sparse.kron(np.ones((1, m)), scipy.sparse.eye(n))
    res = scipy.optimize.linprog(
        cost.ravel(),
        A_eq=scipy.sparse.vstack([rows, cols]),
        b_eq=np.concatenate([a, b]),
        bounds=(0, None),
        method="highs",
    )
    assert res.status == 0
    return res.fun


def test_transport_matches_linear_programming(rng):
    solve = jax.jit(jax.vmap(transport_cost))
    m = 9
    cost = rng.random((40, m, m)) * 3.0
    cost[:10] = np.round(cost[:10])  # integer costs: many ties (degenerate problems)
    a = rng.random((40, m)) * (rng.random((40, m)) > 0.3)
    b = rng.random((40, m)) * (rng.random((40, m)) > 0.3)
    a[:, 0] += 0.1
    b[:, 0] += 0.1
    a, b = a / a.sum(1, keepdims=True), b / b.sum(1, keepdims=True)
    same = np.zeros((40, m, m), bool)
    same[:20, np.arange(3), np.arange(3)] = True  # three shared points, cost 0
    cost[same] = 0.0
    w1, ok = solve(jnp.asarray(cost), jnp.asarray(a), jnp.asarray(b), jnp.asarray(same))
    assert np.all(ok)
    ref = [_linprog_w1(c, p, q) for c, p, q in zip(cost, a, b, strict=True)]
    np.testing.assert_allclose(w1, ref, rtol=1e-7, atol=1e-9)  # HiGHS stops at ~1e-9


def test_transport_gradient_is_the_plan_and_the_duals(rng):
    m = 6
    cost, a, b = rng.random((m, m)), rng.random(m), rng.random(m)
    a, b = a / a.sum(), b / b.sum()
    same = jnp.zeros((m, m), bool)
    ja, jb = jnp.asarray(a), jnp.asarray(b)
    grad_c = jax.grad(lambda c: transport_cost(c, ja, jb, same)[0])(jnp.asarray(cost))
    step = 1e-6
    for i, j in [(0, 0), (1, 3), (4, 2)]:
        e = np.zeros((m, m))
        e[i, j] = step
        fd = (_linprog_w1(cost + e, a, b) - _linprog_w1(cost - e, a, b)) / (2 * step)
        np.testing.assert_allclose(grad_c[i, j], fd, atol=1e-6)
    direction = rng.standard_normal(m)
    direction -= direction.mean()  # keeps the total mass
    grad_a = jax.grad(lambda p: transport_cost(jnp.asarray(cost), p, jb, same)[0])(ja)
    fd = (_linprog_w1(cost, a + step * direction, b) - _linprog_w1(cost, a - step * direction, b)) / (2 * step)
    np.testing.assert_allclose(grad_a @ direction, fd, rtol=1e-5, atol=1e-8)


def test_transport_cancels_a_residual_cycle_that_float32_rounding_made_negative():
    """An edge of a float32 GRC-weighted 1e4-point k-NN graph: after flows of ~1e-6 the residual
    graph held a cycle negative beyond the tie slack, the predecessors formed it, and every
    later augmentation carried nothing (4 M of them: kappa 0.55 instead of -0.05, flagged)."""
    from jaxgeom.geometry import _ollivier as orc

    x = np.random.default_rng(0).random((10000, 2)).astype(np.float32)
    graph = orc.undirected_graph(jaxgeom.knn_graph(x, 10))
    w = orc._edge_weights(graph, None, "full", "graph")
    ids, dist = orc.two_hop_tables(graph, w)
    masses, _ = orc._walker_measures(graph, w, w, 0.5, "grc", None)
    ctx = orc._edge_context(graph, ids, dist, w, masses, None, "full", "graph")
    cost, a, b, same = orc._edge_problem(ctx, jnp.asarray(7149), jnp.asarray(8), graph.neighbors.shape[1] + 1)
    w1, converged = transport_cost(cost, a, b, same)
    assert cost.dtype == jnp.float32 and bool(converged)
    a64, b64 = np.asarray(a, np.float64), np.asarray(b, np.float64)
    np.testing.assert_allclose(
        w1, _linprog_w1(np.asarray(cost, np.float64), a64, b64 * a64.sum() / b64.sum()), rtol=1e-5
    )


def _undirected_lengths(tess, hops=False):
    """Dense (N, N) edge lengths of the undirected graph (inf off the graph, 0 on the diagonal)."""
    x, nbrs = np.asarray(tess.points), np.asarray(tess.neighbors)
    n = len(x)
    w = np.full((n, n), np.inf)
    for i, row in enumerate(nbrs):
        for j in row[row < n]:
            w[i, j] = w[j, i] = 1.0 if hops else np.linalg.norm(x[i] - x[j])
    np.fill_diagonal(w, 0.0)
    return w


def _min_plus(a, b):
    return np.min(a[:, :, None] + b[None, :, :], axis=1)


def _reference_curvature(tess, alpha, measure, cost, kernel_scale=None):
    """kappa of every undirected edge {i: {j: kappa}} from the definition, dense numpy + linprog."""
    x = np.asarray(tess.points)
    w = _undirected_lengths(tess)
    weights = _undirected_lengths(tess, hops=True) if cost == "hops" else w
    hop_limited = _min_plus(_min_plus(weights, weights), weights)  # paths of <= 3 edges
    ground = np.linalg.norm(x[:, None] - x[None], axis=-1) if cost == "direct" else hop_limited

    def measure_of(i):
        nb = np.flatnonzero(np.isfinite(w[i]) & (np.arange(len(x)) != i))
        if measure == "uniform":
            p = np.ones(len(nb))
        elif measure == "grc":
            p = np.exp(-(weights[i, nb] ** 2))
        else:
            h = w[i, nb].mean() if kernel_scale is None else kernel_scale
            p = np.exp(-(w[i, nb] ** 2) / (2 * h**2))
        return np.concatenate([[i], nb]), np.concatenate([[alpha], (1 - alpha) * p / p.sum()])

    out = {}
    for i in range(len(x)):
        si, a = measure_of(i)
        for j in si[1:]:
            sj, b = measure_of(j)
            out.setdefault(i, {})[j] = 1 - _linprog_w1(ground[np.ix_(si, sj)], a, b) / ground[i, j]
    return out


def _assert_matches(orc, ref, atol):
    nbrs, kappa = np.asarray(orc.neighbors), np.asarray(orc.edge_curvature)
    n = len(nbrs)
    count = 0
    for i, row in enumerate(nbrs):
        assert sorted(ref[i]) == sorted(row[row < n].tolist())
        for slot, j in enumerate(row[row < n]):
            assert abs(kappa[i, slot] - ref[i][j]) <= atol, (i, j, kappa[i, slot], ref[i][j])
            count += 1
    assert np.all(np.isnan(kappa[nbrs == n]))
    return count


@pytest.mark.parametrize(
    "cost,measure",
    [("hops", "uniform"), ("graph", "uniform"), ("graph", "grc"), ("direct", "kernel"), ("graph", "kernel")],
)
def test_knn_graph_matches_the_definition(rng, cost, measure):
    tess = jaxgeom.knn_graph(rng.random((70, 2)), 5)
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.3, cost=cost, measure=measure)
    assert _assert_matches(orc, _reference_curvature(tess, 0.3, measure, cost), 1e-7) > 200
    assert not np.any(orc.not_converged) and not orc.overflow


def test_delaunay_graph_and_kernel_scale_match_the_definition(rng):
    tess = jaxgeom.delaunay(rng.random((45, 3)))
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.0, measure="kernel", kernel_scale=0.2)
    _assert_matches(orc, _reference_curvature(tess, 0.0, "kernel", "graph", kernel_scale=0.2), 1e-7)


def _grc_curvature(tess, weighted):
    import networkx as nx
    from GraphRicciCurvature.OllivierRicci import OllivierRicci

    x, nbrs = np.asarray(tess.points), np.asarray(tess.neighbors)
    graph = nx.Graph()
    graph.add_nodes_from(range(len(x)))
    for i, row in enumerate(nbrs):
        for j in row[row < len(x)]:
            graph.add_edge(i, int(j), **({"weight": float(np.linalg.norm(x[i] - x[j]))} if weighted else {}))
    orc = OllivierRicci(graph, alpha=0.5, method="OTD", proc=1, verbose="ERROR")
    orc.compute_ricci_curvature()
    return orc.G


def _two_clusters(rng, n, d):
    x = rng.standard_normal((n, d)) * 0.1
    x[: n // 2, 0] += 5.0  # far apart: the k-NN graph has two components
    return x


@pytest.mark.skipif(not HAS_GRC, reason="GraphRicciCurvature is not installed (test-only reference)")
@pytest.mark.parametrize("n,d,clusters", [(2000, 2, True), (1000, 3, False), (500, 5, True)])
def test_matches_graph_ricci_curvature_exact_transport(rng, n, d, clusters):
    x = _two_clusters(rng, n, d) if clusters else rng.random((n, d))
    tess = jaxgeom.knn_graph(x, 6)
    if clusters:
        adjacency = scipy.sparse.csr_matrix(
            (np.ones(n * 6), (np.repeat(np.arange(n), 6), np.asarray(tess.neighbors).ravel()))
        )
        assert scipy.sparse.csgraph.connected_components(adjacency, directed=False)[0] == 2
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.5, cost="hops")  # GRC's default: unweighted, uniform
    reference = _grc_curvature(tess, weighted=False)
    ref = {i: {j: reference[i][j]["ricciCurvature"] for j in reference[i]} for i in reference}
    assert _assert_matches(orc, ref, 1e-6) == 2 * reference.number_of_edges()


@pytest.mark.skipif(not HAS_GRC, reason="GraphRicciCurvature is not installed (test-only reference)")
def test_matches_graph_ricci_curvature_on_a_weighted_graph(rng):
    """GRC weights by e^{-w^2} and costs by full shortest paths; ours limits paths to 3 edges.
    Where every ground distance of the two neighbourhoods has a shortest path of <= 3 edges the
    two agree to 1e-6; elsewhere the definition test covers ours."""
    tess = jaxgeom.knn_graph(rng.random((600, 2)), 6)
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.5, measure="grc", cost="graph")
    reference = _grc_curvature(tess, weighted=True)
    w = _undirected_lengths(tess)
    exact = scipy.sparse.csgraph.shortest_path(np.where(np.isfinite(w), w, 0.0), directed=False)
    limited = _min_plus(_min_plus(w, w), w)
    nbrs, kappa = np.asarray(orc.neighbors), np.asarray(orc.edge_curvature)
    closed = [np.concatenate([[i], row[row < len(w)]]) for i, row in enumerate(nbrs)]
    agree = total = 0
    for i, row in enumerate(nbrs):
        for slot, j in enumerate(row[row < len(w)]):
            total += 1
            if np.allclose(
                exact[np.ix_(closed[i], closed[j])], limited[np.ix_(closed[i], closed[j])], rtol=0, atol=1e-12
            ):
                agree += 1
                assert abs(kappa[i, slot] - reference[i][j]["ricciCurvature"]) <= 1e-6
    assert agree > 0.75 * total  # measured 82% (600 points, k = 6)


def _with_points(tess, points):
    import equinox as eqx

    return eqx.tree_at(lambda t: t.points, tess, points)


@pytest.mark.parametrize("cost,measure", [("direct", "kernel"), ("graph", "grc")])
def test_gradient_wrt_positions_matches_central_differences(rng, cost, measure):
    tess = jaxgeom.knn_graph(rng.random((40, 2)), 5)
    weights = jnp.asarray(rng.random((40, 16)))

    def loss(points):
        orc = jaxgeom.ollivier_ricci(_with_points(tess, points), alpha=0.25, cost=cost, measure=measure, capacity=16)
        return jnp.sum(jnp.where(orc.edge_mask, weights * orc.edge_curvature, 0.0))

    x0 = tess.points
    grad = jax.grad(loss)(x0)
    assert np.all(np.isfinite(grad))
    direction = jnp.asarray(rng.standard_normal(x0.shape))
    step = 1e-6
    fd = (loss(x0 + step * direction) - loss(x0 - step * direction)) / (2 * step)
    np.testing.assert_allclose(jnp.sum(grad * direction), fd, rtol=1e-5)


def test_gradient_wrt_a_metric_parameter_matches_central_differences(rng):
    tess = jaxgeom.knn_graph(rng.random((40, 3)) - 0.5, 6)

    def mean_kappa(s):
        metric = lambda x: (1.0 + s * jnp.sum(x * x)) ** 2 * jnp.eye(3)  # noqa: E731
        return jaxgeom.ollivier_ricci(tess, metric=metric, cost="direct", capacity=16).mean_curvature

    s0, step = 0.7, 1e-6
    fd = (mean_kappa(s0 + step) - mean_kappa(s0 - step)) / (2 * step)
    np.testing.assert_allclose(jax.grad(mean_kappa)(s0), fd, rtol=1e-5)


def test_jit_with_a_traced_graph_equals_the_host_graph(rng):
    x = rng.random((60, 3))

    @jax.jit
    def traced(points):
        return jaxgeom.ollivier_ricci(jaxgeom.knn_graph(points, 5, method="brute"), capacity=16)

    host = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(x, 5), capacity=16)
    inside = traced(x)
    np.testing.assert_array_equal(inside.neighbors, host.neighbors)
    np.testing.assert_allclose(inside.edge_curvature, host.edge_curvature, rtol=1e-12)
    np.testing.assert_allclose(inside.scalar_curvature, host.scalar_curvature, rtol=1e-12)


def test_isolated_walkers_are_flagged_and_left_out_of_the_summaries(rng):
    x = rng.random((30, 2))
    x[7] = np.nan  # under a trace a NaN walker gets no neighbours and is nobody's neighbour

    @jax.jit
    def curvature(points):
        return jaxgeom.ollivier_ricci(jaxgeom.knn_graph(points, 4, method="brute"), capacity=16)

    orc = curvature(x)
    assert np.flatnonzero(orc.isolated).tolist() == [7]
    assert np.isnan(orc.walker_curvature[7]) and np.isnan(orc.scalar_curvature[7])
    assert np.all(np.isfinite(np.delete(np.asarray(orc.walker_curvature), 7)))
    assert np.isfinite(orc.mean_curvature) and np.isfinite(orc.mean_scalar_curvature)


def test_periodic_knn_graph_equals_the_graph_of_explicit_images(rng):
    """A periodic graph in the unit box against the plain graph of the walkers and their eight
    images: kappa of the original walkers agrees. (The periodic graph's shortest paths run on
    the torus, to the nearest image; with 150 walkers three edges span ~0.3 of the box, so
    they are the plain graph's paths.) Images farther than `margin` from the box are left out:
    an original walker's kappa reads the graph five edges deep at most (its support, paths of
    three edges). Here 0.4 is the smallest margin in steps of 0.1 that agrees (0.3 changes kappa,
    0.1 the edges): 0.5 leaves one step to spare."""
    n, margin = 150, 0.5
    x = rng.random((n, 2))
    periodic = jaxgeom.knn_graph(x, 5, box=([0, 0], [1, 1]), periodic=True)
    images = np.concatenate([x + np.array([i, j]) for i in (0, -1, 1) for j in (0, -1, 1)])
    near = np.all((images > -margin) & (images < 1 + margin), axis=1)  # the originals, first, all kept
    images, walker = images[near], np.tile(np.arange(n), 9)[near]
    plain = jaxgeom.knn_graph(images, 5)
    for cost in ("graph", "direct"):
        a = jaxgeom.ollivier_ricci(periodic, cost=cost)
        b = jaxgeom.ollivier_ricci(plain, cost=cost)
        na, nb = np.asarray(a.neighbors)[:n], np.asarray(b.neighbors)[:n]
        ka, kb = np.asarray(a.edge_curvature)[:n], np.asarray(b.edge_curvature)[:n]
        for i in range(n):
            mine = dict(zip(na[i][na[i] < n].tolist(), ka[i][na[i] < n], strict=True))
            kept = nb[i] < len(images)
            theirs = {walker[j]: v for j, v in zip(nb[i][kept].tolist(), kb[i][kept], strict=True)}
            assert mine.keys() == theirs.keys()
            np.testing.assert_allclose([mine[j] for j in mine], [theirs[j] for j in mine], rtol=1e-10)


def test_float32_runs_and_agrees_with_float64(rng):
    x = rng.random((80, 2))
    ref = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(x, 6), cost="direct")
    single = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(x.astype(np.float32), 6), cost="direct")
    assert single.edge_curvature.dtype == jnp.float32
    np.testing.assert_allclose(single.edge_curvature, ref.edge_curvature, atol=2e-5)


def test_float32_nearly_equal_measures_are_transported_not_dropped(rng):
    """GRC's e^{-w^2} on short edges gives shared points masses that differ by ~1e-6: real
    mass in float32. With 64 ulps of tolerance it fell off the residual graph (kappa 8e-4 off,
    650 of 2000 walkers flagged, and a float32 N = 1e4 run did not finish)."""
    x = rng.random((600, 2)).astype(np.float32)
    ref = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(x.astype(np.float64), 8), cost="graph", measure="grc")
    single = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(x, 8), cost="graph", measure="grc")
    assert not np.any(single.not_converged)
    np.testing.assert_allclose(single.edge_curvature, ref.edge_curvature, atol=5e-5)


@pytest.mark.parametrize(
    "kwargs,error,match",
    [
        ({"alpha": 1.5}, ValueError, "alpha"),
        ({"alpha": -0.1}, ValueError, "alpha"),
        ({"measure": "gauss"}, ValueError, "unknown measure 'gauss'; valid values are 'uniform', 'kernel', 'grc'"),
        ({"cost": "geodesic"}, ValueError, "unknown cost"),
        ({"solver": "sinkhorn"}, ValueError, "unknown solver 'sinkhorn'"),
        ({"kernel_scale": 0.0}, ValueError, "kernel_scale"),
        ({"capacity": 0}, ValueError, "capacity"),
        ({"batch_size": 0}, ValueError, "`batch_size` must be an int >= 1"),
        ({"batch_size": 2.5}, TypeError, "batch_size"),
    ],
)
def test_bad_arguments(rng, kwargs, error, match):
    tess = jaxgeom.knn_graph(rng.random((20, 2)), 3)
    with pytest.raises(error, match=match):
        jaxgeom.ollivier_ricci(tess, **kwargs)


def test_batch_size_changes_the_schedule_not_the_curvature(rng):
    """Batches of 1 and 7 edges (remainders in every support-width group) and one batch per
    group (the accelerator default is wider than this graph) give the reference curvature."""
    tess = jaxgeom.knn_graph(rng.random((60, 2)), 5)
    ref = _reference_curvature(tess, 0.5, "uniform", "hops")
    for batch in (1, 7, 32768):
        _assert_matches(jaxgeom.ollivier_ricci(tess, cost="hops", batch_size=batch), ref, 1e-7)


def test_too_small_capacity_is_reported_not_truncated_silently(rng):
    orc = jaxgeom.ollivier_ricci(jaxgeom.knn_graph(rng.random((60, 2)), 6), capacity=6)
    assert bool(orc.overflow)


def test_closed_forms_cycle_and_complete_graph():
    """Hop costs. The cycle C_n (n >= 6, alpha = 0) is flat: kappa = 0. On the complete graph K_n,
    m_x and m_y differ only at x and y, by alpha - (1 - alpha) / (n - 1), moved one hop:
    kappa = 1 - |alpha - (1 - alpha) / (n - 1)| ((n - 2) / (n - 1) at alpha = 0)."""
    angles = 2 * np.pi * np.arange(12) / 12
    cycle = jaxgeom.knn_graph(np.c_[np.cos(angles), np.sin(angles)] * (1 + 1e-3 * np.arange(12))[:, None], 2)
    kappa = jaxgeom.ollivier_ricci(cycle, alpha=0.0, cost="hops")
    np.testing.assert_allclose(kappa.edge_curvature[kappa.edge_mask], 0.0, atol=1e-14)
    n = 7
    complete = jaxgeom.knn_graph(np.random.default_rng(0).random((n, 3)), n - 1)
    for alpha in (0.0, 0.5, 0.9):
        kappa = jaxgeom.ollivier_ricci(complete, alpha=alpha, cost="hops")
        expected = 1 - abs(alpha - (1 - alpha) / (n - 1))
        np.testing.assert_allclose(kappa.edge_curvature[kappa.edge_mask], expected, atol=1e-14)
