"""metric_curvature: the Ricci scalar of a callable metric in any dimension, against closed
forms (sphere, Poincare ball, products, the Fisher metric of the categorical family), against
each other (Christoffel reference, exact and stochastic Hessian forms) and under coordinate
changes; gradients against central differences; bad input."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import double_well
from jaxgeom.base._checks import metric_defect_masks
from jaxgeom.geometry._metric_curvature import CHRISTOFFEL_FALLBACK_MAX_DIM

R = 1.7


def sphere(x):
    """The round sphere of radius R in stereographic coordinates: S = d(d-1)/R^2."""
    return 4 * R**2 / (1 + x @ x) ** 2 * jnp.eye(x.shape[0], dtype=x.dtype)


def poincare(x):
    """The Poincare ball: S = -d(d-1)."""
    return 4 / (1 - x @ x) ** 2 * jnp.eye(x.shape[0], dtype=x.dtype)


def product(d1):
    """S^d1(R) x H^(d - d1), block diagonal: S = d1(d1-1)/R^2 - d2(d2-1)."""

    def metric(x):
        return jax.scipy.linalg.block_diag(sphere(x[:d1]), poincare(x[d1:]))

    return metric


def categorical(x):
    """log(1 + sum exp x_i): the log-partition of the categorical family, whose Hessian is the
    Fisher metric, the round sphere of radius 2 (Fisher-Rao): S = d(d-1)/4."""
    return jnp.log1p(jnp.sum(jnp.exp(x)))


def convex_landscape(seed, d):
    """logsumexp(A x) + |x|^2 / 4: a nonseparable landscape with a positive definite Hessian."""
    a = jnp.asarray(np.random.default_rng(seed).normal(size=(d + 2, d)))

    def fitness(x):
        return jax.nn.logsumexp(a @ x) + 0.25 * x @ x

    return fitness


def points(n, d, scale=0.4, seed=0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-scale, scale, (n, d)))


def fisher(eps=0.0):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # eps_sigma = 0: the Fisher metric itself
        return jaxgeom.hessian_metric(categorical, eps)


@pytest.mark.parametrize("d", [2, 3, 4, 6, 10])
def test_christoffel_form_on_the_sphere_and_the_poincare_ball(d):
    x = points(6, d)
    s = jaxgeom.metric_curvature(sphere, x)
    b = jaxgeom.metric_curvature(poincare, x)
    np.testing.assert_allclose(s, d * (d - 1) / R**2, rtol=1e-8)
    np.testing.assert_allclose(b, -d * (d - 1), rtol=1e-8)


@pytest.mark.parametrize("d, d1", [(2, 1), (3, 2), (4, 2), (6, 3), (10, 4)])
def test_christoffel_form_adds_over_a_product(d, d1):
    d2 = d - d1
    expected = d1 * (d1 - 1) / R**2 - d2 * (d2 - 1)
    s = jaxgeom.metric_curvature(product(d1), points(5, d))
    np.testing.assert_allclose(s, expected, rtol=1e-8, atol=1e-10)  # d = 2: S^1 x H^1 is flat


def test_ricci_tensor_of_the_sphere_is_einstein():
    d = 4
    x = points(3, d)
    s, info = jaxgeom.metric_curvature(sphere, x, ricci=True, with_info=True)
    g = jax.vmap(sphere)(x)
    np.testing.assert_allclose(info.ricci, (d - 1) / R**2 * g, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(np.trace(np.linalg.solve(g, info.ricci), axis1=1, axis2=2), s, rtol=1e-12)
    assert info.method == "christoffel"


def test_invariant_under_a_linear_change_of_coordinates_and_scales_as_one_over_lambda_squared():
    d = 4
    fitness = convex_landscape(1, d)
    metric = jaxgeom.hessian_metric(fitness, 0.1)
    x = points(8, d)
    a = jnp.asarray(np.random.default_rng(2).normal(size=(d, d))) + 2 * jnp.eye(d)
    y = jnp.linalg.solve(a, x.T).T  # x = A y

    def plain(v):  # the same metric without the floor's eigensolver (inactive here): faster to compile
        return jax.hessian(fitness)(v) + 0.1 * jnp.eye(d)

    def pulled_back(v):
        return a.T @ plain(a @ v) @ a

    s = jaxgeom.metric_curvature(metric, x)
    np.testing.assert_allclose(jaxgeom.metric_curvature(pulled_back, y), s, rtol=1e-9)
    lam = 3.0
    np.testing.assert_allclose(jaxgeom.metric_curvature(lambda v: lam**2 * plain(v), x), s / lam**2, rtol=1e-9)
    # the Hessian metric of lam^2 V with eps lam^2 is lam^2 g: the Hessian form scales too
    scaled = jaxgeom.hessian_metric(lambda v: lam**2 * fitness(v), 0.1 * lam**2)
    np.testing.assert_allclose(jaxgeom.metric_curvature(scaled, x), s / lam**2, rtol=1e-9)


def test_gradients_in_eps_sigma_and_a_landscape_parameter_match_central_differences():
    x = points(6, 3, scale=1.5) + 2.0  # double well's convex region: the Hessian form

    @jax.jit  # eps and a traced: one compilation serves the values and the differences
    def mean_curvature(eps, a):
        def fitness(y):
            return double_well(y) + a * jnp.sum(y**3) / 3

        return jnp.mean(jaxgeom.metric_curvature(jaxgeom.hessian_metric(fitness, eps), x))

    grads = jax.grad(mean_curvature, argnums=(0, 1))(0.1, 0.2)
    h = 1e-5
    fd = (
        (mean_curvature(0.1 + h, 0.2) - mean_curvature(0.1 - h, 0.2)) / (2 * h),
        (mean_curvature(0.1, 0.2 + h) - mean_curvature(0.1, 0.2 - h)) / (2 * h),
    )
    assert all(np.isfinite(grads)) and abs(grads[0]) > 1e-3 and abs(grads[1]) > 1e-3
    np.testing.assert_allclose(grads, fd, rtol=1e-6)
    # and through the Christoffel form, and in the positions
    chris = jax.grad(
        lambda e: jnp.mean(jaxgeom.metric_curvature(jaxgeom.hessian_metric(double_well, e), x, method="christoffel"))
    )(0.1)
    hessian_form = jax.grad(mean_curvature, argnums=(0, 1))(0.1, 0.0)[0]  # the program compiled above
    np.testing.assert_allclose(chris, hessian_form, rtol=1e-8)
    gx = jax.grad(lambda p: jnp.sum(jaxgeom.metric_curvature(sphere, p)))(points(2, 3))
    np.testing.assert_allclose(gx, 0.0, atol=1e-9)  # constant curvature: no gradient in the points


@pytest.mark.parametrize(
    "d",
    [
        2,
        pytest.param(3, marks=pytest.mark.slow),
        pytest.param(4, marks=pytest.mark.slow),
        pytest.param(5, marks=pytest.mark.slow),
        6,
    ],
)  # the sweep in d: slow
def test_exact_hessian_form_equals_the_christoffel_form(d):
    fitness = convex_landscape(d, d)
    x = points(10, d, scale=1.0)
    exact, info = jaxgeom.metric_curvature(jaxgeom.hessian_metric(fitness, 0.05), x, with_info=True)
    # g = H + eps_Sigma I as a plain callable: the general formula knows nothing of Hessian metrics
    reference = jaxgeom.metric_curvature(lambda y: jax.hessian(fitness)(y) + 0.05 * jnp.eye(d), x)
    assert info.method == "hessian" and not info.floor_active.any()
    assert np.all(np.abs(reference) > 1e-3)  # curved: a relative error means something
    np.testing.assert_allclose(exact, reference, rtol=1e-8)


@pytest.mark.parametrize("d", [2, 3, 10, 50])
def test_hessian_form_on_the_fisher_metric_is_the_sphere_of_radius_two(d):
    x = points(4, d, scale=1.0)
    np.testing.assert_allclose(jaxgeom.metric_curvature(fisher(), x), d * (d - 1) / 4, rtol=1e-8)


def test_separable_landscapes_give_flat_hessian_metrics():
    metric = jaxgeom.hessian_metric(lambda x: jnp.sum(x**4 + jnp.cos(x)), 0.2)
    x = points(5, 6, scale=2.0) + 3.0
    np.testing.assert_allclose(jaxgeom.metric_curvature(metric, x), 0.0, atol=1e-10)


@pytest.mark.parametrize(
    "d",
    [
        pytest.param(2, marks=pytest.mark.slow),
        3,
        pytest.param(4, marks=pytest.mark.slow),
        pytest.param(5, marks=pytest.mark.slow),
        6,
    ],
)  # the sweep in d: slow
def test_stochastic_form_is_unbiased_within_three_standard_errors(d):
    metric = jaxgeom.hessian_metric(convex_landscape(d, d), 0.05)
    x = points(12, d, scale=1.0)
    exact = jaxgeom.metric_curvature(metric, x)
    z = []
    for seed in range(4):
        est, info = jaxgeom.metric_curvature(metric, x, probes=400, key=jax.random.key(seed), with_info=True)
        assert info.method == "hessian-stochastic" and np.all(info.standard_error > 0)
        z.append((est - exact) / info.standard_error)
    z = np.concatenate(z)
    assert np.all(np.abs(z) < 4.5) and np.mean(np.abs(z) < 3) >= 0.97
    assert abs(z.mean()) < 3 / np.sqrt(z.size)  # unbiased: the mean of 48 z-scores near 0


def test_stochastic_standard_error_falls_like_one_over_root_m():
    x = points(20, 5, scale=1.0)
    se = [
        np.median(
            jaxgeom.metric_curvature(fisher(), x, probes=m, key=jax.random.key(1), with_info=True)[1].standard_error
        )
        for m in (64, 1024)
    ]
    assert 3.0 < se[0] / se[1] < 5.5  # sqrt(16) = 4


def test_floor_active_walkers_take_the_christoffel_form_up_to_the_fallback_dimension():
    metric = jaxgeom.hessian_metric(double_well, 0.1)
    x = points(30, 3, scale=1.5)
    auto, info = jaxgeom.metric_curvature(metric, x, chunk=7, with_info=True)
    hessian_only = jaxgeom.metric_curvature(metric, x, method="hessian")
    reference = jaxgeom.metric_curvature(metric, x, method="christoffel")
    active = np.asarray(info.floor_active)
    assert 0 < active.sum() < len(active)
    assert np.all(np.isnan(hessian_only[active])) and np.all(np.isfinite(hessian_only[~active]))
    np.testing.assert_allclose(auto, reference, rtol=1e-8)
    soft = jaxgeom.hessian_metric(double_well, 0.1, floor="softabs")
    s, info = jaxgeom.metric_curvature(soft, x[:5], with_info=True)
    assert info.floor_active.all()
    np.testing.assert_allclose(s, jaxgeom.metric_curvature(soft, x[:5], method="christoffel"), rtol=1e-8)


def test_floor_active_walkers_are_flagged_above_the_fallback_dimension():
    d = CHRISTOFFEL_FALLBACK_MAX_DIM + 2
    x = jnp.zeros((3, d)).at[0, 0].set(2.0)  # walker 0 in a convex well, 1 and 2 on the saddle x_0 = 0
    s, info = jaxgeom.metric_curvature(jaxgeom.hessian_metric(double_well, 0.1), x, with_info=True)
    np.testing.assert_array_equal(info.floor_active, [False, True, True])
    assert np.isfinite(s[0]) and np.all(np.isnan(s[1:]))


def test_metrics_that_are_not_positive_definite_are_flagged_not_averaged():
    def metric(x):
        return jnp.diag(jnp.array([1.0, -1.0])) * (1 + x @ x)

    s, info = jaxgeom.metric_curvature(metric, points(3, 2), with_info=True)
    assert info.not_positive_definite.all() and np.all(np.isnan(s))


def test_chunks_do_not_change_the_result_and_float32_works():
    x = points(23, 3)
    full = jaxgeom.metric_curvature(sphere, x)
    np.testing.assert_allclose(jaxgeom.metric_curvature(sphere, x, chunk=5), full, rtol=1e-14)
    s32 = jaxgeom.metric_curvature(sphere, x.astype(jnp.float32))
    assert s32.dtype == jnp.float32
    np.testing.assert_allclose(s32, 6 / R**2, rtol=1e-3)
    jitted = jax.jit(lambda p: jaxgeom.metric_curvature(fisher(), p, probes=8, key=jax.random.key(0)))
    assert np.all(np.isfinite(jitted(x)))


def _not_traceable(x):
    return np.eye(x.shape[0]) * float(x[0])


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(metric=np.eye(2)), TypeError, "callable"),
        (dict(metric=lambda x: jnp.eye(3)), ValueError, r"\(2, 2\)"),
        (dict(metric=lambda x: jnp.eye(2, dtype=jnp.int32)), TypeError, "floating"),
        (dict(metric=lambda x: jnp.eye(2, dtype=jnp.complex64)), TypeError, "floating"),
        (dict(metric=_not_traceable), TypeError, "traceable"),
        (dict(points=np.array([[0.1, np.nan], [0.0, 0.2]])), ValueError, "NaN"),
        (dict(points=np.zeros(2)), ValueError, r"\(N, d\)"),
        (dict(points=np.zeros((2, 2), int)), TypeError, "float"),
        (dict(probes=0, key=jax.random.key(0)), ValueError, "probes"),
        (dict(probes=2.5, key=jax.random.key(0)), TypeError, "probes"),
        (dict(probes=4), ValueError, "key"),
        (dict(metric=sphere, probes=4, key=jax.random.key(0)), ValueError, "Hessian form"),
        (dict(method="exact"), ValueError, "christoffel"),
        (dict(metric=sphere, method="hessian"), ValueError, "hessian_metric"),
        (dict(chunk=0), ValueError, "chunk"),
    ],
)
def test_bad_input_is_refused_with_a_clear_message(kwargs, error, match, own_messages):
    args = dict(metric=fisher(0.1), points=points(2, 2)) | kwargs
    metric, pts = args.pop("metric"), args.pop("points")
    with pytest.raises(error, match=match):
        jaxgeom.metric_curvature(metric, pts, **args)


def test_the_metric_check_is_one_program_of_fixed_size_in_any_dimension():
    """The positive-definiteness and symmetry check every Christoffel walker runs: whole-array
    reductions, not one op per entry (d^2 ops took 40 s of XLA compile time at d = 35, 141 s
    of notebook 06's cell at d = 50)."""

    def ops(d):
        text = jax.jit(lambda g: metric_defect_masks(g, jnp)).lower(jnp.zeros((2, d, d))).as_text()
        return text.count(" = ")

    assert ops(50) == ops(5)
    g = np.tile(np.eye(50), (3, 1, 1))
    g[1, 3, 7] = 0.1  # asymmetric
    g[2, 9, 9] = -1.0  # indefinite
    asymmetric, indefinite = metric_defect_masks(jnp.asarray(g), jnp)
    np.testing.assert_array_equal(asymmetric, [False, True, False])
    np.testing.assert_array_equal(indefinite, [False, False, True])
