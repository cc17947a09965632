"""Every argument is used or refused (issue 49): the audit of the public surface for arguments
that were accepted and silently ignored in some mode, one test each."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom


@pytest.fixture(scope="module")
def tess():
    return jaxgeom.delaunay(np.random.default_rng(0).random((300, 2)))


def test_estimate_gradient_uses_its_weights_in_the_quadratic_fit(tess):
    """Once: order=2 (the default) returned exactly the uniform result for every `weights`."""
    x = np.asarray(tess.points)
    wavy = np.sin(3 * x[:, 0]) + x[:, 1] ** 2
    uniform = np.asarray(jaxgeom.estimate_gradient(tess, wavy))
    for weights in ("inverse_distance", "gaussian"):
        weighted = np.asarray(jaxgeom.estimate_gradient(tess, wavy, weights=weights))
        assert np.nanmax(np.abs(weighted - uniform)) > 1e-6, weights
        quadratic = x[:, 0] ** 2 + 3 * x[:, 0] * x[:, 1] - x[:, 1] ** 2 + x[:, 0]
        exact = np.c_[2 * x[:, 0] + 3 * x[:, 1] + 1, 3 * x[:, 0] - 2 * x[:, 1]]
        np.testing.assert_allclose(
            np.asarray(jaxgeom.estimate_gradient(tess, quadratic, weights=weights)), exact, atol=1e-9
        )


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda t: jaxgeom.estimate_gradient(t, np.zeros(300), method="fd", order=1), "`order` chooses the polynomial"),
        (lambda t: jaxgeom.spectral_gap(t, method="scipy", tol=1e-6), "`tol` of method='lobpcg'"),
        (lambda t: jaxgeom.spectral_gap(t, maxiter=10), "`maxiter` of method='lobpcg'"),
        (lambda t: jaxgeom.spectral_gap(t, seed=3), "`seed` of method='lobpcg'"),
        (lambda t: jaxgeom.geodesic_distances(t, 0, method="dijkstra", t=0.1), "`t` of method='heat'"),
        (lambda t: jaxgeom.geodesic_distances(t, 0, method="bellman_ford", boundary="dirichlet"), "`boundary`"),
        (lambda t: jaxgeom.geodesic_distances(t, 0, method="dijkstra", solver="cg"), "`solver`"),
        (lambda t: jaxgeom.ollivier_ricci(t, kernel_scale=0.1), "`kernel_scale` is the width of measure='kernel'"),
        (
            lambda t: jaxgeom.viscous_force(t, np.zeros((300, 2)), nu=0.1, weights="uniform", length_scale=0.1),
            "`length_scale` sets the width of weights='kernel'",
        ),
        (
            lambda t: jaxgeom.viscous_force(t, np.zeros((300, 2)), nu=0.1, weights="inverse_distance", alpha=2.0),
            "`alpha` sets the adaptive width",
        ),
        (
            lambda t: jaxgeom.viscous_force(t, np.zeros((300, 2)), nu=0.1, length_scale=0.1, alpha=2.0),
            "`alpha` sets the adaptive width",
        ),
        (
            lambda t: jaxgeom.viscous_force(t, np.zeros((300, 2)), nu=0.1, metric=lambda p: jnp.eye(2)),
            "`metric` is used by the metric weights",
        ),
        (lambda t: jaxgeom.edge_weights(t, weights="uniform", alpha=2.0), "`alpha` sets the adaptive width"),
        (lambda t: jaxgeom.graph_laplacian(t, weights="uniform", length_scale=0.2), "`length_scale` sets the width"),
    ],
    ids=[
        "fd order",
        "scipy tol",
        "scipy maxiter",
        "scipy seed",
        "dijkstra t",
        "bellman_ford boundary",
        "dijkstra solver",
        "uniform measure kernel_scale",
        "uniform length_scale",
        "inverse_distance alpha",
        "alpha beside length_scale",
        "kernel metric",
        "edge_weights alpha",
        "laplacian length_scale",
    ],
)
def test_an_argument_the_mode_ignores_is_refused(tess, call, message):
    with pytest.raises(ValueError, match=message):
        call(tess)


def V(x):
    return jnp.sum(x**2)


@pytest.fixture(scope="module")
def swarm():
    return jaxgeom.init_swarm(V, np.random.default_rng(1).random((40, 2)))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(objective="final_fitness", window=0.3), "`window` sets the time average"),
        (dict(objective="best_fitness", window=0.3), "`window` sets the time average"),
        (dict(objective="mean_fitness", observe=("velocity_variance",)), "`observe` lists what a callable objective"),
    ],
)
def test_simulation_loss_refuses_what_its_objective_ignores(swarm, kwargs, message):
    with pytest.raises(ValueError, match=message):
        jaxgeom.simulation_loss(V, swarm, n_steps=2, params=jaxgeom.SwarmParams(), **kwargs)


def test_tune_refuses_atol_with_lbfgsb_and_simulate_a_bar_it_cannot_show(swarm):
    loss = jaxgeom.simulation_loss(V, swarm, n_steps=2, params=jaxgeom.SwarmParams())
    with pytest.raises(ValueError, match="`atol` is optimistix's absolute tolerance"):
        jaxgeom.tune(loss, solver="lbfgsb", atol=1e-3)
    with pytest.raises(ValueError, match="`progress` shows the host driver's steps"):
        jaxgeom.simulate(V, swarm, jaxgeom.SwarmParams(), n_steps=1, rebuild="callback", progress=True)


def test_the_defaults_stay_accepted(tess, swarm):
    """The refusals above concern arguments given, not the defaults every mode resolves."""
    assert np.isfinite(np.asarray(jaxgeom.spectral_gap(tess, k=3))).all()
    assert np.isfinite(np.asarray(jaxgeom.geodesic_distances(tess, 0, method="dijkstra"))).all()
    jaxgeom.viscous_force(tess, np.zeros((300, 2)), nu=0.1, weights="uniform")
    jaxgeom.simulation_loss(V, swarm, "final_fitness", n_steps=2, params=jaxgeom.SwarmParams())
    jaxgeom.simulation_loss(
        V, swarm, lambda h: h["mean_fitness"][-1], n_steps=2, params=jaxgeom.SwarmParams(), observe=("mean_fitness",)
    )
    assert jax.numpy.isfinite(jaxgeom.estimate_gradient(tess, np.asarray(tess.points)[:, 0], method="fd")).any()
