"""Every bad argument gets a clear error naming it and the fix (issue 13)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.cli import main


@pytest.fixture(scope="module")
def tess():
    return jaxgeom.delaunay(np.random.default_rng(0).random((200, 2)))


def bowl(x):
    return jnp.sum(x**2)


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        (dict(dt=float("inf")), ValueError, r"`dt` must be a finite number > 0; got inf"),
        (dict(clone_rate=2), ValueError, r"`clone_rate` must be a finite number >= 0 and <= 1"),
        (dict(reward_power=float("nan")), ValueError, r"`reward_power` must be a finite number >= 0; got nan"),
        (dict(distance_power=-1), ValueError, r"`distance_power` must be a finite number >= 0; got -1"),
        (dict(clone_jitter=float("inf")), ValueError, r"`clone_jitter` must be a finite number > 0"),
        (dict(dt=[0.1, 0.2]), ValueError, r"`dt` must be a scalar; got shape \(2,\).*jax.vmap"),
        (dict(nu="0.1"), TypeError, r"`nu` must be numeric; got str"),
        (dict(nu=np.ones((2, 2))), ValueError, r"`nu` must be a scalar"),
        (dict(temperature=1j), TypeError, r"`temperature` must be real; got complex"),
        (dict(gamma=[[1.0], [2.0, 3.0]]), TypeError, r"`gamma` must be a rectangular numeric array"),
    ],
)
def test_swarm_params_refuse_bad_values(kwargs, error, message):
    with pytest.raises(error, match=message):
        jaxgeom.SwarmParams(**kwargs)


def test_swarm_params_stay_differentiable_and_vmappable():
    assert float(jax.grad(lambda nu: jaxgeom.SwarmParams(nu=nu).nu * 3.0)(1.0)) == 3.0
    dts = jax.vmap(lambda dt: jaxgeom.SwarmParams(dt=dt).dt)(jnp.asarray([0.1, 0.2]))
    np.testing.assert_allclose(np.asarray(dts), [0.1, 0.2])


@pytest.mark.parametrize("eps", [float("nan"), float("inf"), -0.1])
def test_metric_floors_must_be_finite_and_nonnegative(tess, eps):
    with pytest.raises(ValueError, match="`eps_sigma` must be a finite number >= 0"):
        jaxgeom.hessian_metric(bowl, eps)
    with pytest.raises(ValueError, match="`eps_reg` must be a finite number >= 0"):
        jaxgeom.emergent_metric(tess, eps_reg=eps)


def test_kernel_factors_and_lobpcg_block_size(tess):
    v = np.zeros((200, 2))
    with pytest.raises(ValueError, match="`alpha` must be a finite number > 0"):
        jaxgeom.viscous_force(tess, v, nu=0.1, alpha=0)
    with pytest.raises(ValueError, match="`alpha` must be a finite number > 0"):
        jaxgeom.spectral_gap(tess, alpha=-1)
    with pytest.raises(ValueError, match=r"method='lobpcg' needs 5 \(k - 1\) < N = 200; got k=150. Use k <= 40"):
        jaxgeom.spectral_gap(tess, k=150, method="lobpcg")


@pytest.mark.parametrize("key", ["abc", 1.5, True, np.zeros(3)])
def test_init_swarm_refuses_a_key_that_is_no_key(key):
    x = np.random.default_rng(1).random((30, 2))
    with pytest.raises(TypeError, match=r"`key` must be an int seed or a jax.random key"):
        jaxgeom.init_swarm(bowl, x, key=key)


def test_init_swarm_refuses_non_finite_or_complex_velocities():
    x = np.random.default_rng(1).random((30, 2))
    v = np.zeros_like(x)
    v[4, 1] = np.nan
    with pytest.raises(ValueError, match=r"`velocities` has NaN or inf entries in 1 row"):
        jaxgeom.init_swarm(bowl, x, v)
    with pytest.raises(TypeError, match="`velocities` must be real"):
        jaxgeom.init_swarm(bowl, x, v.astype(complex))


def test_kernels_take_a_tessellation_and_a_metric_of_the_right_kind(tess):
    with pytest.raises(TypeError, match=r"jaxgeom.voronoi_volumes takes a jaxgeom.Tessellation .* got ndarray"):
        jaxgeom.voronoi_volumes(np.asarray(tess.points))
    with pytest.raises(TypeError, match=r"jaxgeom.ricci_scalar takes a jaxgeom.Tessellation"):
        jaxgeom.ricci_scalar([[0.0, 1.0]])
    with pytest.raises(TypeError, match=r"got the string 'euclidean'. For the Euclidean metric pass metric=None"):
        jaxgeom.ricci_scalar(tess, metric="euclidean")


def test_box_and_ragged_points_are_refused_clearly():
    x = np.random.default_rng(2).random((30, 2))
    with pytest.raises(TypeError, match=r"`box` must be \(lower, upper\) .* got the string 'unit'"):
        jaxgeom.delaunay(x, box="unit")
    with pytest.raises(TypeError, match=r"`points` must be a rectangular \(N, d\) array; got a ragged sequence"):
        jaxgeom.delaunay([[0.0, 1.0], [1.0], [2.0, 3.0]])
    with pytest.raises(TypeError, match=r"`box` must be a rectangular numeric array"):
        jaxgeom.delaunay(x, box=[[0.0, 0.0], [1.0]])


def metric_calls(tess, g):
    v = np.zeros((tess.n_points, 2))
    return [
        lambda: jaxgeom.ricci_scalar(tess, metric=g),
        lambda: jaxgeom.edge_lengths(tess, metric=g),
        lambda: jaxgeom.viscous_force(tess, v, nu=0.1, weights="metric_full", metric=g),
        lambda: jaxgeom.geodesic_distances(tess, 0, metric=g),
        lambda: jaxgeom.riemannian_volumes(tess, metric=g),
    ]


@pytest.mark.parametrize("call", range(5))
def test_metric_arrays_must_be_symmetric_positive_definite_and_real(tess, call):
    eye = np.tile(np.eye(2), (200, 1, 1))
    skew = eye.copy()
    skew[7, 0, 1] = 0.3
    with pytest.raises(ValueError, match=r"`metric` must be symmetric; 1 walker\(s\) are not, first rows \[7\]"):
        metric_calls(tess, skew)[call]()
    indefinite = eye.copy()
    indefinite[[3, 9], 1, 1] = -1.0
    with pytest.raises(ValueError, match=r"`metric` must be positive definite; 2 walker\(s\) .* first rows \[3, 9\]"):
        metric_calls(tess, indefinite)[call]()
    with pytest.raises(TypeError, match="`metric` must be real; got complex"):
        metric_calls(tess, eye.astype(complex))[call]()


@pytest.mark.parametrize("d", [2, 4])
def test_metric_defects_flags_the_walkers_where_a_callable_is_not_a_metric(d):
    x = np.random.default_rng(1).random((120, d))
    tess = jaxgeom.knn_graph(x, 6)

    def saddle_left(p):  # indefinite where p[0] < 0.5
        return jnp.diag(jnp.ones(d).at[-1].set(p[0] - 0.5))

    def sheared(p):  # not symmetric where p[1] > 0.7
        return jnp.eye(d).at[0, 1].set(jnp.where(p[1] > 0.7, 0.3, 0.0))

    np.testing.assert_array_equal(jaxgeom.metric_defects(tess, saddle_left), x[:, 0] <= 0.5)
    np.testing.assert_array_equal(jaxgeom.metric_defects(tess, sheared), x[:, 1] > 0.7)
    assert not jaxgeom.metric_defects(tess, jaxgeom.hessian_metric(bowl, 0.1)).any()
    assert not jaxgeom.metric_defects(tess, None).any()
    flags = jax.jit(jaxgeom.metric_defects, static_argnums=1)(tess, saddle_left)
    np.testing.assert_array_equal(flags, x[:, 0] <= 0.5)
    # The kernels take the callable as given: a negative definite one gives NaN lengths.
    lengths = np.asarray(jaxgeom.edge_lengths(tess, metric=lambda p: saddle_left(p) - 2 * jnp.eye(d)))
    assert np.isnan(lengths[np.asarray(tess.neighbor_mask)]).all()


@pytest.mark.parametrize("estimate", [jaxgeom.estimate_gradient, jaxgeom.estimate_hessian])
def test_estimates_refuse_values_of_the_wrong_shape_or_kind(tess, estimate):
    with pytest.raises(
        ValueError, match=r"`values` must have shape \(200,\), one entry per walker of `tess`; got \(199,\)"
    ):
        estimate(tess, np.zeros(199))
    with pytest.raises(
        ValueError, match=r"`values` must have shape \(200,\), one entry per walker of `tess`; got \(200, 2\)"
    ):
        estimate(tess, np.zeros((200, 2)))
    with pytest.raises(TypeError, match="`values` must be real; got complex"):
        estimate(tess, np.zeros(200, complex))


def test_viscous_velocities_must_be_real_and_per_walker(tess):
    with pytest.raises(TypeError, match="`velocities` must be real"):
        jaxgeom.viscous_force(tess, np.zeros((200, 2), complex), nu=0.1)
    with pytest.raises(ValueError, match=r"`velocities` must have shape \(200, 2\)"):
        jaxgeom.viscous_force(tess, np.zeros((200, 3)), nu=0.1)
    with pytest.raises(ValueError, match=r"`velocities` must have shape \(200, 2\).*got \(199, 2\)"):
        jax.jit(lambda v: jaxgeom.viscous_force(tess, v, nu=0.1))(np.zeros((199, 2)))  # shapes are static


def test_a_tiny_kernel_width_tends_to_nearest_neighbour_weighting(tess):
    """l -> 0: the row-normalised kernel weights keep only each walker's nearest neighbour
    (they used to underflow to 0 / 0 and the force vanished)."""
    x = np.asarray(tess.points)
    v = np.random.default_rng(3).normal(size=(200, 2))
    nbrs = np.asarray(tess.neighbors)
    dist = np.where(nbrs < 200, np.linalg.norm(x[np.minimum(nbrs, 199)] - x[:, None], axis=2), np.inf)
    nearest = nbrs[np.arange(200), dist.argmin(axis=1)]
    force = np.asarray(jaxgeom.viscous_force(tess, v, nu=2.0, length_scale=1e-30))
    np.testing.assert_allclose(force, 2.0 * (v[nearest] - v), rtol=1e-12, atol=1e-12)
    wide = np.asarray(jaxgeom.viscous_force(tess, v, nu=2.0, length_scale=0.05))
    w = np.where(nbrs < 200, np.exp(-(dist**2) / (2 * 0.05**2)), 0.0)  # the unshifted kernel
    v_pad = np.vstack([v, np.zeros((1, 2))])
    reference = 2.0 * ((w[:, :, None] * (v_pad[nbrs] - v[:, None])).sum(1) / w.sum(1)[:, None])
    np.testing.assert_allclose(wide, reference, rtol=1e-10, atol=1e-12)


def test_a_kernel_graph_that_underflows_says_so(tess):
    with pytest.warns(UserWarning, match=r"edge\(s\) of the kernel graph have weight 0"):
        gaps = np.asarray(jaxgeom.spectral_gap(tess, length_scale=1e-30, k=3))
    assert np.allclose(gaps, 0.0)  # the graph has fallen apart: 0 is the true limit, now announced


@pytest.fixture
def files(tmp_path):
    (tmp_path / "syntax.py").write_text("def V(x)\n    return 1\n")
    for name, box in (("inverted.py", "(3, -3)"), ("scalar.py", "5")):
        (tmp_path / name).write_text(f"import jax.numpy as jnp\nBOX = {box}\n\ndef V(x):\n    return jnp.sum(x**2)\n")
    np.save(tmp_path / "flat.npy", np.arange(10.0))
    np.save(tmp_path / "ints.npy", np.zeros((5, 2), int))
    (tmp_path / "points.txt").write_text("1 2\n3 4\n")
    (tmp_path / "a_file").write_text("")
    return tmp_path


@pytest.mark.parametrize(
    "argv, message",
    [
        (["simulate", "--landscape", "{}/syntax.py"], "could not be loaded: SyntaxError"),
        (["simulate", "--landscape", "{}/inverted.py"], r"BOX in .* must satisfy lower < upper"),
        (["simulate", "--landscape", "{}/scalar.py"], r"BOX in .* must be \(lower, upper\), two numbers; got 5"),
        (["analyze", "--points", "{}/flat.npy", "--periodic"], r"--points must hold an \(N, d\) float array"),
        (["analyze", "--points", "{}/flat.npy", "--box", "0", "1"], r"--points must hold an \(N, d\) float array"),
        (["analyze", "--points", "{}/ints.npy"], r"holds shape \(5, 2\), dtype int64"),
        (["analyze", "--points", "{}/points.txt"], r"--points must be a .npy file written by numpy.save"),
    ],
)
def test_cli_input_files_fail_with_one_line_and_exit_2(files, capsys, argv, message):
    argv = [a.format(files) for a in argv]
    if argv[0] == "simulate":
        argv += ["--n", "20", "--steps", "1", "--no-progress"]  # the CLI sets x64 for the process
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert re.search(message, err)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["analyze", "--seed", "-1"], "--seed must be a finite number >= 0"),
        (["analyze", "--n", "0"], "--n must be a finite number >= 1"),
        (["simulate", "--eps-sigma", "nan"], "--eps-sigma must be a finite number >= 0.0; got nan"),
        (["simulate", "--clone-rate", "5"], "--clone-rate must be a finite number >= 0.0 and <= 1.0"),
        (["simulate", "--gap-every", "-2"], "--gap-every must be a finite number >= 0"),
        (["simulate", "--nu", "-1"], "--nu must be a finite number >= 0.0"),
        (["analyze", "--out", "{}/a_file"], "is an existing file; give a directory"),
        (["analyze", "--out", "{}/a_file/sub"], "cannot be created"),
    ],
)
def test_cli_refuses_bad_numbers_and_outputs_before_any_work(files, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main([a.format(files) for a in argv])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_traced_knn_gives_non_finite_walkers_no_neighbours_and_wraps_periodic_ones():
    x = np.random.default_rng(4).random((100, 2))
    x[7] = np.nan
    graph = jax.jit(lambda p: jaxgeom.knn_graph(p, 6, method="brute"))(jnp.asarray(x))
    nbrs = np.asarray(graph.neighbors)
    assert (nbrs[7] == 100).all() and not (nbrs == 7).any() and int(graph.degree[7]) == 0
    others = np.delete(np.arange(100), 7)
    host = jaxgeom.knn_graph(x[others], 6)  # the same graph without the NaN walker
    np.testing.assert_array_equal(others[np.asarray(host.neighbors)], nbrs[others])
    p = np.random.default_rng(5).random((100, 2))
    knn = jax.jit(lambda q: jaxgeom.knn_graph(q, 6, box=(0.0, 1.0), periodic=True, method="brute"))
    np.testing.assert_array_equal(
        np.sort(np.asarray(knn(jnp.asarray(p)).neighbors), 1),
        np.sort(np.asarray(knn(jnp.asarray(p + [1.0, -2.0])).neighbors), 1),
    )


def test_bellman_ford_sources_outside_the_walkers(tess):
    with pytest.raises(ValueError, match=r"`sources` must lie in \[0, N\) = \[0, 200\)"):
        jaxgeom.geodesic_distances(tess, [3, 200], method="bellman_ford")
    rows = jax.jit(lambda s: jaxgeom.geodesic_distances(tess, s, method="bellman_ford"))(jnp.asarray([250, -1, 3]))
    rows = np.asarray(rows)
    assert np.isinf(rows[:2]).all() and np.isfinite(rows[2]).all() and rows[2, 3] == 0.0


def test_a_checked_jax_metric_is_not_checked_again(tess, monkeypatch):
    import jaxgeom.base._checks as checks

    g = jnp.asarray(np.tile(np.eye(2), (200, 1, 1)))
    jaxgeom.riemannian_volumes(tess, metric=g)
    monkeypatch.setattr(checks, "_positive_definite", lambda *a: pytest.fail("checked twice"))
    jaxgeom.ricci_scalar(tess, metric=g)  # the same immutable array: no second O(N) check
    with pytest.raises(pytest.fail.Exception, match="checked twice"):
        jaxgeom.ricci_scalar(tess, metric=np.asarray(g))  # numpy arrays can change: checked every call


def test_edge_weights_refuse_an_unknown_rule_instead_of_returning_inverse_distances(tess):
    with pytest.raises(
        ValueError,
        match=r"unknown weights 'kernal'; valid values are 'uniform', 'kernel', "
        r"'inverse_distance', 'metric_diagonal', 'metric_full'",
    ):
        jaxgeom.edge_weights(tess, weights="kernal")
    with pytest.raises(ValueError, match=r"weights 'metric_full' needs `metric`"):
        jaxgeom.edge_weights(tess, weights="metric_full")
    with pytest.raises(ValueError, match=r"unknown weights 'gaussian'; valid values are 'kernel', 'uniform'"):
        jaxgeom.graph_laplacian(tess, weights="gaussian")
    with pytest.raises(ValueError, match=r"unknown weights 'kernel'; valid values are 'uniform'"):
        jaxgeom.estimate_gradient(tess, np.zeros(200), method="fd", weights="kernel")


# --- issue 32: the last unchecked arguments -------------------------------------------------


N = 200  # walkers of the `tess` fixture
VOL = np.linspace(0.5, 1.5, N)


@pytest.mark.parametrize(
    "call, error, message",
    [
        # per-walker arrays of the cell proxies and curvature: length, strings, complex, signs, masks
        (lambda t: jaxgeom.volume_distortion(t, VOL[:5]), ValueError, r"`volumes` must have shape \(200,\)"),
        (lambda t: jaxgeom.volume_distortion(t, "abc"), TypeError, r"`volumes` must be numeric; got str"),
        (lambda t: jaxgeom.volume_distortion(t, VOL + 0j), TypeError, r"`volumes` must be real; got complex"),
        (lambda t: jaxgeom.volume_distortion(t, -VOL), ValueError, r"`volumes` must be >= 0"),
        (lambda t: jaxgeom.ricci_scalar(t, volumes=VOL[:5]), ValueError, r"`volumes` must have shape \(200,\)"),
        (lambda t: jaxgeom.ricci_scalar(t, volumes="abc"), TypeError, r"`volumes` must be numeric"),
        (lambda t: jaxgeom.ricci_scalar(t, volumes=VOL + 0j), TypeError, r"`volumes` must be real"),
        (lambda t: jaxgeom.riemannian_volumes(t, volumes=list(VOL[:5])), ValueError, r"`volumes` must have shape"),
        (lambda t: jaxgeom.riemannian_volumes(t, volumes=-VOL), ValueError, r"`volumes` must be >= 0"),
        (
            lambda t: jaxgeom.viscous_force(t, np.zeros((N, 2)), nu=0.1, volume_weights=VOL + 0j),
            TypeError,
            r"`volume_weights` must be real",
        ),
        (lambda t: jaxgeom.riemannian_mean(VOL, VOL, mask=np.ones(N)), TypeError, r"`mask` must be a bool mask"),
        (lambda t: jaxgeom.riemannian_mean(VOL, VOL, mask=np.ones(5, bool)), ValueError, r"`mask` must have shape"),
        (lambda t: jaxgeom.riemannian_mean(VOL, "abc"), TypeError, r"`weights` must be a 1-D array"),
        (lambda t: jaxgeom.riemannian_mean(VOL, -VOL), ValueError, r"`weights` must be >= 0"),
        (lambda t: jaxgeom.riemannian_mean(VOL + 0j, VOL), TypeError, r"`values` must be real"),
        (lambda t: jaxgeom.riemannian_mean(VOL, VOL[:5]), ValueError, r"`values` and `weights` must have the same"),
        (
            lambda t: jaxgeom.raychaudhuri_expansion(np.ones((N, 2)), np.ones((N, 2)), 0.1),
            ValueError,
            r"`volumes_before` must be 1-D",
        ),
        (lambda t: jaxgeom.raychaudhuri_expansion(VOL + 0j, VOL, 0.1), TypeError, r"`volumes_before` must be real"),
        (
            lambda t: jaxgeom.raychaudhuri_expansion(VOL, VOL, 0.1, valid=np.ones(N)),
            TypeError,
            r"`valid` must be a bool",
        ),
        (lambda t: jaxgeom.mean_curvature_estimate(np.array([1.0, 2.0]) + 0j), TypeError, r"`theta` must be real"),
        # callables
        (lambda t: jaxgeom.hessian_metric(5, 0.1), TypeError, r"`fitness` must be a JAX function"),
        (
            lambda t: jaxgeom.ricci_scalar(t, metric=lambda p: float(p[0]) * jnp.eye(2)),
            TypeError,
            r"the metric callable must be JAX-traceable.*no float\(\)",
        ),
        (
            lambda t: jaxgeom.init_swarm(lambda p: 1, np.random.default_rng(0).random((30, 2))),
            TypeError,
            r"`fitness` must return a real floating-point scalar.*int",
        ),
        (
            lambda t: jaxgeom.init_swarm(
                lambda p: jnp.sum(p).astype(complex), np.random.default_rng(0).random((30, 2))
            ),
            TypeError,
            r"`fitness` must return a real floating-point scalar.*complex",
        ),
        # the estimation helpers
        (lambda t: jaxgeom.geometric_hessian(t, -1.0), ValueError, r"`eps_sigma` must be a finite number >= 0"),
        (lambda t: jaxgeom.geometric_hessian(t, float("nan")), ValueError, r"`eps_sigma` must be a finite number >= 0"),
        (lambda t: jaxgeom.compare_estimation_methods(t, VOL, eps_sigma=-1.0), ValueError, r"`eps_sigma` must be"),
        (
            lambda t: jaxgeom.validate_on_synthetic_function("quadratic", n_walkers=100.5),
            TypeError,
            r"`n_walkers` must be an int >= 4; got 100.5",
        ),
        (
            lambda t: jaxgeom.validate_on_synthetic_function("quadratic", eps_sigma=float("nan")),
            ValueError,
            r"`eps_sigma` must be",
        ),
        (lambda t: jaxgeom.plot_estimation_quality({}, "unused.png"), ValueError, r"`result` lacks \['points'"),
        # LOBPCG and meshes
        (
            lambda t: jaxgeom.spectral_gap(t, method="lobpcg", tol=-1.0),
            ValueError,
            r"`tol` must be a finite number > 0",
        ),
        (lambda t: jaxgeom.spectral_gap(t, method="lobpcg", tol=float("nan")), ValueError, r"`tol` must be"),
        (lambda t: jaxgeom.spectral_gap(t, method="lobpcg", maxiter=-3), ValueError, r"`maxiter` must be an int >= 1"),
        (
            lambda t: jaxgeom.batch_mesh("cpu"),
            TypeError,
            r"`devices` must be a sequence of JAX devices.*jax.devices\('cpu'\)",
        ),
        (lambda t: jaxgeom.batch_mesh([jax.devices()[0]] * 2), ValueError, r"`devices` lists a device more than once"),
    ],
)
def test_unchecked_arguments_of_issue_32(tess, call, error, message, own_messages):
    with pytest.raises(error, match=message):
        call(tess)


def test_plain_lists_and_nan_entries_are_legal_per_walker_input(tess):
    """A list is an array (once: jnp.isfinite on a list); NaN entries are left out, not zero."""
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    assert float(jaxgeom.volume_distortion(tess, list(vol))) == pytest.approx(
        float(jaxgeom.volume_distortion(tess, vol))
    )
    assert float(jaxgeom.mean_curvature_estimate([1.0, 2.0, float("nan")])) == -1.5


@pytest.fixture(scope="module")
def swarm():
    return jaxgeom.init_swarm(bowl, np.random.default_rng(0).random((40, 2)))


@pytest.mark.parametrize(
    "call, error, message",
    [
        (
            lambda s: jaxgeom.simulate(bowl, s, jaxgeom.SwarmParams(), n_steps=1, spectral_gap_every=-2),
            ValueError,
            r"`spectral_gap_every` must be an int >= 0; got -2",
        ),
        (
            lambda s: jaxgeom.simulate(lambda p: float(np.sum(p)), s, jaxgeom.SwarmParams(), n_steps=1),
            TypeError,
            r"`fitness` must be a JAX-traceable function",
        ),
        (
            lambda s: jaxgeom.simulation_loss(bowl, s, n_steps=2, params=jaxgeom.SwarmParams(), key="abc"),
            TypeError,
            r"`key` must be an int seed or a jax.random key",
        ),
        (
            lambda s: jaxgeom.simulation_loss(
                bowl, s, n_steps=2, params=jaxgeom.SwarmParams(), bounds={"nu": ("a", "b")}
            ),
            TypeError,
            r"bounds for 'nu' must be real numbers or None",
        ),
        (
            lambda s: jaxgeom.simulation_loss(bowl, s, n_steps=2, params=jaxgeom.SwarmParams())(jnp.zeros(5)),
            ValueError,
            r"theta must have shape \(1,\), one entry per tuned parameter",
        ),
        (
            lambda s: jaxgeom.tune(
                jaxgeom.simulation_loss(bowl, s, n_steps=2, params=jaxgeom.SwarmParams()), rtol=-1.0
            ),
            ValueError,
            r"`rtol` must be a finite number > 0",
        ),
        (
            lambda s: jaxgeom.tune(
                jaxgeom.simulation_loss(bowl, s, n_steps=2, params=jaxgeom.SwarmParams()),
                solver="lbfgsb",
                bounds={"nu": (1.0, 0.1)},
            ),
            ValueError,
            r"bounds for 'nu' must have lower < upper; got \(1.0, 0.1\)",
        ),
        (
            lambda s: jaxgeom.shard_batch(jaxgeom.stack_swarms([s, s]), "cpu"),
            TypeError,
            r"`mesh` must be a jax.sharding.Mesh",
        ),
        (
            lambda s: jaxgeom.shard_batch(jaxgeom.stack_swarms([s, s]), jaxgeom.walker_mesh()),
            ValueError,
            r"`mesh` must have an axis named 'batch'",
        ),
    ],
)
def test_unchecked_swarm_arguments_of_issue_32(swarm, call, error, message, own_messages):
    with pytest.raises(error, match=message):
        call(swarm)


def test_one_observable_name_is_one_observable(swarm):
    """Once: observe="mean_fitness" was read letter by letter ("unknown observable 'm'")."""
    _, history = jaxgeom.simulate(bowl, swarm, jaxgeom.SwarmParams(), n_steps=2, observe="mean_fitness")
    assert history["mean_fitness"].shape == (3,)
    loss = jaxgeom.simulation_loss(
        bowl, swarm, lambda h: h["mean_fitness"][-1], n_steps=2, params=jaxgeom.SwarmParams(), observe="mean_fitness"
    )
    assert loss.observe == ("mean_fitness",)


@pytest.mark.parametrize(
    "body, message",
    [
        ("import jax.numpy as jnp\ndef V(x):\n    return 2.0 * x\n", r"it must return a scalar \(shape \(\)\)"),
        ("def V(x):\n    raise RuntimeError('boom')\n", r"tracing it failed: RuntimeError: boom"),
        (
            "import numpy as np\ndef V(x):\n    return float(np.sum(np.asarray(x) ** 2))\n",
            r"must be a JAX-traceable function.*TracerArrayConversionError",
        ),
        (
            "import jax.numpy as jnp\ndef V(x):\n    return jnp.sum(x ** 2).astype(int)\n",
            r"it must return a real floating-point scalar.*int",
        ),
    ],
)
def test_analyze_refuses_a_landscape_file_it_cannot_use(tmp_path, capsys, body, message):
    (tmp_path / "v.py").write_text(body)
    assert main(["analyze", "--landscape", str(tmp_path / "v.py"), "--n", "100"]) == 2
    assert re.search(r"V in .*v\.py: .*" + message, capsys.readouterr().err)


@pytest.mark.parametrize("dim", ["0", "-1"])
def test_analyze_refuses_a_dimension_below_one(capsys, dim):
    assert main(["analyze", "--dim", dim, "--n", "100"]) == 2
    assert f"--dim must be >= 1; got {dim}" in capsys.readouterr().err
