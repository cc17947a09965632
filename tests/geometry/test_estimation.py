import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom


def graphs(x):
    d = x.shape[1]
    return {"delaunay": jaxgeom.delaunay(x), "knn": jaxgeom.knn_graph(x, 12 if d == 2 else 20)}


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("graph", ["delaunay", "knn"])
def test_linear_and_quadratic_fields_are_recovered_exactly(rng, d, graph):
    x = rng.random((1500, d))
    tess = graphs(x)[graph]
    interior = np.asarray(tess.tier) == 2 if graph == "delaunay" else np.ones(len(x), bool)
    a = rng.normal(size=d)
    h = rng.normal(size=(d, d))
    h = h + h.T
    linear = x @ a - 0.7
    quadratic = 0.5 * np.einsum("ni,ij,nj->n", x, h, x) + x @ a
    grad = np.asarray(jaxgeom.estimate_gradient(tess, linear))
    assert np.abs(grad[interior] - a).max() < 1e-10
    grad_q = np.asarray(jaxgeom.estimate_gradient(tess, quadratic))
    rmse = np.sqrt(np.mean(np.sum((grad_q[interior] - (x[interior] @ h + a)) ** 2, axis=1)))
    assert rmse < 1e-9
    grad_lin = np.asarray(jaxgeom.estimate_gradient(tess, linear, order=1))
    assert np.abs(grad_lin[interior] - a).max() < 1e-10
    hess, info = jaxgeom.estimate_hessian(tess, quadratic, with_info=True)
    hess = np.asarray(hess)
    rel = np.linalg.norm(hess[interior] - h, axis=(1, 2)) / np.linalg.norm(h)
    assert np.all(np.isfinite(rel)) and rel.max() < 1e-8
    assert int(info.n_over_capacity) == 0


def test_quadratic_fit_gradient_rmse(rng):
    """The gradient of the local quadratic fit is exact on quadratics (the WLS gradient is not)."""
    from jaxgeom.geometry._estimation import _quadratic_fit, _value_differences

    x = rng.random((800, 2))
    tess = jaxgeom.knn_graph(x, 12)
    h = np.array([[2.0, 0.5], [0.5, 1.0]])
    values = 0.5 * np.einsum("ni,ij,nj->n", x, h, x)
    dv, usable = _value_differences(tess, jnp.asarray(values))
    hess, grad, ok = _quadratic_fit(jaxgeom.tessellation._graph.neighbor_coord_displacements(tess), dv, usable)
    assert np.asarray(ok).all()
    np.testing.assert_allclose(np.asarray(hess), np.broadcast_to(h, (800, 2, 2)), rtol=1e-9)
    np.testing.assert_allclose(np.asarray(grad), x @ h, rtol=1e-9, atol=1e-12)


def test_fd_gradient_reproduces_the_chapter_formula(rng):
    x = rng.random((60, 2))
    values = np.sin(3 * x[:, 0]) + x[:, 1] ** 2
    tess = jaxgeom.delaunay(x)
    nbrs = np.asarray(tess.neighbors)
    for weighting in ("uniform", "inverse_distance", "gaussian"):
        ours = np.asarray(jaxgeom.estimate_gradient(tess, values, method="fd", weights=weighting))
        for i in range(60):
            js = nbrs[i][nbrs[i] < 60]
            dx = x[js] - x[i]
            dist = np.linalg.norm(dx, axis=1)
            w = {
                "uniform": np.ones(len(js)),
                "inverse_distance": 1 / dist,
                "gaussian": np.exp(-(dist**2) / (2 * np.median(dist) ** 2)),
            }[weighting]
            w = w / w.sum()
            ref = np.sum((w * (values[js] - values[i]) / dist**2)[:, None] * dx, axis=0)
            np.testing.assert_allclose(ours[i], ref, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("jitter, rtol", [(0.0, 1e-10), (1e-3, 1e-2)])
def test_diagonal_hessian_and_axis_quality(jitter, rtol):
    i, j = np.meshgrid(np.arange(12.0), np.arange(12.0))
    x = np.stack([0.3 * i.ravel(), 0.2 * j.ravel()], axis=1) + jitter * np.random.default_rng(1).normal(size=(144, 2))
    values = 1.5 * x[:, 0] ** 2 - 0.5 * x[:, 1] ** 2 + 4.0 * x[:, 0] + 3.0 * x[:, 1]
    tess = jaxgeom.knn_graph(x, 8)
    diag, info = jaxgeom.estimate_hessian(tess, values, kind="diagonal", with_info=True)
    quality = info.axis_quality
    inner = np.all((x > 0.5) & (x < [3.0, 2.0]), axis=1)
    np.testing.assert_allclose(np.asarray(diag)[inner], np.broadcast_to([3.0, -1.0], (inner.sum(), 2)), rtol=rtol)
    q = np.asarray(quality)
    assert np.all((q >= 0) & (q <= 1)) and q[inner].min() > 0.98 and bool(info.valid[inner].all())


def test_degenerate_neighbourhoods_give_nan_and_a_count_without_leaking(rng):
    x = rng.random((400, 2))
    values = x[:, 0] * 2.0 + x[:, 1]
    values[7] = np.nan
    tess = jaxgeom.delaunay(x)
    grad, info = jaxgeom.estimate_gradient(tess, values, order=1, with_info=True)
    grad = np.asarray(grad)
    assert np.isnan(grad[7]).all() and not bool(info.valid[7])
    nbrs = np.asarray(tess.neighbors)[7]
    around = nbrs[nbrs < 400]
    interior_around = around[np.asarray(tess.tier)[around] == 2]
    np.testing.assert_allclose(
        grad[interior_around], np.broadcast_to([2.0, 1.0], (len(interior_around), 2)), rtol=1e-10
    )
    assert int(info.n_invalid) == int(np.isnan(grad).any(axis=1).sum())
    thin = jaxgeom.knn_graph(rng.random((50, 3)), 2)  # 2 neighbours cannot determine a 3D gradient
    g2, info2 = jaxgeom.estimate_gradient(thin, rng.random(50), order=1, with_info=True)
    assert np.isnan(np.asarray(g2)).all() and int(info2.n_invalid) == 50
    h2, info3 = jaxgeom.estimate_hessian(thin, rng.random(50), with_info=True)
    assert int(info3.n_invalid) == 50


def test_estimates_run_inside_jit_and_in_float32(rng):
    x = rng.random((300, 2))
    tess = jaxgeom.delaunay(x)
    values = jnp.asarray(x[:, 0] ** 2 + x[:, 1])
    grad = jax.jit(lambda t, v: jaxgeom.estimate_gradient(t, v))(tess, values)
    assert np.isfinite(np.asarray(grad)[np.asarray(tess.tier) == 2]).all()
    with jax.enable_x64(False):
        t32 = jaxgeom.delaunay(x.astype(np.float32))
        h32 = np.asarray(jaxgeom.estimate_hessian(t32, (x[:, 0] ** 2 + x[:, 1]).astype(np.float32)))
    assert h32.dtype == np.float32
    np.testing.assert_allclose(np.nanmedian(h32[:, 0, 0]), 2.0, rtol=1e-2)


def test_geometric_hessian_is_emergent_metric_minus_eps(rng):
    tess = jaxgeom.delaunay(rng.random((200, 2)))
    np.testing.assert_allclose(
        np.asarray(jaxgeom.geometric_hessian(tess, 0.1)),
        np.asarray(jaxgeom.emergent_metric(tess)) - 0.1 * np.eye(2),
        rtol=1e-14,
    )


def test_estimation_bad_input(rng):
    tess = jaxgeom.delaunay(rng.random((30, 2)))
    with pytest.raises(ValueError, match="unknown method 'central'; valid values are 'wls', 'fd'"):
        jaxgeom.estimate_gradient(tess, np.zeros(30), method="central")
    with pytest.raises(ValueError, match="unknown weights 'cubic'"):
        jaxgeom.estimate_gradient(tess, np.zeros(30), weights="cubic")
    with pytest.raises(ValueError, match="`order` must be 1"):
        jaxgeom.estimate_gradient(tess, np.zeros(30), order=3)
    with pytest.raises(ValueError, match="unknown kind 'mixed'; valid values are 'full', 'diagonal'"):
        jaxgeom.estimate_hessian(tess, np.zeros(30), kind="mixed")


def test_compare_estimation_methods_metrics_match_numpy(rng):
    x = rng.normal(size=(800, 2))
    tess = jaxgeom.delaunay(x)
    values = 0.5 * (2.0 * x[:, 0] ** 2 + 0.5 * x[:, 1] ** 2)
    out = jaxgeom.compare_estimation_methods(tess, values, eps_sigma=0.1)
    valid = out["valid"]
    assert valid.sum() > 500
    h_fd, h_geo = np.asarray(out["hessian_fd"])[valid], np.asarray(out["hessian_geometric"])[valid]
    np.testing.assert_allclose(h_fd, np.broadcast_to(np.diag([2.0, 0.5]), h_fd.shape), atol=1e-8)
    e_fd, e_geo = np.linalg.eigvalsh(h_fd), np.linalg.eigvalsh(h_geo)
    metrics = out["metrics"]
    assert abs(metrics["eigenvalue_correlation"] - np.corrcoef(e_fd.ravel(), e_geo.ravel())[0, 1]) < 1e-12
    frob = 1 - np.linalg.norm(h_fd - h_geo, axis=(1, 2)) / (
        np.linalg.norm(h_fd, axis=(1, 2)) + np.linalg.norm(h_geo, axis=(1, 2))
    )
    assert abs(metrics["frobenius_agreement"] - frob.mean()) < 1e-12
    rho = metrics["eigenvalue_correlation"]
    assert metrics["method_preference"] == ("excellent" if rho > 0.8 else "good" if rho > 0.6 else "poor")


def test_validate_on_synthetic_functions():
    quad = jaxgeom.validate_on_synthetic_function("quadratic", n_walkers=300)
    assert quad["passed"] and quad["gradient_rmse"] < 1e-9 and quad["hessian_frobenius_error"] < 1e-8
    coarse = jaxgeom.validate_on_synthetic_function("rosenbrock", n_walkers=300)
    fine = jaxgeom.validate_on_synthetic_function("rosenbrock", n_walkers=3000)
    assert fine["gradient_relative_rmse"] < coarse["gradient_relative_rmse"] / 3
    assert fine["hessian_frobenius_error"] < coarse["hessian_frobenius_error"] / 1.5
    assert -1 <= fine["fd_geometric_correlation"] <= 1
    with pytest.raises(ValueError, match="unknown name 'sphere'"):
        jaxgeom.validate_on_synthetic_function("sphere")


def test_plot_estimation_quality_writes_four_panels(tmp_path, rng):
    result = jaxgeom.validate_on_synthetic_function("rosenbrock", n_walkers=400)
    path = jaxgeom.plot_estimation_quality(result, tmp_path / "quality.png")
    assert path.stat().st_size > 20_000
    x = rng.normal(size=(300, 2))
    comparison = jaxgeom.compare_estimation_methods(jaxgeom.delaunay(x), x[:, 0] ** 2, eps_sigma=0.1)
    assert jaxgeom.plot_estimation_quality(comparison, tmp_path / "cmp.png").stat().st_size > 20_000


def test_plotting_leaves_the_users_matplotlib_alone(tmp_path):
    """A notebook's inline backend stays (it once was switched to Agg, and the notebook's own
    figures after the call were not shown), and no figure is left open in pyplot."""
    import matplotlib
    import matplotlib.pyplot as plt

    before = matplotlib.get_backend()
    plt.switch_backend("svg")  # a backend of the user's, distinct from Agg
    try:
        result = jaxgeom.validate_on_synthetic_function("rosenbrock", n_walkers=200)
        jaxgeom.plot_estimation_quality(result, tmp_path / "quality.png")
        assert matplotlib.get_backend() == "svg"
        assert plt.get_fignums() == []
    finally:
        plt.switch_backend(before)


def test_periodic_two_ring_uses_stored_image_shifts(rng):
    """A periodic quadratic-in-image field: every walker's fit (2-ring ones included) is exact."""
    x = rng.random((600, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    h = np.array([[1.5, 0.4], [0.4, -0.8]])
    values = 0.5 * np.einsum("ni,ij,nj->n", x, h, x)
    # the field is not periodic, so compare fits on walkers whose 2-ring stays inside the box
    hess, info = jaxgeom.estimate_hessian(tess, values, with_info=True)
    inner = np.all((x > 0.25) & (x < 0.75), axis=1)
    assert bool(info.two_ring[inner].any()), "some inner walkers use the 2-ring"
    rel = np.linalg.norm(np.asarray(hess)[inner] - h, axis=(1, 2)) / np.linalg.norm(h)
    assert rel.max() < 1e-8


def test_two_ring_displacements_compose_neighbour_displacements(rng):
    """In a thin periodic box 2-ring steps exceed half the box, where minimum image fails."""
    from jaxgeom.geometry._estimation import TWO_RING_WIDTH, _two_ring

    lower, upper = np.zeros(2), np.array([3.0, 0.4])
    x = lower + rng.random((14, 2)) * (upper - lower)
    tess = jaxgeom.delaunay(x, box=(lower, upper), periodic=True)
    walkers = jnp.arange(14, dtype=jnp.int32)
    dxs, _, usable = _two_ring(tess, jnp.zeros(14), walkers)
    got, usable = np.stack([np.asarray(d) for d in dxs], -1), np.asarray(usable)
    m = min(tess.neighbors.shape[1], TWO_RING_WIDTH[2])
    nbrs, disp = np.asarray(tess.neighbors)[:, :m], np.asarray(jaxgeom.neighbor_displacements(tess))[:, :m]
    second = disp[:, :, None, :] + disp[np.minimum(nbrs, 13)]  # i -> j, then j -> k
    expected = np.concatenate([disp, second.reshape(14, -1, 2)], axis=1)
    assert np.abs(expected[usable][:, 1]).max() > 0.2, "some 2-ring step spans more than half the box"
    np.testing.assert_allclose(got[usable], expected[usable], atol=1e-12)
