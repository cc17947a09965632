"""`spatial_dims=k`: the graph of the first k coordinates, the rest carried along."""

import jax
import numpy as np
import pytest
from helpers import brute_knn
from scipy.spatial import Delaunay

import jaxgeom


def _edges(simplices, n):
    s = np.asarray(simplices)
    s = s[(s < n).all(axis=1)]
    return {tuple(sorted(e)) for tri in s for e in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[0], tri[2]))}


def test_delaunay_of_the_first_two_of_four_coordinates_is_scipys_planar_graph(rng):
    x = rng.random((300, 4))
    tess = jaxgeom.delaunay(x, spatial_dims=2, box=(np.zeros(4), np.ones(4)))
    assert tess.dim == 2 and tess.points.shape == (300, 2)
    np.testing.assert_array_equal(np.asarray(tess.carried), x[:, 2:])
    np.testing.assert_array_equal(np.asarray(tess.all_coordinates), x)
    assert _edges(tess.simplices, 300) == _edges(Delaunay(x[:, :2]).simplices, 300)
    np.testing.assert_array_equal(np.asarray(tess.box), [[0, 0], [1, 1]])
    volumes = np.asarray(jaxgeom.voronoi_volumes(tess))
    np.testing.assert_allclose(volumes.sum(), 1.0, rtol=1e-10)  # the unit square, not a 4D box


def test_delaunay_of_three_of_five_coordinates_matches_the_three_dimensional_graph(rng):
    x = rng.random((200, 5))
    cut = jaxgeom.delaunay(x, spatial_dims=3)
    plain = jaxgeom.delaunay(x[:, :3])
    np.testing.assert_array_equal(np.asarray(cut.neighbors), np.asarray(plain.neighbors))
    np.testing.assert_array_equal(np.asarray(cut.carried), x[:, 3:])


def test_all_coordinates_tessellated_carries_nothing(rng):
    x = rng.random((100, 3))
    tess = jaxgeom.delaunay(x, spatial_dims=3)
    assert tess.carried is None
    np.testing.assert_array_equal(np.asarray(tess.neighbors), np.asarray(jaxgeom.delaunay(x).neighbors))


@pytest.mark.parametrize("method", ["kdtree", "brute"])
def test_knn_of_the_first_coordinates_is_brute_force_on_them(rng, method):
    x = rng.random((250, 6))
    tess = jaxgeom.knn_graph(x, 7, spatial_dims=2, method=method)
    np.testing.assert_array_equal(np.asarray(tess.neighbors), brute_knn(x[:, :2], 7))
    np.testing.assert_array_equal(np.asarray(tess.carried), x[:, 2:])


def test_knn_with_spatial_dims_traces(rng):
    x = rng.random((120, 4))
    graph = jax.jit(lambda p: jaxgeom.knn_graph(p, 5, spatial_dims=3, method="brute"))(x)
    np.testing.assert_array_equal(np.asarray(graph.neighbors), brute_knn(x[:, :3], 5))
    np.testing.assert_array_equal(np.asarray(graph.carried), x[:, 3:])


@pytest.mark.parametrize("k", [0, 1, 5])
@pytest.mark.parametrize("build", ["delaunay", "knn"])
def test_spatial_dims_outside_two_to_d_is_refused(rng, k, build):
    x = rng.random((50, 4))
    call = (
        (lambda: jaxgeom.delaunay(x, spatial_dims=k))
        if build == "delaunay"
        else (lambda: jaxgeom.knn_graph(x, 4, spatial_dims=k))
    )
    with pytest.raises(ValueError, match=r"spatial_dims.*\[2, 4\]"):
        call()


def test_spatial_dims_must_be_an_int(rng):
    with pytest.raises(TypeError, match="spatial_dims"):
        jaxgeom.delaunay(rng.random((50, 3)), spatial_dims=2.0)
