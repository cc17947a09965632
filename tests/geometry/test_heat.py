"""The heat method: its operators against independent references, its distances against
closed-form geodesics, its derivatives against central differences, and its solvers."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import sphere

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.geometry import _heat


def disk(rng, n, d=2, radius=0.5):
    x = rng.uniform(-radius, radius, (4 * n, d))
    return x[np.linalg.norm(x, axis=1) < radius][:n]


def median_error(tess, dist, true):
    """Median relative error over tier-2 walkers (the source itself left out)."""
    sel = np.asarray(tess.interior)[None] & (true > 0)
    return float(np.median(np.abs(dist[sel] / true[sel] - 1)))


def straight(x, sources):
    return np.linalg.norm(x[None] - x[sources][:, None], axis=-1)


def to_sphere(x):
    sq = np.sum(x * x, axis=-1, keepdims=True)
    return np.concatenate([2 * x, sq - 1], axis=-1) / (1 + sq)


def dense(op, n):
    """Dense K and M from the per-simplex operators (test reference sizes only)."""
    k = np.zeros((n, n))
    simplices, stiffness = np.asarray(op.simplices), np.asarray(op.stiffness)
    for s, local in zip(simplices, stiffness, strict=True):
        if s[0] < n:
            k[np.ix_(s, s)] += local
    return k, np.asarray(op.mass)


def test_2d_operators_are_the_cotangent_laplacian(rng):
    x = rng.random((60, 2))
    tess = jaxgeom.delaunay(x)
    k, mass = dense(_heat.heat_operators(tess), 60)
    ref = np.zeros((60, 60))
    area = np.zeros(60)
    for tri in np.asarray(tess.simplices):
        if tri[0] >= 60:
            continue
        for a in range(3):  # the angle at vertex a weighs the opposite edge (b, c) by cot / 2
            b, c = tri[(a + 1) % 3], tri[(a + 2) % 3]
            u, v = x[b] - x[tri[a]], x[c] - x[tri[a]]
            cot = np.dot(u, v) / abs(u[0] * v[1] - u[1] * v[0])
            ref[b, c] -= cot / 2
            ref[c, b] -= cot / 2
        p = x[tri]
        e1, e2 = p[1] - p[0], p[2] - p[0]
        area[tri] += abs(e1[0] * e2[1] - e1[1] * e2[0]) / 6
    np.fill_diagonal(ref, -ref.sum(axis=1))
    np.testing.assert_allclose(k, ref, atol=1e-12)
    np.testing.assert_allclose(mass, area, rtol=1e-12)


def test_3d_stiffness_is_the_p1_finite_element_matrix(rng):
    x = rng.random((40, 3))
    tess = jaxgeom.delaunay(x)
    k, mass = dense(_heat.heat_operators(tess), 40)
    ref, vol = np.zeros((40, 40)), np.zeros(40)
    for tet in np.asarray(tess.simplices):
        if tet[0] >= 40:
            continue
        # barycentric gradients: rows of inverse([x_v, 1]) without the constant column
        affine = np.hstack([x[tet], np.ones((4, 1))])
        grads = np.linalg.inv(affine)[:3].T
        volume = abs(np.linalg.det(affine)) / 6
        ref[np.ix_(tet, tet)] += volume * grads @ grads.T
        vol[tet] += volume / 4
    np.testing.assert_allclose(k, ref, atol=1e-11)
    np.testing.assert_allclose(mass, vol, rtol=1e-12)


def test_constant_metric_equals_euclidean_operators_of_mapped_points(rng):
    """g = A^T A is the Euclidean metric of the points x A^T: same intrinsic simplices."""
    x = rng.random((80, 2))
    a = np.array([[1.3, 0.4], [0.0, 0.7]])
    tess = jaxgeom.delaunay(x)
    g = np.broadcast_to(a.T @ a, (80, 2, 2))
    mapped = jaxgeom.Tessellation(
        jnp.asarray(x @ a.T), tess.neighbors, tess.tier, tess.hull, tess.simplices, None, None, None, tess.overflow
    )
    ours, ref = _heat.heat_operators(tess, g), _heat.heat_operators(mapped)
    np.testing.assert_allclose(ours.stiffness, ref.stiffness, atol=1e-11)
    np.testing.assert_allclose(ours.mass, ref.mass, rtol=1e-12)
    np.testing.assert_allclose(ours.t, ref.t, rtol=1e-12)


def test_flat_2d_heat_distances_beat_the_graph_distance_and_converge(rng):
    errors, graph = [], []
    for n in (1000, 10000):
        x = disk(rng, n)
        tess = jaxgeom.delaunay(x)
        sources = np.flatnonzero(np.linalg.norm(x, axis=1) < 0.2)[:3]
        true = straight(x, sources)
        errors.append(median_error(tess, np.asarray(jaxgeom.geodesic_distances(tess, sources)), true))
        dijkstra = np.asarray(jaxgeom.geodesic_distances(tess, sources, method="dijkstra"))
        graph.append(median_error(tess, dijkstra, true))
    assert errors[1] < 0.5 * errors[0] and errors[1] < 0.006, errors
    assert min(graph) > 0.03 and errors[1] < 0.2 * min(graph), (errors, graph)


def test_sphere_distances_are_great_circle_arcs(rng):
    x = disk(rng, 6000)
    tess = jaxgeom.delaunay(x)
    sources = np.flatnonzero(np.linalg.norm(x, axis=1) < 0.2)[:3]
    s = to_sphere(x)
    true = np.arccos(np.clip(s[sources] @ s.T, -1.0, 1.0))
    dist = np.asarray(jaxgeom.geodesic_distances(tess, sources, sphere))
    assert median_error(tess, dist, true) < 0.01
    flat = np.asarray(jaxgeom.geodesic_distances(tess, sources))  # the metric matters: 2x longer at the centre
    assert median_error(tess, flat, true) > 0.3


def test_flat_3d_heat_distances(rng):
    x = disk(rng, 6000, d=3)
    tess = jaxgeom.delaunay(x)
    sources = np.flatnonzero(np.linalg.norm(x, axis=1) < 0.15)[:2]
    dist = np.asarray(jaxgeom.geodesic_distances(tess, sources))
    assert median_error(tess, dist, straight(x, sources)) < 0.03


def test_periodic_distances_are_minimum_image_distances(rng):
    x = rng.random((3000, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    sources = [0, 1]
    dx = x[None] - x[sources][:, None]
    dx -= np.round(dx)
    true = np.linalg.norm(dx, axis=-1)
    dist = np.asarray(jaxgeom.geodesic_distances(tess, sources))
    assert median_error(tess, dist, true) < 0.02
    # no boundary: the setting is ignored, every walker is measured
    np.testing.assert_array_equal(dist, np.asarray(jaxgeom.geodesic_distances(tess, sources, boundary="dirichlet")))


def test_boundary_choices_and_the_source_row(rng):
    x = disk(rng, 3000)
    tess = jaxgeom.delaunay(x)
    true = straight(x, [7])
    for boundary in ("mean", "neumann", "dirichlet"):
        dist = np.asarray(jaxgeom.geodesic_distances(tess, 7, boundary=boundary))
        assert dist[0, 7] == 0.0 and np.isfinite(dist).all()
        assert median_error(tess, dist, true) < 0.1


def test_cg_agrees_with_the_direct_solver_under_jit_and_vmap(rng):
    x = rng.random((700, 2))
    tess = jaxgeom.delaunay(x)
    sources = jnp.asarray([3, 50, 400], jnp.int32)
    direct = np.asarray(jaxgeom.geodesic_distances(tess, sources, solver="direct"))
    cg = jax.jit(lambda s: jaxgeom.geodesic_distances(tess, s, solver="cg"))(sources)
    np.testing.assert_allclose(cg, direct, rtol=0, atol=1e-7 * direct.max())
    # traced sources outside [0, N) are a NaN row, like Bellman-Ford's row of inf
    rows = np.asarray(jax.jit(lambda s: jaxgeom.geodesic_distances(tess, s))(jnp.asarray([3, 700], jnp.int32)))
    np.testing.assert_allclose(rows[0], direct[0], rtol=1e-12, atol=1e-14)
    assert np.isnan(rows[1]).all()
    # a batch of swarms (same capacities) under vmap, each against its own call
    swarms = jnp.stack([tess.points, tess.points * 2.0])
    batched = jax.vmap(lambda p: jaxgeom.geodesic_distances(eqx_replace(tess, p), [3], solver="cg"))(swarms)
    np.testing.assert_allclose(batched[1], 2.0 * batched[0], rtol=1e-7)
    np.testing.assert_allclose(batched[0], direct[:1], rtol=0, atol=1e-7 * direct.max())


def eqx_replace(tess, points):
    return eqx.tree_at(lambda t: t.points, tess, points)


def _metric(a):
    """An anisotropic, position-dependent metric with one parameter a."""
    return lambda p: (1.0 + a * p[0] ** 2) * jnp.diag(jnp.stack([jnp.ones_like(p[0]), 1.0 + a + 0.0 * p[0]]))


@pytest.mark.parametrize("solver", ["direct", "cg"])
def test_gradient_in_a_metric_parameter_matches_central_differences(rng, solver):
    tess = jaxgeom.delaunay(rng.random((300, 2)))
    targets = jnp.asarray([40, 120, 250])

    def total(a, solver):
        return jnp.sum(jaxgeom.geodesic_distances(tess, [5], _metric(a), solver=solver)[0, targets])

    grad = float(jax.grad(total)(0.7, solver))
    h = 1e-5  # central differences of the direct solver (no CG tolerance in them)
    fd = (float(total(0.7 + h, "direct")) - float(total(0.7 - h, "direct"))) / (2 * h)
    assert abs(grad - fd) < (1e-7 if solver == "direct" else 1e-5) * abs(fd), (grad, fd)


def test_gradient_in_the_positions_and_the_time_step(rng):
    x = rng.random((200, 2))
    tess = jaxgeom.delaunay(x)

    def distance(points, t):
        moved = eqx_replace(tess, points)
        return jaxgeom.geodesic_distances(moved, [4], t=t)[0, 150]

    t0 = 0.01
    g_points, g_t = jax.grad(distance, argnums=(0, 1))(jnp.asarray(x), jnp.asarray(t0))
    h = 1e-6
    step = np.zeros_like(x)
    step[150, 0] = h
    fd = (float(distance(jnp.asarray(x + step), t0)) - float(distance(jnp.asarray(x - step), t0))) / (2 * h)
    assert abs(float(g_points[150, 0]) - fd) < 1e-6 * max(abs(fd), 1e-3)
    fd_t = (float(distance(jnp.asarray(x), t0 + h)) - float(distance(jnp.asarray(x), t0 - h))) / (2 * h)
    assert abs(float(g_t) - fd_t) < 1e-5 * max(abs(fd_t), 1e-3)


def test_float32_distances(rng):
    x = disk(rng, 3000).astype(np.float32)
    tess = jaxgeom.delaunay(x)
    sources = np.flatnonzero(np.linalg.norm(x, axis=1) < 0.2)[:2]
    true = straight(x.astype(np.float64), sources)
    for solver in ("direct", "cg"):
        dist = jaxgeom.geodesic_distances(tess, sources, solver=solver)
        assert dist.dtype == jnp.float32
        assert median_error(tess, np.asarray(dist, np.float64), true) < 0.02


def test_the_factorisation_is_cached_per_operator(rng, monkeypatch):
    tess = jaxgeom.delaunay(rng.random((500, 2)))
    calls = []
    real = _heat._assemble
    monkeypatch.setattr(_heat, "_assemble", lambda *a: calls.append(1) or real(*a))
    _heat._FACTORS.clear()
    first = np.asarray(jaxgeom.geodesic_distances(tess, [1, 2], solver="direct"))
    assert len(calls) == 3  # Neumann and Dirichlet heat operators, pinned Laplacian
    again = np.asarray(jaxgeom.geodesic_distances(tess, [2, 9, 30], solver="direct"))
    assert len(calls) == 3
    np.testing.assert_array_equal(again[0], first[1])
    jaxgeom.geodesic_distances(tess, [1], sphere, solver="direct")  # another metric: new operators
    assert len(calls) == 6


@pytest.mark.parametrize("backend", ["cholmod", "superlu"])
def test_direct_backends_solve_the_assembled_systems(rng, backend):
    if backend == "cholmod" and _heat.cholespy is None:
        pytest.skip("cholespy is not installed")
    tess = jaxgeom.delaunay(rng.random((300, 2)))
    op = _heat.heat_operators(tess)
    keep = ~np.asarray(tess.hull)
    matrix = _heat._assemble(op.simplices, op.stiffness, op.mass, op.t, keep)
    factor = _heat.new_factor(matrix, backend)
    assert isinstance(factor, _heat._Cholesky) == (backend == "cholmod")
    rhs = rng.random((300, 3))
    np.testing.assert_allclose(matrix @ factor.solve(rhs), rhs, atol=1e-12)
    # a matrix that is not positive definite falls back to SuperLU
    indefinite = _heat.scipy.sparse.csr_matrix(np.array([[1.0, 2.0], [2.0, 1.0]]))
    np.testing.assert_allclose(_heat.new_factor(indefinite, backend).solve(np.array([1.0, 0.0])), [-1 / 3, 2 / 3])
    # one that needs pivoting is solved; an exactly singular one gives NaN, not an exception
    swap = _heat.scipy.sparse.csr_matrix(np.array([[0.0, 1.0], [1.0, 0.0]]))
    np.testing.assert_allclose(_heat.new_factor(swap, backend).solve(np.array([1.0, 2.0])), [2.0, 1.0])
    singular = _heat.scipy.sparse.csr_matrix(np.array([[1.0, 1.0], [1.0, 1.0]]))
    assert np.all(np.isnan(_heat.new_factor(singular, backend).solve(np.array([1.0, 0.0]))))


def test_heat_bad_arguments(rng):
    x = rng.random((50, 2))
    tess = jaxgeom.delaunay(x)
    with pytest.raises(ValueError, match="method='heat' needs Delaunay simplices.*method='dijkstra'"):
        jaxgeom.geodesic_distances(jaxgeom.knn_graph(x, 6), 0)
    with pytest.raises(ValueError, match="unknown boundary 'robin'; valid values are 'mean', 'neumann', 'dirichlet'"):
        jaxgeom.geodesic_distances(tess, 0, boundary="robin")
    with pytest.raises(ValueError, match="unknown solver 'lu'; valid values are 'auto', 'direct', 'cg'"):
        jaxgeom.geodesic_distances(tess, 0, solver="lu")
    with pytest.raises(ValueError, match=r"`t` must be a finite number > 0 \(the heat time step"):
        jaxgeom.geodesic_distances(tess, 0, t=-1.0)


def test_gram_route_matches_simplex_volumes_in_4d(rng):
    """Any dimension: the intrinsic volumes are the Euclidean simplex volumes."""
    x = rng.random((40, 4))
    tess = jaxgeom.delaunay(x)
    op = _heat.heat_operators(tess)
    valid = np.asarray(tess.simplex_mask)
    p = np.asarray(x)[np.asarray(tess.simplices)[valid]]
    ref = np.abs(np.linalg.det(p[:, 1:] - p[:, :1])) / math.factorial(4)
    np.testing.assert_allclose(np.asarray(op.volumes)[valid], ref, rtol=1e-10)
    assert op.stiffness.shape[1:] == (5, 5) and np.allclose(np.asarray(op.stiffness).sum(axis=2), 0.0, atol=1e-9)


@pytest.mark.parametrize("dim, n", [(2, 300), (3, 400)])
def test_heat_distances_where_the_metric_lengths_do_not_close(dim, n):
    """A clipped Hessian metric of Rastrigin varies faster than a few hundred walkers resolve:
    most simplices' metric edge lengths violate a triangle inequality. (Once: a singular factor
    raised from the host callback.) Those simplices take their mean edge metric with
    non-negative weights; the distances are finite, said to be coarse, the same with both
    solvers, and (2D) above the bound sqrt(eps) |x - x_0| that g >= eps I gives."""
    rng = np.random.default_rng(0)
    x = rng.uniform(-5.12, 5.12, (n, dim))
    tess, metric = jaxgeom.delaunay(x), jaxgeom.hessian_metric(rastrigin, 0.1)
    with pytest.warns(UserWarning, match=r"in \d+ of \d+ simplices the metric edge lengths do not close"):
        direct = np.asarray(jaxgeom.geodesic_distances(tess, 0, metric, solver="direct"))[0]
    with pytest.warns(UserWarning, match="do not close"):
        cg = np.asarray(jaxgeom.geodesic_distances(tess, 0, metric, solver="cg"))[0]
    assert np.all(np.isfinite(direct))
    np.testing.assert_allclose(cg, direct, atol=1e-7)
    lower = np.sqrt(0.1) * np.linalg.norm(x[1:] - x[0], axis=1)
    graph = np.asarray(jaxgeom.geodesic_distances(tess, 0, metric, method="dijkstra"))[0]
    if dim == 2:
        assert np.all(direct[1:] >= lower) and np.median(direct[1:] / graph[1:]) < 1.0
    else:  # 96% of simplices fall back: coarse, a few walkers below the bound
        assert np.mean(direct[1:] >= lower) > 0.95 and np.median(direct[1:] / graph[1:]) < 1.5


def test_positive_definite_is_not_a_positive_determinant():
    """Gram matrices with two negative eigenvalues have det > 0 and are no simplex."""
    from jaxgeom.base._simplex import small_positive_definite

    m = np.array([np.diag([1.0, 2.0, 3.0]), np.diag([1.0, -2.0, -3.0]), np.diag([1.0, 0.0, 3.0])])
    assert np.linalg.det(m[1]) > 0
    np.testing.assert_array_equal(small_positive_definite(jnp.asarray(m)), [True, False, False])


def test_components_of_the_weight_graph(rng):
    """A walker whose simplices all lost their weights is its own component, pinned on its own."""
    tess = jaxgeom.delaunay(rng.random((60, 2)))
    op = _heat.heat_operators(tess)
    assert np.all(np.asarray(_heat.component_labels(op)) == 0)
    cut = np.any(np.asarray(tess.simplices) == 7, axis=1)
    op = eqx.tree_at(
        lambda o: (o.stiffness, o.closes), op, (jnp.where(cut[:, None, None], 0.0, op.stiffness), jnp.asarray(~cut))
    )
    labels = np.asarray(_heat.component_labels(op))
    assert labels[7] == 7 and np.all(np.delete(labels, 7) == 0)
