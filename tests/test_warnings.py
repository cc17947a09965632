"""Issue 63: every warning jaxgeom emits names the caller's line (here, this file), not a line
inside the library, however deep the call runs (decorators, jit tracing)."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
import jaxgeom.geometry._geodesic as geodesic_module
import jaxgeom.swarm._history as history_module
import jaxgeom.tessellation._delaunay as delaunay_module


@pytest.fixture(scope="module")
def tess():
    return jaxgeom.delaunay(np.random.default_rng(0).random((120, 2)))


def attributed_here(record, text):
    mine = [w for w in record if text in str(w.message)]
    assert mine, "no warning was emitted"
    assert all(w.filename == __file__ for w in mine), [(w.filename, w.lineno, str(w.message)[:60]) for w in mine]


def test_kernel_weights_that_underflow(tess):
    with pytest.warns(UserWarning, match="weight 0") as record:
        jaxgeom.spectral_gap(tess, length_scale=1e-6)
    attributed_here(record, "weight 0")


def test_a_defective_metric_callable(tess):
    with pytest.warns(RuntimeWarning, match="metric_defects") as record:
        jaxgeom.ricci_scalar(tess, metric=lambda p: jnp.full((2, 2), jnp.nan))
    attributed_here(record, "metric_defects")


def test_eps_sigma_zero():
    with pytest.warns(UserWarning, match="eps_sigma = 0") as record:
        jaxgeom.hessian_metric(lambda p: jnp.sum(p**2), 0.0)
    attributed_here(record, "eps_sigma = 0")


def test_heat_distances_on_a_metric_that_varies_too_fast(tess):
    with pytest.warns(UserWarning, match="do not close") as record:
        jaxgeom.geodesic_distances(tess, [0], lambda p: jnp.eye(2) * jnp.exp(60.0 * p[0]))
    attributed_here(record, "do not close")


def test_singular_heat_systems(tess, monkeypatch):
    monkeypatch.setattr(
        geodesic_module,
        "_heat_jit",
        lambda tess, sources, *rest: (jnp.full((len(sources), tess.n_points), jnp.nan), jnp.asarray(0)),
    )
    with pytest.warns(UserWarning, match="singular") as record:
        jaxgeom.geodesic_distances(tess, [0])
    attributed_here(record, "singular")


def test_a_triangulator_replaced_by_qhull(tess, monkeypatch):
    monkeypatch.setattr(
        delaunay_module,
        "build_delaunay",
        lambda *a, **k: (tess, ("the backend failed its check; Qhull built this graph instead",)),
    )
    with pytest.warns(RuntimeWarning, match="Qhull built this graph") as record:
        jaxgeom.delaunay(np.asarray(tess.points))
    attributed_here(record, "Qhull built this graph")


def test_a_failed_spectral_gap_in_simulate(monkeypatch):
    def fails(tess):
        raise RuntimeError("no convergence")

    monkeypatch.setattr(history_module, "bulk_spectral_gap", fails)
    state = jaxgeom.init_swarm(lambda p: jnp.sum(p**2), np.random.default_rng(1).uniform(-1, 1, (60, 2)), key=0)
    with pytest.warns(RuntimeWarning, match="spectral gap failed") as record:
        jaxgeom.simulate(lambda p: jnp.sum(p**2), state, jaxgeom.SwarmParams(), n_steps=2, spectral_gap_every=1)
    attributed_here(record, "spectral gap failed")


def test_an_undetermined_hessian_fit():
    x = np.random.default_rng(2).normal(size=(200, 6))
    with pytest.warns(RuntimeWarning, match="undetermined") as record:
        jaxgeom.compare_estimation_methods(jaxgeom.knn_graph(x, 12), np.sum(x**2, axis=1), eps_sigma=0.1)
    attributed_here(record, "undetermined")
