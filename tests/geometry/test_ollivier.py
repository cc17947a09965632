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
    res = scipy.optimize.linprog(cost.ravel(), A_eq=scipy.sparse.vstack([rows, cols]), b_eq=np.concatenate([a, b]),
                                 bounds=(0, None), method="highs")
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
    ref = [_linprog_w1(c, p, q) for c, p, q in zip(cost, a, b)]
    np.testing.assert_allclose(w1, ref, rtol=1e-7, atol=1e-9)  # HiGHS stops at ~1e-9


def test_transport_gradient_is_the_plan_and_the_duals(rng):
    m = 6
    cost, a, b = rng.random((m, m)), rng.random(m), rng.random(m)
    a, b = a / a.sum(), b / b.sum()
    same = jnp.zeros((m, m), bool)
    grad_c = jax.grad(lambda c: transport_cost(c, a, b, same)[0])(jnp.asarray(cost))
    step = 1e-6
    for i, j in [(0, 0), (1, 3), (4, 2)]:
        e = np.zeros((m, m))
        e[i, j] = step
        fd = (_linprog_w1(cost + e, a, b) - _linprog_w1(cost - e, a, b)) / (2 * step)
        np.testing.assert_allclose(grad_c[i, j], fd, atol=1e-6)
    direction = rng.standard_normal(m)
    direction -= direction.mean()  # keeps the total mass
    grad_a = jax.grad(lambda p: transport_cost(cost, p, b, same)[0])(jnp.asarray(a))
    fd = (_linprog_w1(cost, a + step * direction, b) - _linprog_w1(cost, a - step * direction, b)) / (2 * step)
    np.testing.assert_allclose(grad_a @ direction, fd, rtol=1e-5, atol=1e-8)


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
            p = np.exp(-weights[i, nb] ** 2)
        else:
            h = w[i, nb].mean() if kernel_scale is None else kernel_scale
            p = np.exp(-w[i, nb] ** 2 / (2 * h**2))
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


@pytest.mark.parametrize("cost,measure", [("hops", "uniform"), ("graph", "uniform"), ("graph", "grc"),
                                          ("direct", "kernel"), ("graph", "kernel")])
def test_knn_graph_matches_the_definition(rng, cost, measure):
    tess = jaxgeom.knn_graph(rng.random((70, 2)), 5)
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.3, cost=cost, measure=measure)
    assert _assert_matches(orc, _reference_curvature(tess, 0.3, measure, cost), 1e-7) > 200
    assert not np.any(orc.not_converged) and not orc.overflow


def test_delaunay_graph_and_kernel_scale_match_the_definition(rng):
    tess = jaxgeom.delaunay(rng.random((45, 3)))
    orc = jaxgeom.ollivier_ricci(tess, alpha=0.0, measure="kernel", kernel_scale=0.2)
    _assert_matches(orc, _reference_curvature(tess, 0.0, "kernel", "graph", kernel_scale=0.2), 1e-7)
