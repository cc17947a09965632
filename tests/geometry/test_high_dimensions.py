"""k-NN graphs beyond 3D: the per-walker tensors that are written out entry by entry in 2D
and 3D are einsums from d = 4 (`WRITTEN_OUT_MAX_DIM`), programs whose size does not grow
with d^2 (d = 30 took minutes to compile before: the Hessian fit over 10 minutes, the emergent
metric 45 s), against numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.base._simplex import WRITTEN_OUT_MAX_DIM

D = 24


@pytest.fixture(scope="module")
def cloud():
    x = np.random.default_rng(5).uniform(-0.4, 0.4, (90, D))
    return x, jaxgeom.knn_graph(x, 10)


def neighbours(tess, i):
    return np.asarray(tess.neighbors)[i][np.asarray(tess.neighbor_mask)[i]]


def test_the_einsum_forms_start_above_the_written_out_dimensions():
    assert WRITTEN_OUT_MAX_DIM == 3  # the tests below at d = 4, 5 and 24 take the einsum forms


@pytest.mark.parametrize("d", [4, 5])
def test_quadratic_fields_are_recovered_exactly_in_4d_and_5d(rng, d):
    x = rng.random((400, d))
    tess = jaxgeom.knn_graph(x, 30)  # a 1-ring of 30 >= the (d + 1)(d + 2) / 2 - 1 coefficients
    a = rng.normal(size=d)
    h = rng.normal(size=(d, d))
    h = h + h.T
    quadratic = 0.5 * np.einsum("ni,ij,nj->n", x, h, x) + x @ a
    grad, info = jaxgeom.estimate_gradient(tess, quadratic, with_info=True)
    assert int(info.n_invalid) == 0
    np.testing.assert_allclose(np.asarray(grad), x @ h + a, atol=1e-8)
    hess = np.asarray(jaxgeom.estimate_hessian(tess, quadratic))
    np.testing.assert_allclose(hess, np.broadcast_to(h, hess.shape), atol=1e-7)


def test_emergent_metric_is_the_inverse_regularised_neighbour_covariance(cloud):
    x, tess = cloud
    g = np.asarray(jaxgeom.emergent_metric(tess, eps_reg=1e-3))
    for i in range(0, len(x), 11):
        dx = x[neighbours(tess, i)] - x[i]
        c = dx.T @ dx / len(dx)
        c += 1e-3 * np.trace(c) / D * np.eye(D)
        np.testing.assert_allclose(g[i], np.linalg.inv(c), rtol=1e-7)


def test_edge_lengths_under_a_metric_callable_and_array(cloud):
    x, tess = cloud

    def metric(y):
        return (1 + y @ y) * jnp.eye(D, dtype=y.dtype) + 0.1 * jnp.outer(y, y)

    def g_at(y):
        return (1 + y @ y) * np.eye(D) + 0.1 * np.outer(y, y)

    lengths = np.asarray(jaxgeom.edge_lengths(tess, metric=metric))
    on_walkers = np.asarray(jaxgeom.edge_lengths(tess, metric=jnp.asarray(np.stack([g_at(y) for y in x]))))
    for i in range(0, len(x), 13):
        for slot, j in enumerate(neighbours(tess, i)):
            dx = x[j] - x[i]
            np.testing.assert_allclose(lengths[i, slot], np.sqrt(dx @ g_at(x[i] + dx / 2) @ dx), rtol=1e-12)
            both = 0.5 * (dx @ g_at(x[i]) @ dx + dx @ g_at(x[j]) @ dx)
            np.testing.assert_allclose(on_walkers[i, slot], np.sqrt(both), rtol=1e-12)


def test_quadratic_fits_no_stencil_can_determine_are_nan_and_never_solved(cloud):
    """d = 24 has 324 coefficients: a 1-ring of 10 and a 2-ring of 20 determine none, so the
    fit is NaN by its shapes alone (it took 6 s per call on 300 walkers at d = 30 to solve the
    325 x 325 normal equations of every walker for nothing)."""
    x, tess = cloud
    values = jnp.asarray(x[:, 0] ** 2)
    grad, info = jaxgeom.estimate_gradient(tess, values, with_info=True)
    assert np.isnan(np.asarray(grad)).all() and int(info.n_invalid) == len(x)
    assert np.isnan(np.asarray(jaxgeom.estimate_hessian(tess, values))).all()
    program = jax.jit(jaxgeom.estimate_hessian).lower(tess, values).as_text()
    assert "potrf" not in program  # no Cholesky factor of normal equations


def test_the_programs_do_not_grow_with_the_square_of_the_dimension():
    def size(d, call):
        x = np.random.default_rng(0).uniform(-0.4, 0.4, (40, d))
        tess = jaxgeom.knn_graph(x, 8)
        return jax.jit(call).lower(tess, jnp.asarray(x[:, 0])).as_text().count(" = ")

    calls = {
        "emergent_metric": lambda t, v: jaxgeom.emergent_metric(t),
        "edge_lengths": lambda t, v: jaxgeom.edge_lengths(t, metric=jnp.eye(t.dim) * (1 + v[:, None, None] ** 2)),
        "estimate_hessian": lambda t, v: jaxgeom.estimate_hessian(t, v),
    }
    for name, call in calls.items():
        small, large = size(8, call), size(40, call)
        assert large == small, (name, small, large)
