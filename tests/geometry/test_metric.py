import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import sphere, tile

import jaxgeom


def rosenbrock(x):
    return 100.0 * (x[1] - x[0] ** 2) ** 2 + (1.0 - x[0]) ** 2


def rosenbrock_hessian(x):
    return np.array([[1200 * x[0] ** 2 - 400 * x[1] + 2, -400 * x[0]], [-400 * x[0], 200.0]])


def test_hessian_metric_quadratic_is_a_plus_eps():
    a = np.array([[3.0, 1.0, 0.0], [1.0, 2.0, 0.5], [0.0, 0.5, 1.0]])
    g = jaxgeom.hessian_metric(lambda x: 0.5 * x @ a @ x, 0.05)
    for x in np.random.default_rng(0).normal(size=(4, 3)):
        np.testing.assert_allclose(g(jnp.asarray(x)), a + 0.05 * np.eye(3), rtol=1e-12)


def test_hessian_metric_rosenbrock_where_positive_definite():
    g = jaxgeom.hessian_metric(rosenbrock, 0.1)
    for x in [np.array([1.0, 1.0]), np.array([0.5, 0.1]), np.array([-1.2, 1.0])]:
        h = rosenbrock_hessian(x)
        assert np.linalg.eigvalsh(h).min() > 0
        np.testing.assert_allclose(g(jnp.asarray(x)), h + 0.1 * np.eye(2), rtol=1e-10)


@pytest.mark.parametrize("floor", ["clip", "softabs"])
def test_hessian_metric_floors_indefinite_hessians(floor):
    eps = 0.03
    g = jaxgeom.hessian_metric(rosenbrock, eps, floor=floor)
    x = jnp.asarray([0.5, 1.0])  # 1200/4 - 400 + 2 < 0: indefinite
    assert np.linalg.eigvalsh(rosenbrock_hessian(np.asarray(x))).min() < 0
    lam = np.linalg.eigvalsh(np.asarray(g(x)))
    assert lam.min() >= eps * (1 - 1e-12)
    saddle = jaxgeom.hessian_metric(lambda x: x[0] ** 2 - x[1] ** 2, eps, floor=floor)
    lam = np.linalg.eigvalsh(np.asarray(saddle(jnp.zeros(2))))
    expected = [eps, 2 + eps] if floor == "clip" else [2 / np.tanh(2 / eps), 2 / np.tanh(2 / eps)]
    np.testing.assert_allclose(np.sort(lam), np.sort(expected), rtol=1e-10)


def test_hessian_metric_gradients_are_finite_for_repeated_eigenvalues():
    g = jaxgeom.hessian_metric(lambda x: jnp.sum(x**2) + 0.1 * jnp.sum(x**4), 0.1)
    grad = jax.grad(lambda x: jnp.sum(g(x)))(jnp.zeros(3))
    assert np.isfinite(np.asarray(grad)).all()


def hex_lattice(n):
    i, j = np.meshgrid(np.arange(n), np.arange(n))
    return np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2], -1).reshape(-1, 2).astype(float)


@pytest.mark.parametrize("a", [np.diag([1.3, 1.0]), np.array([[1.0, 0.15], [0.0, 1.0]])])
def test_emergent_metric_of_deformed_hexagonal_lattice(a):
    z = hex_lattice(14)
    tess = jaxgeom.delaunay(z @ a.T)
    c0 = 0.5 * np.eye(2)  # six unit neighbours: mean of e e^T is I/2
    c = a @ c0 @ a.T
    eps = 1e-5
    expected = np.linalg.inv(c + eps * np.trace(c) / 2 * np.eye(2))
    g = np.asarray(jaxgeom.emergent_metric(tess, eps_reg=eps))
    interior = np.asarray(tess.tier) == 2
    assert interior.sum() > 50 and np.all(np.asarray(tess.degree)[interior] == 6)
    np.testing.assert_allclose(g[interior], np.broadcast_to(expected, g[interior].shape), rtol=1e-10, atol=1e-12)


def test_emergent_metric_of_stretched_fcc_lattice_with_knn():
    base = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]])
    cells = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), -1).reshape(-1, 1, 3)
    z = (cells + base).reshape(-1, 3)
    a = np.diag([1.1, 1.0, 1.0])
    tess = jaxgeom.knn_graph(z @ a.T, 12)
    shell = np.array(
        [v for v in np.stack(np.meshgrid(*[[-0.5, 0, 0.5]] * 3), -1).reshape(-1, 3) if np.isclose(np.sum(v * v), 0.5)]
    )
    c0 = shell.T @ shell / 12
    c = a @ c0 @ a.T
    expected = np.linalg.inv(c + 1e-5 * np.trace(c) / 3 * np.eye(3))
    inner = np.all((z > 1.2) & (z < 4.3), axis=1)
    g = np.asarray(jaxgeom.emergent_metric(tess))
    np.testing.assert_allclose(g[inner], np.broadcast_to(expected, g[inner].shape), rtol=1e-10, atol=1e-12)


def test_emergent_metric_is_scale_covariant(rng):
    x = rng.random((300, 2))
    g1 = np.asarray(jaxgeom.emergent_metric(jaxgeom.delaunay(x)))
    g2 = np.asarray(jaxgeom.emergent_metric(jaxgeom.delaunay(1e-3 * x)))
    np.testing.assert_allclose(g2, g1 * 1e6, rtol=1e-9)


def test_edge_lengths_modes(rng):
    x = rng.random((100, 2))
    tess = jaxgeom.delaunay(x)
    nbrs, mask = np.asarray(tess.neighbors), np.asarray(tess.neighbor_mask)
    dx = np.where(mask[..., None], x[np.minimum(nbrs, 99)] - x[:, None], 0.0)
    euclid = np.linalg.norm(dx, axis=-1)
    np.testing.assert_allclose(np.asarray(jaxgeom.edge_lengths(tess)), euclid, atol=1e-15)

    def metric(p):
        return jnp.array([[2.0 + p[0], 0.3], [0.3, 1.0 + p[1] ** 2]])

    mid = x[:, None] + 0.5 * dx
    g = np.stack(
        [
            np.stack([2 + mid[..., 0], np.full_like(mid[..., 0], 0.3)], -1),
            np.stack([np.full_like(mid[..., 0], 0.3), 1 + mid[..., 1] ** 2], -1),
        ],
        -2,
    )
    full = np.sqrt(np.einsum("nki,nkij,nkj->nk", dx, g, dx))
    diag = np.sqrt(np.einsum("nki,nkij,nkj->nk", dx, g * np.eye(2), dx))
    np.testing.assert_allclose(np.asarray(jaxgeom.edge_lengths(tess, metric=metric))[mask], full[mask], rtol=1e-12)
    np.testing.assert_allclose(
        np.asarray(jaxgeom.edge_lengths(tess, metric=metric, mode="diagonal"))[mask], diag[mask], rtol=1e-12
    )
    np.testing.assert_allclose(np.asarray(jaxgeom.edge_lengths(tess, metric=metric, mode="none")), euclid, atol=1e-15)
    per_walker = np.asarray(jaxgeom.metric_at_walkers(tess, metric))
    pair = 0.5 * (per_walker[:, None] + per_walker[np.minimum(nbrs, 99)])
    arr = np.sqrt(np.einsum("nki,nkij,nkj->nk", dx, pair, dx))
    np.testing.assert_allclose(np.asarray(jaxgeom.edge_lengths(tess, metric=per_walker))[mask], arr[mask], rtol=1e-12)


def periodic_metric(p):
    c = (1.0 + 0.5 * jnp.sin(2 * jnp.pi * p[0])) ** 2
    return c * jnp.eye(2)  # sqrt(det g) = c, integral over the unit box = 1.125


def test_riemannian_volumes_integrate_sqrt_det_g_with_decreasing_error():
    errors = []
    for n in [300, 1200, 4800, 19200]:
        x = np.random.default_rng(n).random((n, 2))
        tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
        total = float(jnp.sum(jaxgeom.riemannian_volumes(tess, metric=periodic_metric)))
        errors.append(abs(total - 1.125))
    assert errors[-1] < 1e-3
    assert errors[-1] < errors[0] / 10, errors


def test_riemannian_volumes_and_mean(rng):
    x = rng.random((200, 2))
    tess = jaxgeom.delaunay(x)
    g = np.asarray(jaxgeom.metric_at_walkers(tess, periodic_metric))
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    riem = np.asarray(jaxgeom.riemannian_volumes(tess, metric=periodic_metric))
    np.testing.assert_allclose(riem, vol * np.sqrt(np.linalg.det(g)), rtol=1e-12)
    values = rng.random(200)
    interior = np.asarray(tess.interior)
    expected = np.sum((values * riem)[interior]) / np.sum(riem[interior])
    assert abs(float(jaxgeom.riemannian_mean(values, riem, tess.interior)) - expected) < 1e-12


def test_metric_bad_input(rng):
    tess = jaxgeom.delaunay(rng.random((30, 2)))
    with pytest.raises(ValueError, match="unknown mode 'fulll'; valid values are 'none', 'diagonal', 'full'"):
        jaxgeom.edge_lengths(tess, metric=None, mode="fulll")
    with pytest.raises(ValueError, match=r"shape \(N, d, d\) = \(30, 2, 2\); got an array of shape \(30, 2\)"):
        jaxgeom.edge_lengths(tess, metric=np.ones((30, 2)))
    with pytest.raises(ValueError, match="must map x \\(d,\\) to g \\(d, d\\)"):
        jaxgeom.edge_lengths(tess, metric=lambda p: p)
    with pytest.raises(ValueError, match="unknown floor 'abs'"):
        jaxgeom.hessian_metric(rosenbrock, 0.1, floor="abs")
    with pytest.raises(ValueError, match="`eps_sigma` must be a finite number >= 0"):
        jaxgeom.hessian_metric(rosenbrock, -0.1)
    with pytest.raises(ValueError, match="`eps_reg` must be a finite number >= 0"):
        jaxgeom.emergent_metric(tess, eps_reg=-1.0)


def test_periodic_callable_metric_sees_wrapped_positions(rng):
    x = rng.random((150, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    tiled, _, _ = tile(x, np.zeros(2), np.ones(2))
    big = jaxgeom.delaunay(tiled)
    ours = np.asarray(jaxgeom.riemannian_volumes(tess, metric=periodic_metric))
    ref = np.asarray(jaxgeom.riemannian_volumes(big, metric=periodic_metric))[:150]
    np.testing.assert_allclose(ours, ref, rtol=1e-10)


@pytest.mark.parametrize("d, n", [(2, 300), (3, 300)])
@pytest.mark.parametrize("c", [1e200, 1e-200])
def test_metric_of_extreme_scale(rng, d, n, c):
    """c g for c = 1e200 and 1e-200: Riemannian volumes scale by c^(d/2) and the Ricci scalar
    by 1/c, all representable. (Once: det g overflowed to inf, and the host check refused
    1e-200 I because its minor underflowed to 0.)"""
    x = rng.uniform(-0.5, 0.5, (n, d))
    tess = jaxgeom.delaunay(x)
    g = np.asarray(jax.vmap(sphere)(jnp.asarray(x)))
    for metric, scaled in ((g, c * g), (sphere, lambda p: c * sphere(p))):
        vol, vol_c = (np.asarray(jaxgeom.riemannian_volumes(tess, metric=m)) for m in (metric, scaled))
        ricci, ricci_c = (np.asarray(jaxgeom.ricci_scalar(tess, metric=m)) for m in (metric, scaled))
        finite = np.isfinite(vol)
        assert finite.sum() > n // 2 and np.array_equal(np.isfinite(vol_c), finite)
        np.testing.assert_allclose(vol_c[finite], c ** (d / 2) * vol[finite], rtol=1e-12)
        finite = np.isfinite(ricci)
        assert finite.sum() > n // 4 and np.array_equal(np.isfinite(ricci_c), finite)
        np.testing.assert_allclose(ricci_c[finite], ricci[finite] / c, rtol=1e-6)
