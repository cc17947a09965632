import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import brute_knn

import jaxgeom


@pytest.mark.parametrize("method", ["kdtree", "brute"])
@pytest.mark.parametrize("d, k", [(2, 6), (3, 10), (12, 5)])
def test_knn_equals_numpy_brute_force(rng, method, d, k):
    x = rng.random((300, d))
    tess = jaxgeom.knn_graph(x, k, method=method)
    np.testing.assert_array_equal(np.asarray(tess.neighbors), brute_knn(x, k))
    assert tess.simplices is None and tess.neighbors.dtype == jnp.int32
    assert np.all(np.asarray(tess.tier) == 2), "without a box a k-NN graph has no boundary"


@pytest.mark.parametrize("method", ["kdtree", "brute"])
def test_periodic_knn_equals_brute_force_and_shifts_give_minimum_image(rng, method):
    lower, upper = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 1.0, 3.0])
    x = lower + rng.random((250, 3)) * (upper - lower)
    tess = jaxgeom.knn_graph(x, 8, box=(lower, upper), periodic=True, method=method)
    np.testing.assert_array_equal(np.asarray(tess.neighbors), brute_knn(x, 8, upper - lower))
    dx = np.asarray(jaxgeom.neighbor_displacements(tess))
    raw = x[np.asarray(tess.neighbors)] - x[:, None, :]
    wrapped = raw - (upper - lower) * np.round(raw / (upper - lower))
    np.testing.assert_allclose(dx, wrapped, atol=1e-12)
    assert np.abs(np.asarray(tess.neighbor_shifts)).max() == 1
    assert not bool(tess.overflow)


def test_knn_is_jittable_and_matches_host(rng):
    x = rng.random((200, 5))
    traced = jax.jit(lambda p: jaxgeom.knn_graph(p, 7))(x)
    np.testing.assert_array_equal(np.asarray(traced.neighbors), brute_knn(x, 7))


def test_knn_blocks_bound_memory(rng, monkeypatch):
    import jaxgeom.tessellation._knn as knn

    monkeypatch.setattr(knn, "TILE_ELEMENTS", 1000)  # forces 10-row blocks with a ragged last block
    x = rng.random((97, 2))
    tess = jaxgeom.knn_graph(x, 4, method="brute")
    np.testing.assert_array_equal(np.asarray(tess.neighbors), brute_knn(x, 4))


def test_knn_tiers_with_box(rng):
    x = rng.random((400, 2))
    tess = jaxgeom.knn_graph(x, 6, box=(0.0, 1.0))
    nbrs = np.asarray(tess.neighbors)
    radius = np.linalg.norm(x[nbrs[:, -1]] - x, axis=1)[:, None]
    tier0 = np.any((x - radius < 0) | (x + radius > 1), axis=1)
    tier1 = ~tier0 & tier0[nbrs].any(axis=1)
    np.testing.assert_array_equal(np.asarray(tess.tier), np.where(tier0, 0, np.where(tier1, 1, 2)))
    assert (np.asarray(tess.tier) == 2).sum() > 100


def test_periodic_knn_flags_ambiguous_images(rng):
    x = rng.random((12, 2))
    tess = jaxgeom.knn_graph(x, 10, box=(0.0, 1.0), periodic=True)
    assert bool(tess.overflow), "10 neighbours of 12 walkers reach beyond half the box"
