import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import quadratic, rastrigin
from jaxgeom.swarm._dynamics import ornstein_uhlenbeck, relativize, swarm_step


def bowl(x):
    return 0.5 * (x[0] ** 2 + 2.0 * x[1] ** 2)


def flat(x):
    return 0.0 * jnp.sum(x)


def swarm(rng, n=300, lo=-1.0, hi=1.0, dtype=np.float64, fitness=bowl, **kwargs):
    x = rng.uniform(lo, hi, (n, 2)).astype(dtype)
    return jaxgeom.init_swarm(fitness, x, key=3, **kwargs)


def test_same_seed_gives_bitwise_identical_runs(rng):
    state = swarm(rng)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.2, nu=0.3, clone_rate=0.5)
    a, ha = jaxgeom.simulate(bowl, state, params, n_steps=15)
    b, hb = jaxgeom.simulate(bowl, state, params, n_steps=15)
    assert np.array_equal(np.asarray(a.positions), np.asarray(b.positions))
    assert np.array_equal(np.asarray(a.velocities), np.asarray(b.velocities))
    for name in jaxgeom.OBSERVABLES:
        assert np.array_equal(ha[name], hb[name], equal_nan=True)
    assert ha["n_clones"].sum() > 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float32_and_float64_both_run(rng, dtype):
    state = swarm(rng, dtype=dtype)
    final, history = jaxgeom.simulate(bowl, state, jaxgeom.SwarmParams(dt=0.05), n_steps=5, rebuild_every=2)
    assert final.positions.dtype == dtype and final.velocities.dtype == dtype
    assert np.isfinite(final.positions).all()
    assert all(history[name].shape == (6,) for name in jaxgeom.OBSERVABLES)
    assert np.isfinite(history["mean_ricci"]).all() and np.isfinite(history["mean_expansion"][1:]).all()


def test_no_recompilation_after_warm_up(rng):
    traces = []

    def counted(x):
        traces.append(1)  # runs only while JAX traces
        return bowl(x)

    state = swarm(rng, n=400, fitness=counted)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.3, nu=0.2, clone_rate=0.3)
    state, _ = jaxgeom.simulate(counted, state, params, n_steps=3)
    before = len(traces)
    final, history = jaxgeom.simulate(counted, state, params, n_steps=100)
    assert len(traces) == before
    assert history["n_reallocations"] == 0 and history["n_clones"].sum() > 0
    assert not bool(final.tess.overflow)


def test_a_new_swarm_size_compiles_whole_programs_not_single_operations(rng):
    """init_swarm and simulate's host driver compile a few programs for a swarm size not seen
    before (the graph build, the fitness and force, the chunk of steps, ...), not one per
    jax.numpy operation run eagerly on the host (64 in init_swarm and 29 in simulate before; 7 and 12)."""
    programs = []

    def count(event, duration, **kwargs):
        if event == "/jax/core/compile/jaxpr_to_mlir_module_duration":
            programs.append(event)

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        state = jaxgeom.init_swarm(bowl, rng.uniform(-1.0, 1.0, (137, 2)), key=0)
        in_init = len(programs)
        jaxgeom.simulate(bowl, state, jaxgeom.SwarmParams(), n_steps=2)
    finally:
        jax.monitoring.unregister_event_duration_listener(count)
    assert in_init <= 12 and len(programs) - in_init <= 16, (in_init, len(programs) - in_init)


def test_cloning_improves_the_best_fitness_on_rastrigin(rng):
    state = jaxgeom.init_swarm(rastrigin, rng.uniform(2.0, 5.0, (500, 2)), key=0)
    runs = {}
    for cloning in (True, False):
        params = jaxgeom.SwarmParams(dt=0.02, gamma=2.0, temperature=1.0, nu=0.05, clone_rate=0.5, cloning=cloning)
        runs[cloning] = jaxgeom.simulate(
            rastrigin, state, params, n_steps=150, observe=("best_fitness", "mean_fitness", "n_clones")
        )[1]
    history = runs[True]
    assert history["best_fitness"][-1] < 0.6 * history["best_fitness"][0]
    assert history["n_clones"].sum() > 100 and runs[False]["n_clones"].sum() == 0
    # cloning moves the swarm into the good wells: far lower mean fitness than Langevin alone
    assert history["mean_fitness"][-1] < 0.5 * runs[False]["mean_fitness"][-1]


def test_viscous_only_dynamics_reach_a_common_velocity(rng):
    state = swarm(rng, n=200, fitness=flat, velocities=rng.normal(size=(200, 2)))
    params = jaxgeom.SwarmParams(dt=0.5, gamma=0.0, temperature=0.0, nu=1.0, weights="uniform", cloning=False)
    final, history = jaxgeom.simulate(flat, state, params, n_steps=600, rebuild_every=10)
    variance = history["velocity_variance"]
    assert variance[-1] < 1e-5 * variance[0] and variance[-1] < 0.1 * variance[300]  # still decaying geometrically
    assert np.all(np.diff(history["degree_weighted_variance"][:10]) <= 1e-12)


def test_langevin_equipartition_without_viscosity(rng):
    state = swarm(rng, n=1000)
    params = jaxgeom.SwarmParams(dt=0.05, gamma=1.0, temperature=0.5, nu=0.0, cloning=False)
    final, history = jaxgeom.simulate(
        bowl, state, params, n_steps=400, rebuild_every=50, observe=("velocity_variance", "mean_fitness")
    )
    # the velocity variance is per component: T at equilibrium in any d; <V> = d T / 2 for a
    # quadratic V (BAOAB is exact-ish at this dt)
    np.testing.assert_allclose(history["velocity_variance"][200:].mean(), 0.5, rtol=0.03)
    np.testing.assert_allclose(
        history["velocity_variance"][-1], np.var(np.asarray(final.velocities), axis=0).mean(), rtol=1e-12
    )
    np.testing.assert_allclose(history["mean_fitness"][200:].mean(), 0.5, rtol=0.05)


def test_anisotropic_noise_has_covariance_T_inverse_metric():
    g = jnp.array([[4.0, 1.0], [1.0, 2.0]])
    params = jaxgeom.SwarmParams(dt=1.0, gamma=50.0, temperature=0.3, anisotropic=True)
    v = ornstein_uhlenbeck(
        params,
        jnp.zeros((200_000, 2)),
        jnp.broadcast_to(g, (200_000, 2, 2)),
        jax.random.normal(jax.random.PRNGKey(0), (200_000, 2)),
    )
    np.testing.assert_allclose(np.cov(np.asarray(v).T), 0.3 * np.linalg.inv(np.asarray(g)), atol=3e-3)


def test_relativize_is_monotone_and_positive():
    values = jnp.array([3.0, -1.0, 0.5, 10.0, 2.0])
    r = np.asarray(relativize(values, jnp.ones(5, bool)))
    assert np.all(r > 0) and np.array_equal(np.argsort(r), np.argsort(np.asarray(values)))


def test_schedules(rng):
    stiff = lambda x: 0.5 * (1e7 * x[0] ** 2 + x[1] ** 2)  # noqa: E731
    state = jaxgeom.init_swarm(stiff, rng.uniform(-1e-3, 1e-3, (200, 2)) * [1, 1000], key=0)
    params = jaxgeom.SwarmParams(
        dt=1e-4,
        nu=0.1,
        nu_initial=0.01,
        eps_sigma=1e-3,
        anneal_nu=True,
        adapt_eps_sigma=True,
        adapt_length_scale=True,
        cloning=False,
    )
    _, history = jaxgeom.simulate(stiff, state, params, n_steps=6, observe=("nu", "eps_sigma"))
    np.testing.assert_allclose(history["nu"][:6], np.linspace(0.01, 0.1, 6), rtol=1e-12)
    # cond(g) = (1e7 + eps) / (1 + eps) > 1e6 until eps ~ 9: raised 10x per step up to 10
    np.testing.assert_allclose(history["eps_sigma"][:6], [1e-3, 1e-2, 1e-1, 1.0, 10.0, 10.0], rtol=1e-12)


def test_swarm_step_without_friction_viscosity_or_cloning_is_velocity_verlet(rng):
    state = swarm(rng, n=100, velocities=rng.normal(size=(100, 2)), graph="knn")
    params = jaxgeom.SwarmParams(dt=0.05, gamma=0.0, nu=0.0, cloning=False)
    x, v, dt = np.asarray(state.positions), np.asarray(state.velocities), 0.05
    force = lambda p: -p * np.array([1.0, 2.0])  # -grad bowl
    half = v + 0.5 * dt * force(x)
    x1 = x + dt * half
    new = swarm_step(bowl, params, state, 0.0, True)
    np.testing.assert_allclose(np.asarray(new.positions), x1, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(np.asarray(new.velocities), half + 0.5 * dt * force(x1), rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(np.asarray(new.force), force(x1), rtol=1e-13, atol=1e-15)
    assert int(new.step) == 1


@pytest.mark.parametrize("rebuild", ["host", "callback"])
def test_simulate_runs_the_phases_of_swarm_step_apart_with_the_same_result(rng, rebuild):
    state = swarm(rng, n=200)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.2, nu=0.3, clone_rate=0.5)
    expected = swarm_step(bowl, params, state, 0.0, True)
    assert int(np.sum(expected.cloned)) > 0
    final, _ = jaxgeom.simulate(bowl, state, params, n_steps=1, rebuild=rebuild, observe=())
    for field in ("positions", "velocities", "fitness", "cloned"):
        np.testing.assert_allclose(
            np.asarray(getattr(final, field)), np.asarray(getattr(expected, field)), rtol=1e-12, atol=1e-14
        )


def test_history_has_the_same_keys_and_types_in_both_rebuild_modes(rng):
    state = swarm(rng, n=120)
    params = jaxgeom.SwarmParams(dt=0.05)
    _, host = jaxgeom.simulate(bowl, state, params, n_steps=4, rebuild_every=2, spectral_gap_every=2)
    _, callback = jaxgeom.simulate(bowl, state, params, n_steps=4, rebuild_every=2, rebuild="callback")
    assert host.keys() == callback.keys()
    for key in host:
        assert isinstance(host[key], jax.Array) and isinstance(callback[key], jax.Array), key
        assert host[key].dtype == callback[key].dtype, key
        if key not in ("spectral_gap_step", "spectral_gap", "spectral_components", "spectral_gap_rounding"):
            assert host[key].shape == callback[key].shape, key
    assert host["spectral_gap_step"].tolist() == [0, 2, 4] and callback["spectral_gap_step"].shape == (0,)
    assert np.isnan(callback["seconds_steps"]) and float(host["seconds_steps"]) > 0


def test_callback_rebuild_matches_host_rebuild(rng):
    state = swarm(rng, n=200)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.2, nu=0.3, clone_rate=0.5)
    a, ha = jaxgeom.simulate(bowl, state, params, n_steps=8)
    b, hb = jaxgeom.simulate(bowl, state, params, n_steps=8, rebuild="callback")
    np.testing.assert_allclose(np.asarray(b.positions), np.asarray(a.positions), atol=1e-10)
    assert np.array_equal(np.asarray(a.tess.neighbors), np.asarray(b.tess.neighbors))
    np.testing.assert_allclose(np.asarray(hb["mean_ricci"]), ha["mean_ricci"], rtol=1e-8, atol=1e-12)  # ~0 in a bowl


@pytest.mark.slow
def test_device_rebuild_matches_host_rebuild(rng):
    """The device rebuild's steps are Qhull's graphs: certified ones by the Delaunay lemma,
    the others rebuilt by Qhull and counted."""
    state = swarm(rng, n=160)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.2, nu=0.3, clone_rate=0.5)
    a, ha = jaxgeom.simulate(bowl, state, params, n_steps=8)
    b, hb = jaxgeom.simulate(bowl, state, params, n_steps=8, rebuild="device")
    np.testing.assert_allclose(np.asarray(b.positions), np.asarray(a.positions), atol=1e-10)
    assert np.array_equal(np.asarray(a.tess.neighbors), np.asarray(b.tess.neighbors))
    assert ha.keys() == hb.keys() and int(ha["n_fallbacks"]) == 0 and 0 <= int(hb["n_fallbacks"]) <= 8


@pytest.mark.slow
def test_an_uncertified_device_rebuild_falls_back_to_qhull_and_is_counted(rng, monkeypatch):
    import equinox as eqx

    import jaxgeom.swarm._rebuild

    real = jaxgeom.swarm._rebuild.rebuild_unchecked
    monkeypatch.setattr(
        jaxgeom.swarm._rebuild,
        "rebuild_unchecked",
        lambda tess, x, mesh=None: eqx.tree_at(lambda t: t.overflow, real(tess, x, mesh), jnp.asarray(True)),
    )
    state = swarm(rng, n=140)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.2, nu=0.3, clone_rate=0.5)
    a, _ = jaxgeom.simulate(bowl, state, params, n_steps=6, rebuild="callback")
    b, hb = jaxgeom.simulate(bowl, state, params, n_steps=6, rebuild="device")
    assert int(hb["n_fallbacks"]) == 6
    np.testing.assert_array_equal(np.asarray(b.positions), np.asarray(a.positions))
    assert np.array_equal(np.asarray(a.tess.neighbors), np.asarray(b.tess.neighbors))


@pytest.mark.parametrize("rebuild, n_steps", [("callback", 10), pytest.param("device", 20, marks=pytest.mark.slow)])
def test_gradient_through_a_whole_simulation_matches_finite_differences(rng, rebuild, n_steps):
    x = rng.uniform(-1, 1, (120, 2))
    state = jaxgeom.init_swarm(quadratic, x, rng.normal(size=(120, 2)), key=1)

    def loss(theta):
        params = jaxgeom.SwarmParams(
            dt=0.05,
            temperature=0.1,
            nu=theta[0],
            eps_sigma=theta[1],
            weights="metric_full",
            anisotropic=True,
            cloning=False,
        )
        _, history = jaxgeom.simulate(
            quadratic, state, params, n_steps=n_steps, rebuild=rebuild, observe=("mean_fitness",)
        )
        return history["mean_fitness"][-1]

    theta = jnp.array([0.3, 0.5])
    grad = jax.grad(loss)(theta)
    h = 1e-6
    fd = [(loss(theta.at[i].add(h)) - loss(theta.at[i].add(-h))) / (2 * h) for i in range(2)]
    np.testing.assert_allclose(np.asarray(grad), np.asarray(fd), rtol=1e-5)
    assert abs(float(grad[0])) > 0 and abs(float(grad[1])) > 0


@pytest.mark.parametrize("rebuild", ["host", pytest.param("callback", marks=pytest.mark.slow)])
def test_capacity_overflow_reallocates_instead_of_truncating(rng, rebuild):
    x = rng.uniform(-1, 1, (300, 2))
    tess = jaxgeom.delaunay(x)
    tight = jaxgeom.Capacity(tess.capacity.simplices, int(np.asarray(tess.degree).max()))
    state = jaxgeom.init_swarm(bowl, x, key=0, capacity=tight)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.3, clone_rate=1.0, clone_jitter=0.05)
    final, history = jaxgeom.simulate(bowl, state, params, n_steps=20, rebuild=rebuild)
    assert final.tess.capacity.neighbors > tight.neighbors
    assert not bool(final.tess.overflow)
    rebuilt = jaxgeom.delaunay(np.asarray(final.positions))
    assert np.array_equal(
        np.sort(np.asarray(rebuilt.neighbors), 1)[:, :8], np.sort(np.asarray(final.tess.neighbors), 1)[:, :8]
    )
    if rebuild == "host":
        assert history["n_reallocations"] >= 1


def test_volume_weighted_metric_mode_runs_and_keeps_the_velocity_range(rng):
    state = swarm(rng, n=300, fitness=flat, velocities=rng.normal(size=(300, 2)))
    params = jaxgeom.SwarmParams(
        dt=0.5, gamma=0.0, temperature=0.0, nu=1.0, weights="metric_diagonal", volume_weighting=True, cloning=False
    )
    final, history = jaxgeom.simulate(flat, state, params, n_steps=20, observe=("velocity_variance",))
    v0, v1 = np.asarray(state.velocities), np.asarray(final.velocities)
    assert np.all(v1.min(0) >= v0.min(0) - 1e-12) and np.all(v1.max(0) <= v0.max(0) + 1e-12)
    assert history["velocity_variance"][-1] < 0.5 * history["velocity_variance"][0]


def test_knn_swarm_in_4d(rng):
    f = lambda x: jnp.sum(x**2)  # noqa: E731
    state = jaxgeom.init_swarm(f, rng.normal(size=(300, 4)), graph="knn", k=10)
    final, history = jaxgeom.simulate(f, state, jaxgeom.SwarmParams(dt=0.05), n_steps=5)
    assert np.isnan(history["mean_ricci"]).all() and np.isfinite(history["degree_weighted_variance"]).all()
    assert final.tess.neighbors.shape == state.tess.neighbors.shape


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(weights="gauss"), ValueError, "unknown weights 'gauss'; valid values are 'uniform'"),
        (dict(nu=-1.0), ValueError, "`nu` must be a finite number >= 0"),
        (dict(dt=-0.1), ValueError, "`dt` must be a finite number > 0"),
        (dict(temperature=-1.0), ValueError, "`temperature` must be a finite number >= 0"),
        (dict(eps_sigma=-0.1), ValueError, "`eps_sigma` must be a finite number >= 0"),
    ],
)
def test_bad_params(kwargs, error, match):
    with pytest.raises(error, match=match):
        jaxgeom.SwarmParams(**kwargs)


def test_bad_swarm_input(rng):
    x = rng.uniform(-1, 1, (50, 2))
    with pytest.raises(TypeError, match="must return a scalar per walker"):
        jaxgeom.init_swarm(lambda p: p * 2.0, x)
    with pytest.raises(ValueError, match="`fitness` is NaN or inf at 1 initial walker"):
        jaxgeom.init_swarm(lambda p: jnp.where(p[0] == x[7, 0], jnp.nan, 1.0), x)
    with pytest.raises(ValueError, match=r"`velocities` must be a float array of shape \(N, d\)"):
        jaxgeom.init_swarm(bowl, x, np.zeros((50, 3)))
    with pytest.raises(ValueError, match="`positions` has NaN or inf"):
        jaxgeom.init_swarm(bowl, np.where(np.arange(50)[:, None] == 3, np.nan, x))
    state = jaxgeom.init_swarm(bowl, x)
    params = jaxgeom.SwarmParams()
    with pytest.raises(ValueError, match="`rebuild_every` must be an integer >= 1"):
        jaxgeom.simulate(bowl, state, params, n_steps=5, rebuild_every=0)
    with pytest.raises(ValueError, match="unknown observable 'ricci'; valid values are 'mean_fitness'"):
        jaxgeom.simulate(bowl, state, params, n_steps=5, observe=("ricci",))
    knn = jaxgeom.init_swarm(bowl, x, graph="knn", k=6)
    with pytest.raises(ValueError, match="`volume_weighting=True` needs Voronoi volumes"):
        jaxgeom.simulate(bowl, knn, jaxgeom.SwarmParams(volume_weighting=True), n_steps=2)
    with pytest.raises(ValueError, match="unknown rebuild 'gpu'; valid values are 'host', 'callback', 'device'"):
        jaxgeom.simulate(bowl, state, params, n_steps=5, rebuild="gpu")
    with pytest.raises(ValueError, match="rebuild='device'.* 2D Delaunay swarms"):
        jaxgeom.simulate(bowl, knn, params, n_steps=2, rebuild="device")


def convex(x):
    """A curved Hessian metric with a positive definite Hessian everywhere (no floor)."""
    return jnp.log1p(jnp.sum(jnp.exp(x))) + 0.25 * jnp.sum(x * x)


def test_mean_metric_curvature_is_opt_in_and_is_the_riemannian_mean_of_the_exact_curvature(rng):
    assert "mean_metric_curvature" not in jaxgeom.OBSERVABLES
    assert "mean_metric_curvature" in jaxgeom.ALL_OBSERVABLES
    params = jaxgeom.SwarmParams(dt=0.05, eps_sigma=0.2)
    state = swarm(rng, fitness=convex, lo=-2.0, hi=2.0)
    _, history = jaxgeom.simulate(convex, state, params, n_steps=2, observe=("mean_metric_curvature",))
    metric = jaxgeom.hessian_metric(convex, 0.2)
    exact = jaxgeom.metric_curvature(metric, state.positions)
    weights = jaxgeom.riemannian_volumes(state.tess, metric=metric)
    expected = jaxgeom.riemannian_mean(exact, weights, state.tess.interior)
    np.testing.assert_allclose(history["mean_metric_curvature"][0], expected, rtol=1e-9)
    assert np.isfinite(history["mean_metric_curvature"]).all() and history["mean_metric_curvature"][0] > 0


def test_mean_metric_curvature_on_a_knn_swarm_in_high_dimension(rng):
    d, k = 18, 10  # above EXACT_HESSIAN_MAX_DIM: the stochastic form
    x = rng.normal(scale=0.5, size=(200, d))
    state = jaxgeom.init_swarm(convex, x, key=3, graph="knn", k=k)
    _, history = jaxgeom.simulate(
        convex, state, jaxgeom.SwarmParams(dt=0.01, eps_sigma=0.2), n_steps=1, observe=("mean_metric_curvature",)
    )
    # independent: the exact Hessian form, weights r_k^d sqrt(det g) computed in numpy (logs)
    metric = jaxgeom.hessian_metric(convex, 0.2)
    exact = np.asarray(jaxgeom.metric_curvature(metric, jnp.asarray(x)))
    r_k = np.sort(np.linalg.norm(x[:, None] - x[None], axis=-1), axis=1)[:, k]
    log_w = d * np.log(r_k) + 0.5 * np.linalg.slogdet(np.asarray(jax.vmap(metric)(jnp.asarray(x))))[1]
    w = np.exp(log_w - log_w.max())
    expected = w @ exact / w.sum()
    # its standard error from the stochastic form's own per-walker errors (64 probe pairs)
    _, info = jaxgeom.metric_curvature(metric, jnp.asarray(x), probes=64, key=jax.random.key(0), with_info=True)
    error = np.sqrt(np.sum((w * np.asarray(info.standard_error)) ** 2)) / w.sum()
    assert 0 < error < 0.1 * abs(expected)
    assert abs(history["mean_metric_curvature"][0] - expected) < 4 * error


def test_tiers_left_to_after_the_step_change_nothing(rng, monkeypatch):
    """A 3D host run whose steps and observables read no tiers builds its graphs without them
    and computes them only for the state it returns (`deferred_tiers`): the same run, and the
    final graph's tiers are those of a fresh `delaunay` of the final walkers."""
    from jaxgeom.swarm import _drivers

    state = jaxgeom.init_swarm(bowl, rng.uniform(-1, 1, (400, 3)), key=0)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.3, clone_rate=0.5)
    observe = ("mean_fitness", "n_clones")
    deferred = jaxgeom.simulate(bowl, state, params, n_steps=6, observe=observe, spectral_gap_every=3)
    monkeypatch.setattr(_drivers, "reads_tiers", lambda params, observe: True)
    at_once = jaxgeom.simulate(bowl, state, params, n_steps=6, observe=observe, spectral_gap_every=3)
    (a, history_a), (b, history_b) = deferred, at_once
    for leaf_a, leaf_b in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        assert np.array_equal(np.asarray(leaf_a), np.asarray(leaf_b), equal_nan=True)
    for name in (*observe, "spectral_gap"):
        assert np.array_equal(np.asarray(history_a[name]), np.asarray(history_b[name]), equal_nan=True)
    fresh = jaxgeom.delaunay(np.asarray(a.positions))
    assert np.array_equal(np.asarray(a.tess.tier), np.asarray(fresh.tier))
    assert 0 < int(np.sum(np.asarray(a.tess.tier) == 0)) < 400


@pytest.mark.parametrize(
    "params_kwargs, observe",
    [({}, ("mean_fitness", "best_fitness", "n_clones")), ({"weights": "metric_diagonal"}, ("velocity_variance",))],
)
def test_a_step_that_reads_no_tiers_is_blind_to_them(rng, params_kwargs, observe):
    """The condition under which `simulate` leaves the tiers out of its graphs (`reads_tiers`
    false) holds: a chunk's results do not change with the tiers."""
    from jaxgeom.swarm._observables import reads_tiers
    from jaxgeom.swarm._steps import _begin_step, _run_chunk

    state = jaxgeom.init_swarm(bowl, rng.uniform(-1, 1, (300, 3)), key=0)
    params = jaxgeom.SwarmParams(dt=0.05, clone_rate=0.5, **params_kwargs)
    assert not reads_tiers(params, observe)
    blind = state.tess.tier.at[:].set(0)
    outs = [
        _run_chunk(bowl, params, s, _begin_step(params, s), jnp.asarray(0), jnp.asarray(5), 2, observe)
        for s in (state, eqx.tree_at(lambda s: s.tess.tier, state, blind))
    ]
    same_tiers = [eqx.tree_at(lambda o: o[0].tess.tier, o, blind) for o in outs]  # the tiers pass through
    for leaf_a, leaf_b in zip(*map(jax.tree_util.tree_leaves, same_tiers), strict=True):
        assert np.array_equal(np.asarray(leaf_a), np.asarray(leaf_b), equal_nan=True)
