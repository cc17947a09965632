"""The scutoid observables of `simulate`: the same counts as `jaxgeom.scutoids` on the graphs of
consecutive steps with the clone parents of the step, in every driver and across calls."""

import jax.numpy as jnp
import numpy as np

import jaxgeom

SCUTOIDS = ("prism_fraction", "simple_scutoid_fraction", "complex_scutoid_fraction", "mean_neighbor_change")


def V(x):
    return jnp.sum(x**2 - 2.0 * jnp.cos(3.0 * x))


def test_a_translating_swarm_is_all_prisms():
    """No force, no noise, equal velocities: every walker moves by v dt, the graph is translated."""
    x0 = np.random.default_rng(0).random((200, 2))
    flat = lambda x: 0.0 * jnp.sum(x)  # noqa: E731
    state = jaxgeom.init_swarm(flat, x0, velocities=np.tile([0.3, -0.2], (200, 1)), key=0)
    params = jaxgeom.SwarmParams(dt=0.1, gamma=0.0, temperature=0.0, nu=0.2, cloning=False)
    _, history = jaxgeom.simulate(flat, state, params, n_steps=4, observe=SCUTOIDS)
    assert np.isnan(history["prism_fraction"][0])  # no step before the first state
    np.testing.assert_array_equal(history["prism_fraction"][1:], 1.0)
    np.testing.assert_array_equal(history["mean_neighbor_change"][1:], 0.0)
    np.testing.assert_array_equal(history["complex_scutoid_fraction"][1:], 0.0)


def test_observables_equal_the_kernel_on_consecutive_graphs_with_the_clone_parents():
    x0 = np.random.default_rng(1).uniform(-2, 2, (300, 2))
    state = jaxgeom.init_swarm(V, x0, key=3)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.5, nu=0.2, clone_rate=0.5)
    states, fractions = [state], []
    for _ in range(3):
        state, history = jaxgeom.simulate(V, state, params, n_steps=1, observe=SCUTOIDS)
        states.append(state)
        fractions.append([float(history[name][-1]) for name in SCUTOIDS])
    for before, after, seen in zip(states[:-1], states[1:], fractions, strict=True):
        parents = np.asarray(after.scutoid_trace.parents)
        cloned = np.asarray(after.cloned)
        assert cloned.sum() > 0 and (parents[~cloned] == np.flatnonzero(~cloned)).all()
        s = jaxgeom.scutoids(before.tess, after.tess, parents)
        mask = np.asarray(s.interior)
        expected = list(np.asarray(s.fractions())) + [float(np.mean(np.asarray(s.lost + s.gained)[mask]))]
        np.testing.assert_allclose(seen, expected, rtol=1e-12)


def test_one_call_equals_continued_calls_and_the_callback_driver():
    x0 = np.random.default_rng(2).uniform(-2, 2, (150, 2))
    state = jaxgeom.init_swarm(V, x0, key=1)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.5, nu=0.2, clone_rate=0.3)
    _, whole = jaxgeom.simulate(V, state, params, n_steps=4, observe=SCUTOIDS)
    middle, first = jaxgeom.simulate(V, state, params, n_steps=2, observe=SCUTOIDS)
    _, second = jaxgeom.simulate(V, middle, params, n_steps=2, observe=SCUTOIDS)
    _, traced = jaxgeom.simulate(V, state, params, n_steps=4, observe=SCUTOIDS, rebuild="callback")
    for name in SCUTOIDS:
        joined = np.concatenate([first[name], second[name][1:]])
        np.testing.assert_allclose(joined, whole[name], rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(traced[name], whole[name], rtol=1e-12, equal_nan=True)
    assert np.isfinite(whole["prism_fraction"][1:]).all() and (whole["complex_scutoid_fraction"][1:] > 0).any()


def test_scutoid_observables_are_nan_on_a_knn_graph():
    state = jaxgeom.init_swarm(V, np.random.default_rng(3).random((80, 2)), graph="knn", k=8)
    _, history = jaxgeom.simulate(V, state, jaxgeom.SwarmParams(dt=0.05), n_steps=2, observe=SCUTOIDS)
    assert all(np.isnan(history[name]).all() for name in SCUTOIDS)
