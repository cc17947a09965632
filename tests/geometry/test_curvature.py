import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import sphere

import jaxgeom
from jaxgeom.geometry._curvature import ricci_from_deficits


def hyperbolic(x):  # Poincare ball: R = -d (d - 1)
    return 4.0 / (1.0 - jnp.sum(x * x)) ** 2 * jnp.eye(x.shape[0])


def anisotropic(x):  # a curved, non-diagonal, strongly anisotropic metric
    c, s = jnp.cos(3.0 * x[0]), jnp.sin(3.0 * x[0])
    rot = jnp.array([[c, -s], [s, c]])
    return rot @ jnp.diag(jnp.array([1.0 + x[1] ** 2, 0.2])) @ rot.T


def anisotropic_3d(x):
    c, s = jnp.cos(4.0 * x[2]), jnp.sin(4.0 * x[2])
    rot = jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ jnp.diag(jnp.array([30.0 * (1.0 + x[0] ** 2), 1.0, 0.05])) @ rot.T


def ball(n, d, seed, radius=0.5):
    x = np.random.default_rng(seed).uniform(-radius, radius, size=(4 * n, d))
    return x[np.linalg.norm(x, axis=1) < radius][:n]


@pytest.mark.parametrize("d, n", [(2, 3000), (3, 2000)])
def test_flat_metric_gives_zero_curvature_and_zero_interior_deficits(d, n):
    x = ball(n, d, seed=1)
    tess = jaxgeom.delaunay(x)
    interior = np.asarray(tess.tier) == 2
    r = np.asarray(jaxgeom.ricci_scalar(tess))
    assert np.all(r[interior] == 0.0)
    r_textbook = np.asarray(ricci_from_deficits(tess))
    assert np.abs(r_textbook[interior]).max() < 1e-7 * n, "2 pi - angle sums vanish to rounding"
    delta = np.asarray(jaxgeom.deficit_angles(tess))
    if d == 2:
        assert np.abs(delta[~np.asarray(tess.hull)]).max() < 1e-12
    else:
        both = interior[:, None] & np.append(interior, False)[np.asarray(tess.neighbors)]
        assert np.abs(delta[both]).max() < 1e-10
    assert np.all(np.isnan(r[np.asarray(tess.tier) == 0]))


def test_periodic_flat_deficits_vanish_everywhere(rng):
    tess = jaxgeom.delaunay(rng.random((400, 3)), box=(0.0, 1.0), periodic=True)
    delta = np.asarray(jaxgeom.deficit_angles(tess))
    assert np.abs(delta).max() < 1e-9


@pytest.mark.parametrize(
    "metric", [None, sphere, hyperbolic, anisotropic, "array"], ids=lambda m: getattr(m, "__name__", str(m))
)
def test_discrete_gauss_bonnet_on_a_disk(metric):
    x = ball(1500, 2, seed=2)
    tess = jaxgeom.delaunay(x)
    if metric == "array":
        metric = jaxgeom.emergent_metric(tess)
    hull = np.asarray(tess.hull)
    sums = np.asarray(jaxgeom.angle_sums(tess, metric=metric))
    delta = np.asarray(jaxgeom.deficit_angles(tess, metric=metric))
    assert np.all(delta[hull] == 0.0), "hull hinges carry no deficit"
    total = delta[~hull].sum() + np.sum(np.pi - sums[hull])
    assert abs(total - 2 * np.pi) < 1e-9


@pytest.mark.parametrize(
    "d, n, metric, exact, tol",
    [
        (2, 20000, sphere, 2.0, 0.01),
        (2, 20000, hyperbolic, -2.0, 0.01),
        (3, 20000, sphere, 6.0, 0.02),
        (3, 20000, hyperbolic, -6.0, 0.02),
    ],
    ids=["sphere2", "hyperbolic2", "sphere3", "hyperbolic3"],
)
def test_constant_curvature_region_average(d, n, metric, exact, tol):
    x = ball(n, d, seed=3)
    tess = jaxgeom.delaunay(x)
    region = tess.interior & jnp.asarray(np.linalg.norm(x, axis=1) < 0.35)
    assert int(region.sum()) >= 1000
    r = jaxgeom.ricci_scalar(tess, metric=metric)
    avg = float(jaxgeom.riemannian_mean(r, jaxgeom.riemannian_volumes(tess, metric=metric), region))
    assert abs(avg / exact - 1) < tol


@pytest.mark.parametrize("d", [2, 3])
def test_ricci_equals_textbook_deficit_form(d):
    x = ball(1500, d, seed=4)
    tess = jaxgeom.delaunay(x)
    metric = sphere
    r = np.asarray(jaxgeom.ricci_scalar(tess, metric=metric))
    r_textbook = np.asarray(ricci_from_deficits(tess, metric))
    ok = np.asarray(tess.tier) > 0
    np.testing.assert_allclose(r[ok], r_textbook[ok], rtol=1e-8, atol=1e-8 * np.abs(r[ok]).max())


def test_mode_none_ignores_the_metric_and_diagonal_equals_full_for_diagonal_metrics():
    x = ball(1500, 2, seed=5)
    tess = jaxgeom.delaunay(x)
    interior = np.asarray(tess.tier) == 2
    assert np.all(np.asarray(jaxgeom.ricci_scalar(tess, metric=sphere, mode="none"))[interior] == 0.0)
    full = np.asarray(jaxgeom.ricci_scalar(tess, metric=sphere))
    diag = np.asarray(jaxgeom.ricci_scalar(tess, metric=sphere, mode="diagonal"))
    np.testing.assert_allclose(diag[interior], full[interior], rtol=1e-12)
    aniso_full = np.asarray(jaxgeom.ricci_scalar(tess, metric=anisotropic))
    aniso_diag = np.asarray(jaxgeom.ricci_scalar(tess, metric=anisotropic, mode="diagonal"))
    assert np.abs(aniso_full - aniso_diag)[interior].max() > 1e-3


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_no_nan_or_inf_under_strongly_anisotropic_3d_metric(rng, dtype):
    x = rng.random((1500, 3))
    with jax.enable_x64(dtype == "float64"):
        tess = jaxgeom.delaunay(x.astype(dtype))
        r = np.asarray(jaxgeom.ricci_scalar(tess, metric=anisotropic_3d))
        delta = np.asarray(jaxgeom.deficit_angles(tess, metric=anisotropic_3d))
        sq = np.asarray(jaxgeom.geometry._metric.simplex_sq_lengths(tess, anisotropic_3d))
    assert r.dtype == np.dtype(dtype)
    keep = np.asarray(tess.tier) > 0
    assert np.isfinite(r[keep]).all() and np.isfinite(delta).all()
    from jaxgeom.geometry._curvature import hinge_angle_vectors

    gram_det = np.asarray(jax.vmap(lambda s: hinge_angle_vectors(s, 3)[1])(jnp.asarray(sq, jnp.float64)))
    assert (gram_det == 0).any(), "the metric makes some tetrahedra invalid (det G <= 0)"


def test_grad_of_mean_ricci_and_riemannian_volume_wrt_eps_sigma():
    x = ball(400, 2, seed=6, radius=1.5)
    tess = jaxgeom.delaunay(x)

    def double_well(p):
        return (p[0] ** 2 - 1.0) ** 2 + 0.5 * p[1] ** 2

    def mean_ricci(eps):
        metric = jaxgeom.hessian_metric(double_well, eps)
        r = jaxgeom.ricci_scalar(tess, metric=metric)
        return jaxgeom.riemannian_mean(r, jaxgeom.riemannian_volumes(tess, metric=metric), tess.interior)

    def total_volume(eps):
        vol = jaxgeom.riemannian_volumes(tess, metric=jaxgeom.hessian_metric(double_well, eps))
        return jnp.sum(jnp.where(tess.interior, vol, 0.0))

    for fn in (mean_ricci, total_volume):
        eps, h = 0.1, 1e-5
        grad = float(jax.grad(fn)(eps))
        fd = (float(fn(eps + h)) - float(fn(eps - h))) / (2 * h)
        assert np.isfinite(grad) and grad != 0.0
        assert abs(grad - fd) <= 1e-6 * max(1.0, abs(fd))


def test_curvature_bad_input(rng):
    knn = jaxgeom.knn_graph(rng.random((50, 2)), 6)
    with pytest.raises(ValueError, match="needs Delaunay simplices"):
        jaxgeom.ricci_scalar(knn)
    tess = jaxgeom.delaunay(rng.random((50, 2)))
    with pytest.raises(ValueError, match="unknown mode 'exact'"):
        jaxgeom.ricci_scalar(tess, metric=sphere, mode="exact")
    tess4 = jaxgeom.delaunay(rng.random((60, 4)))
    with pytest.raises(ValueError, match="d = 2 and 3"):
        jaxgeom.deficit_angles(tess4)


@pytest.mark.slow
def test_ricci_in_4d_is_finite_in_the_bulk(rng):
    tess4 = jaxgeom.delaunay(rng.random((60, 4)))
    assert np.isfinite(np.asarray(jaxgeom.ricci_scalar(tess4))[np.asarray(tess4.tier) == 2]).all()
