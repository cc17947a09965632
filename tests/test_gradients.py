"""The gradient audit (issue 45): every public differentiable function, and whole simulations
through `simulate(rebuild="callback")`, give finite gradients equal to central differences,
on landscapes whose Hessians are definite, indefinite and degenerate (repeated eigenvalues),
with both floors of the Hessian metric. The eigensolvers underneath are checked first.

Where a function cannot be differentiated (the clip floor at an eigenvalue exactly 0) the
gradient is the symmetric derivative, the mean of the one-sided ones: defined, never NaN.
The full grids of combinations are in the slow tier; the default tier runs one or two of each.
"""

import itertools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.base._simplex import small_eigh, spectral_function
from jaxgeom.geometry._metric import _clip_correction, _softabs
from jaxgeom.swarm._tuning import ignored_parameter

A3 = np.random.default_rng(0).normal(size=(3, 3))


def definite(x):
    """Hess V = 2 I + 0.2 (e0 e1^T + e1 e0^T) + 0.6 diag(x^2): positive definite everywhere."""
    return jnp.sum(x**2) + 0.2 * x[0] * x[1] + 0.05 * jnp.sum(x**4)


def indefinite(x):
    """The issue's landscape (3D) and its 2D restriction: Hess V indefinite almost everywhere."""
    d = x.shape[0]
    return jnp.sum(jnp.sin(jnp.asarray(A3[:d, :d], x.dtype) @ x)) + 0.3 * jnp.prod(x)


def degenerate(x):
    """The Mexican hat (|x|^2 - 1)^2 / 4: Hess V = (|x|^2 - 1) I + 2 x x^T has the eigenvalue
    |x|^2 - 1 d - 1 times everywhere; negative inside the unit sphere (the clip floor acts on a
    repeated eigenvalue), positive outside."""
    return 0.25 * (jnp.sum(x**2) - 1.0) ** 2


LANDSCAPES = {"definite": definite, "indefinite": indefinite, "degenerate": degenerate}


# --- the eigensolvers ---------------------------------------------------------------------------


def symmetric_matrices(rng, d, n=200):
    """Random symmetric matrices, then repeated spectra (random rotations of diag with equal
    entries), exactly diagonal and block-diagonal ones (exact zeros off the diagonal)."""
    a = rng.normal(size=(n, d, d))
    a = a + np.swapaxes(a, 1, 2)
    q = np.linalg.qr(rng.normal(size=(n, d, d)))[0]
    spectra = rng.normal(size=(n, d))
    spectra[: n // 2, 1:] = spectra[: n // 2, :1]  # one eigenvalue d times
    spectra[n // 2 :, 1] = spectra[n // 2 :, 0]  # a repeated pair
    spectra[::7, 0] = 0.0
    repeated = np.einsum("nij,nj,nkj->nik", q, spectra, q)
    diagonal = np.stack([np.diag(s) for s in spectra[:20]])
    block = a[:20].copy()
    block[:, 0, 1:] = block[:, 1:, 0] = 0.0
    return np.concatenate([a, repeated, diagonal, block, np.zeros((1, d, d)), np.eye(d)[None]])


def projectors(values, vectors, tol):
    """Q_c Q_c^T for each cluster of eigenvalues within `tol`: basis-independent eigenspaces."""
    out, start = [], 0
    for i in range(1, len(values) + 1):
        if i == len(values) or values[i] - values[i - 1] > tol:
            q = vectors[:, start:i]
            out.append((values[start], q @ q.T))
            start = i
    return out


@pytest.mark.parametrize("d", [2, 3, 4])
def test_small_eigh_matches_lapack_with_repeated_spectra_and_exact_zeros(rng, d):
    a = symmetric_matrices(rng, d)
    values, vectors = map(np.asarray, small_eigh(jnp.asarray(a)))
    ref_values, ref_vectors = np.linalg.eigh(a)
    np.testing.assert_allclose(values, ref_values, atol=1e-13 * max(1.0, np.abs(a).max()))
    for k in range(len(a)):
        ours = projectors(values[k], vectors[k], 1e-9)
        ref = projectors(ref_values[k], ref_vectors[k], 1e-9)
        assert len(ours) == len(ref)
        for (_, p), (_, p_ref) in zip(ours, ref, strict=True):  # the eigenvalues: compared above
            np.testing.assert_allclose(p, p_ref, atol=1e-9)


@pytest.mark.parametrize("d", [2, 3, 4])
def test_small_eigh_gradients_are_finite_and_exact_for_distinct_eigenvalues(rng, d):
    """d lambda_k / dA = q_k q_k^T (first-order perturbation theory), through the Jacobi sweeps
    (which read the upper triangle: the symmetric part of their derivative is compared)."""
    a = rng.normal(size=(60, d, d))
    a = jnp.asarray(a + np.swapaxes(a, 1, 2))
    jac = np.asarray(jax.vmap(jax.jacrev(lambda m: small_eigh(m)[0]))(a))
    assert np.isfinite(jac).all()
    jac = 0.5 * (jac + np.swapaxes(jac, -1, -2))
    _, q = np.linalg.eigh(np.asarray(a))
    expected = np.einsum("nik,njk->nkij", q, q)
    np.testing.assert_allclose(jac, expected, atol=1e-8)


def daleckii_krein(f, h, e, eps=1e-6):
    """d/dt f(h + t e) at t = 0 by central differences of the primal (numpy's eigh)."""

    def apply(m):
        lam, q = np.linalg.eigh(m)
        return (q * f(lam)) @ q.T

    return (apply(h + eps * e) - apply(h - eps * e)) / (2 * eps)


FLOORS = {
    "clip": (_clip_correction, lambda lam: np.maximum(-lam, 0.0)),
    "softabs": (_softabs, lambda lam: lam / np.tanh(lam / 0.1)),
}


@pytest.mark.parametrize("eigh", [small_eigh, jnp.linalg.eigh], ids=["jacobi", "lapack"])
@pytest.mark.parametrize("floor", list(FLOORS))
@pytest.mark.parametrize("d", [2, 3, 4])
def test_floor_derivatives_are_right_at_repeated_eigenvalues(rng, eigh, floor, d):
    """The floors' derivative (Daleckii-Krein) against central differences of the floor itself, on
    repeated and nearly repeated spectra away from the clip kink, in random directions. Through the
    eigenvectors this is 0/0: an exact repeat missed the off-diagonal part of the direction."""
    fn, reference = FLOORS[floor]
    q = np.linalg.qr(rng.normal(size=(d, d)))[0]
    for spectrum in (
        [-1.0] * d,
        [-1.0, -1.0 + 1e-9] + [0.7] * (d - 2),
        [-0.5] + [2.0] * (d - 1),
        [-2.0, 1e-12 - 2.0] + list(rng.uniform(0.3, 3.0, d - 2)),
    ):
        h = (q * np.asarray(spectrum)) @ q.T
        e = rng.normal(size=(d, d))
        e = e + e.T
        p = jnp.asarray(0.0 if floor == "clip" else 0.1)
        _, tangent = jax.jvp(lambda m: spectral_function(fn, eigh, m, p), (jnp.asarray(h),), (jnp.asarray(e),))
        np.testing.assert_allclose(np.asarray(tangent), daleckii_krein(reference, h, e), atol=1e-7)


@pytest.mark.slow
@pytest.mark.parametrize("floor", list(FLOORS))
def test_floor_higher_derivatives_are_right_at_repeated_eigenvalues(rng, floor):
    """Second and third derivatives (in h and in eps_Sigma), which `metric_curvature` and its
    gradient take, against central differences of the derivative one order below, on a
    spectrum with a repeated eigenvalue (the Mexican hat's Hessian has one everywhere)."""
    fn, _ = FLOORS[floor]
    d = 3
    q = np.linalg.qr(rng.normal(size=(d, d)))[0]
    h0 = jnp.asarray((q * np.asarray([-0.8, -0.8, 1.3])) @ q.T)
    e = [jnp.asarray(m + m.T) for m in rng.normal(size=(3, d, d))]
    p0 = jnp.asarray(0.0 if floor == "clip" else 0.1)

    def f(t):  # F along h0 + t0 e0 + t1 e1 + t2 e2, and eps_Sigma + t3 (softabs)
        return spectral_function(fn, small_eigh, h0 + t[0] * e[0] + t[1] * e[1] + t[2] * e[2], p0 + t[3])

    first = jax.jit(jax.jacfwd(f))
    second = jax.jit(jax.jacfwd(jax.jacfwd(f)))
    third = jax.jacfwd(second)(jnp.zeros(4))
    t0, step = jnp.zeros(4), 1e-4
    for a in range(4):
        u = jnp.zeros(4).at[a].set(step)
        fd2 = (first(t0 + u) - first(t0 - u)) / (2 * step)
        np.testing.assert_allclose(np.asarray(second(t0)[..., a]), np.asarray(fd2), atol=1e-6)
        fd3 = (second(t0 + u) - second(t0 - u)) / (2 * step)
        # the reference, not the derivative, limits this: the split of the repeated eigenvalue at
        # t = +-step puts second divided differences at the edge of their Taylor window
        np.testing.assert_allclose(np.asarray(third[..., a]), np.asarray(fd3), atol=2e-5 * np.abs(third).max())


def test_clip_floor_at_its_kink_gives_the_symmetric_derivative():
    """At an eigenvalue exactly 0 the clip floor has one-sided derivatives 1 (H) and 0 (H + its
    correction): the derivative is their mean, 1/2, which is what central differences measure."""

    def floored(m):
        return m + spectral_function(_clip_correction, small_eigh, m, jnp.asarray(0.0))

    h0, e = jnp.diag(jnp.asarray([2.0, 0.0])), jnp.diag(jnp.asarray([0.0, 1.0]))
    _, tangent = jax.jvp(floored, (h0,), (e,))
    fd = (floored(h0 + 1e-6 * e) - floored(h0 - 1e-6 * e)) / 2e-6
    np.testing.assert_allclose(np.asarray(tangent), 0.5 * np.asarray(e))
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(fd), atol=1e-9)
    metric = jaxgeom.hessian_metric(lambda x: x[0] ** 2 + x[0] * x[1] ** 3, 0.1)  # Hess V singular on x1 = 0
    assert np.isfinite(np.asarray(jax.jacfwd(metric)(jnp.asarray([0.3, 0.0])))).all()


@pytest.mark.parametrize("floor", ["clip", "softabs"])
def test_hessian_metric_position_gradient_equals_central_differences(floor):
    """The issue's 200 points: 195 of them, where the 3 x 3 Hessian is indefinite, gave NaN."""
    metric = jaxgeom.hessian_metric(indefinite, 0.1, floor=floor)
    loss = jax.jit(jax.vmap(lambda y: jnp.sum(metric(y) ** 2)))
    x = np.random.default_rng(1).uniform(-2, 2, (200, 3))
    g = np.asarray(jax.jit(jax.vmap(jax.grad(lambda y: jnp.sum(metric(y) ** 2))))(x))
    h = 1e-6
    fd = np.stack([(loss(x + h * e) - loss(x - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
    assert np.isfinite(g).all()
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max())


def test_hessian_metric_float32_gradient_matches_float64():
    metric = jaxgeom.hessian_metric(indefinite, 0.1)
    grad = jax.jit(jax.vmap(jax.grad(lambda y: jnp.sum(metric(y) ** 2))))
    x = np.random.default_rng(2).uniform(-2, 2, (200, 3))
    g32, g64 = np.asarray(grad(x.astype(np.float32))), np.asarray(grad(x))
    assert g32.dtype == np.float32 and np.isfinite(g32).all()
    np.testing.assert_allclose(g32, g64, rtol=2e-3, atol=2e-3 * np.abs(g64).max())


# --- the public kernels ---------------------------------------------------------------------------


def velocities(points):
    return jnp.asarray(np.random.default_rng(7).normal(size=points.shape), points.dtype)


KERNELS = {  # name: (kernel(tess, metric) -> array, takes a metric, works on a k-NN graph)
    "voronoi_volumes": (lambda t, m: jaxgeom.voronoi_volumes(t), False, False),
    "circumcenters": (lambda t, m: jaxgeom.circumcenters(t), False, False),
    "edge_lengths": (lambda t, m: jaxgeom.edge_lengths(t, metric=m), True, True),
    "metric_at_walkers": (lambda t, m: jaxgeom.metric_at_walkers(t, m), True, True),
    "riemannian_volumes": (lambda t, m: jaxgeom.riemannian_volumes(t, metric=m), True, False),
    "angle_sums": (lambda t, m: jaxgeom.angle_sums(t, metric=m), True, False),
    "deficit_angles": (lambda t, m: jaxgeom.deficit_angles(t, metric=m), True, False),
    "ricci_scalar": (lambda t, m: jaxgeom.ricci_scalar(t, metric=m), True, False),
    "metric_curvature": (lambda t, m: jaxgeom.metric_curvature(m, t.points), True, True),
    **{
        f"viscous_force[{w}]": (
            (
                lambda w: (
                    lambda t, m: jaxgeom.viscous_force(
                        t, velocities(t.points), nu=0.3, weights=w, metric=m if w.startswith("metric") else None
                    )
                )
            )(w),
            w.startswith("metric"),
            True,
        )
        for w in jaxgeom.VISCOUS_WEIGHTS
    },
    "emergent_metric": (lambda t, m: jaxgeom.emergent_metric(t), False, True),
    "shape_distortion": (lambda t, m: jaxgeom.shape_distortion(t), False, False),
    "vertex_distance_variance": (lambda t, m: jaxgeom.vertex_distance_variance(t), False, False),
    "volume_distortion": (lambda t, m: jaxgeom.volume_distortion(t), False, False),
    "estimate_gradient": (lambda t, m: jaxgeom.estimate_gradient(t, jax.vmap(definite)(t.points)), False, True),
    "estimate_hessian": (lambda t, m: jaxgeom.estimate_hessian(t, jax.vmap(indefinite)(t.points)), False, True),
    "geometric_hessian": (lambda t, m: jaxgeom.geometric_hessian(t, 0.1), False, True),
    "geodesic_distances": (lambda t, m: jaxgeom.geodesic_distances(t, [0, 5], m), True, False),
    "ollivier_ricci": (lambda t, m: jaxgeom.ollivier_ricci(t, metric=m).edge_curvature, True, True),
}


def swarm_points(d, n=None):
    n = n or (60 if d == 2 else 80)
    return np.random.default_rng(3).uniform(-1.2, 1.2, (n, d))


def graph(kind, d):
    x = swarm_points(d)
    if kind == "knn":
        return jaxgeom.knn_graph(x, 8)
    return jaxgeom.delaunay(x, box=(-1.5, 1.5))


def kernel_loss(name, kind, d, floor, landscape, dtype=np.float64):
    """(loss(x, eps), x0, eps0): sum_i w_i out_i with w fixed and random and the entries
    finite at x0, a function of the positions (on a fixed graph) and of eps_Sigma."""
    kernel, takes_metric, _ = KERNELS[name]
    tess = graph(kind, d)
    tess = eqx.tree_at(lambda t: t.points, tess, tess.points.astype(dtype))
    fitness = LANDSCAPES[landscape]

    def output(x, eps):
        moved = eqx.tree_at(lambda t: t.points, tess, x)
        metric = jaxgeom.hessian_metric(fitness, eps, floor=floor) if takes_metric else None
        return kernel(moved, metric)

    x0, eps0 = tess.points, jnp.asarray(0.1, dtype)
    base = np.asarray(output(x0, eps0))
    finite = jnp.asarray(np.isfinite(base))
    weights = jnp.asarray(np.random.default_rng(4).normal(size=base.shape), dtype)
    return jax.jit(lambda x, e: jnp.sum(jnp.where(finite, weights * output(x, e), 0.0))), x0, eps0


def kernel_gradients(loss, x0, eps0):
    gx, ge = map(np.asarray, jax.jit(jax.grad(loss, argnums=(0, 1)))(x0, eps0))
    assert np.isfinite(gx).all() and np.isfinite(ge).all(), "a gradient is not finite"
    return gx, ge


def check_kernel_gradients(name, kind, d, floor, landscape):
    """d/dx (3 random directions) and d/d eps_Sigma against central differences."""
    loss, x0, eps0 = kernel_loss(name, kind, d, floor, landscape)
    gx, ge = kernel_gradients(loss, x0, eps0)
    rng, h = np.random.default_rng(5), 1e-6
    scale = np.abs(gx).sum()
    for _ in range(3):
        u = jnp.asarray(rng.normal(size=x0.shape))
        fd = (loss(x0 + h * u, eps0) - loss(x0 - h * u, eps0)) / (2 * h)
        np.testing.assert_allclose(np.sum(gx * np.asarray(u)), fd, rtol=1e-5, atol=1e-7 * scale)
    fd = (loss(x0, eps0 + h * 0.1) - loss(x0, eps0 - h * 0.1)) / (2 * h * 0.1)
    np.testing.assert_allclose(ge, fd, rtol=1e-5, atol=1e-7 * (abs(fd) + scale))
    if not KERNELS[name][1]:
        assert ge == 0.0


# The default tier: each cheap kernel once, the metric kernels whose lengths failed in the issue's
# case (3D, clip floor, indefinite Hessians), and a k-NN graph with the softabs floor on repeated
# eigenvalues. The curvature kernels (tens of seconds to compile their gradients in 3D) and
# ollivier_ricci (its own module checks its gradients) run in the slow tier.
HEAVY = (
    "ricci_scalar",
    "deficit_angles",
    "angle_sums",
    "riemannian_volumes",
    "geodesic_distances",
    "metric_curvature",
    "ollivier_ricci",
)
DEFAULT_KERNEL_CASES = [
    (name, "delaunay", 3 if KERNELS[name][1] else 2, "clip", "indefinite") for name in KERNELS if name not in HEAVY
]
DEFAULT_KERNEL_CASES += [
    (name, "knn", 3, "softabs", "degenerate")
    for name in ("viscous_force[metric_full]", "estimate_hessian", "edge_lengths")
]
# The slow tier: with the default case, every metric kernel sees each floor, each landscape and
# both dimensions (and a k-NN graph where it takes one); the others both dimensions and graphs.
METRIC_ROWS = [
    ("delaunay", 2, "clip", "definite"),
    ("knn", 3, "softabs", "indefinite"),
    ("delaunay", 2, "softabs", "degenerate"),
]
SLOW_KERNEL_CASES = [
    (name, kind if KERNELS[name][2] else "delaunay", d, floor, landscape)
    for name in KERNELS
    if KERNELS[name][1]
    for kind, d, floor, landscape in METRIC_ROWS
]
SLOW_KERNEL_CASES += [
    (name, kind, 3, "clip", "indefinite")
    for name in KERNELS
    if not KERNELS[name][1]
    for kind in (("delaunay", "knn") if KERNELS[name][2] else ("delaunay",))
]
SLOW_KERNEL_CASES += [(name, "delaunay", 3, "clip", "indefinite") for name in HEAVY]
SLOW_KERNEL_CASES = [case for case in dict.fromkeys(SLOW_KERNEL_CASES) if case not in DEFAULT_KERNEL_CASES]


@pytest.mark.parametrize("name, kind, d, floor, landscape", DEFAULT_KERNEL_CASES)
def test_kernel_gradients_equal_central_differences(name, kind, d, floor, landscape):
    check_kernel_gradients(name, kind, d, floor, landscape)


@pytest.mark.slow
@pytest.mark.parametrize("name, kind, d, floor, landscape", SLOW_KERNEL_CASES)
def test_kernel_gradients_on_every_floor_and_landscape(name, kind, d, floor, landscape):
    check_kernel_gradients(name, kind, d, floor, landscape)


@pytest.mark.parametrize(
    "name", ["viscous_force[metric_full]", "edge_lengths", pytest.param("metric_curvature", marks=pytest.mark.slow)]
)
def test_kernel_gradients_in_float32_match_float64(name):
    """float32 central differences cannot resolve these; the float64 gradient can."""
    g32 = kernel_gradients(*kernel_loss(name, "delaunay", 3, "clip", "indefinite", np.float32))
    g64 = kernel_gradients(*kernel_loss(name, "delaunay", 3, "clip", "indefinite"))
    for a, b in zip(g32, g64, strict=True):
        assert a.dtype == np.float32
        np.testing.assert_allclose(a, b, rtol=1e-2, atol=1e-2 * np.abs(b).max())


# --- whole simulations ----------------------------------------------------------------------------

FIVE = ("nu", "eps_sigma", "dt", "gamma", "temperature")

# Every pair of values of any two factors appears in some row (checked below): weight rule,
# noise, graph, dimension, floor, landscape. All five parameters are tuned in every row.
SIMULATION_GRID = [
    ("inverse_distance", "aniso", "delaunay", 2, "softabs", "definite"),
    ("inverse_distance", "aniso", "knn", 3, "clip", "indefinite"),
    ("inverse_distance", "iso", "knn", 3, "clip", "degenerate"),
    ("kernel", "aniso", "delaunay", 3, "clip", "indefinite"),
    ("kernel", "aniso", "knn", 2, "softabs", "degenerate"),
    ("kernel", "iso", "delaunay", 3, "softabs", "definite"),
    ("metric_diagonal", "aniso", "knn", 2, "clip", "definite"),
    ("metric_diagonal", "iso", "delaunay", 3, "softabs", "indefinite"),
    ("metric_diagonal", "iso", "knn", 3, "clip", "degenerate"),
    ("metric_full", "aniso", "delaunay", 2, "softabs", "indefinite"),
    ("metric_full", "aniso", "knn", 2, "clip", "degenerate"),
    ("metric_full", "iso", "knn", 3, "clip", "definite"),
    ("uniform", "aniso", "delaunay", 3, "softabs", "degenerate"),
    ("uniform", "iso", "knn", 2, "clip", "definite"),
    ("uniform", "iso", "knn", 2, "clip", "indefinite"),
]
# the example: 3D, clip, indefinite, metric weights (its anisotropic twin: slow tier)
DEFAULT_SIMULATIONS = [("metric_full", "iso", "delaunay", 3, "clip", "indefinite")]


def test_simulation_grid_covers_every_pair_of_factors():
    levels = [
        jaxgeom.VISCOUS_WEIGHTS,
        ("iso", "aniso"),
        ("delaunay", "knn"),
        (2, 3),
        ("clip", "softabs"),
        tuple(LANDSCAPES),
    ]
    for (a, la), (b, lb) in itertools.combinations(enumerate(levels), 2):
        missing = {(u, v) for u in la for v in lb} - {(row[a], row[b]) for row in SIMULATION_GRID}
        assert not missing, f"factors {a} and {b}: {missing} not covered"


def simulation_loss(weights, noise, kind, d, floor, landscape, dtype=np.float64, n_steps=4):
    fitness = LANDSCAPES[landscape]
    x0 = np.random.default_rng(1).uniform(-1.5, 1.5, (40 if d == 2 else 60, d)).astype(dtype)
    state = jaxgeom.init_swarm(fitness, x0, key=0, graph=kind, k=8)
    params = jaxgeom.SwarmParams(
        dt=0.02,
        temperature=0.3,
        gamma=1.0,
        nu=0.3,
        eps_sigma=0.1,
        weights=weights,
        anisotropic=noise == "aniso",
        floor=floor,
        cloning=False,
    )
    tuned = tuple(name for name in FIVE if not ignored_parameter(name, params, ("mean_fitness",)))
    return jaxgeom.simulation_loss(fitness, state, "mean_fitness", n_steps=n_steps, params=params, tuned=tuned)


def loss_gradient(loss, theta):
    return np.asarray(eqx.filter_jit(lambda l, t: jax.grad(l)(t))(loss, theta))


def check_simulation_gradient(*row):
    loss = simulation_loss(*row)
    theta = loss.to_theta()
    g = loss_gradient(loss, theta)
    h, p = 1e-5, len(loss.tuned)  # no Delaunay flip inside (checked: the same value at h and h / 10 to 1e-4)
    steps = np.concatenate([np.eye(p) * h, -np.eye(p) * h])
    values = np.asarray(eqx.filter_jit(lambda l, t: jax.vmap(l)(t))(loss, theta[None] + steps))
    fd = (values[:p] - values[p:]) / (2 * h)
    assert np.isfinite(g).all(), f"{row}: gradient {g}"
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


@pytest.mark.parametrize("row", DEFAULT_SIMULATIONS, ids=str)
def test_simulation_gradients_equal_central_differences(row):
    check_simulation_gradient(*row)


@pytest.mark.slow
@pytest.mark.parametrize("row", SIMULATION_GRID + [("kernel", "aniso", "delaunay", 3, "clip", "indefinite")], ids=str)
def test_simulation_gradients_over_the_grid(row):
    check_simulation_gradient(*row)


@pytest.mark.slow
def test_simulation_gradient_in_float32_equals_central_differences():
    """float32 draws other random numbers than float64 (another run), so its gradient is checked
    against its own central differences, with a step float32 resolves (1% in each parameter)."""
    loss = simulation_loss("metric_full", "aniso", "delaunay", 3, "clip", "indefinite", dtype=np.float32)
    theta = loss.to_theta()
    g = loss_gradient(loss, theta)
    h, p = 1e-2, len(loss.tuned)
    steps = np.concatenate([np.eye(p) * h, -np.eye(p) * h]).astype(np.float32)
    values = np.asarray(eqx.filter_jit(lambda l, t: jax.vmap(l)(t))(loss, theta[None] + steps), np.float64)
    fd = (values[:p] - values[p:]) / (2 * h)
    assert g.dtype == np.float32 and np.isfinite(g).all()
    np.testing.assert_allclose(g, fd, rtol=2e-2, atol=2e-3 * np.abs(fd).max())


@pytest.mark.parametrize(
    "weights, noise, floor",
    [("metric_full", "iso", "clip"), pytest.param("kernel", "aniso", "softabs", marks=pytest.mark.slow)],
)
def test_no_nan_anywhere_in_a_gradient_through_simulate(weights, noise, floor):
    """Under jax.debug_nans every primitive's output is checked: a state that carried NaN as a
    marker (unbounded cells' volumes), or a NaN the gradient later masked, would raise."""
    loss = simulation_loss(weights, noise, "delaunay", 3, floor, "indefinite", n_steps=2)
    theta = loss.to_theta()
    with jax.debug_nans(True):
        g = np.asarray(jax.grad(loss)(theta))
    assert np.isfinite(g).all()
