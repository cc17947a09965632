"""The graph lifecycle of a moving swarm (jaxgeom.swarm._rebuild): padding, the growth rule."""

import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.swarm._rebuild import (
    NEIGHBOR_HEADROOM,
    SIMPLEX_HEADROOM,
    allocate_graph,
    capacity_with_headroom,
    grown,
    pad_to_capacity,
)
from jaxgeom.tessellation import _delaunay as delaunay_module
from jaxgeom.tessellation._graph import bucket_neighbors, bucket_simplices


@pytest.mark.parametrize("d", [2, 3])
def test_padding_keeps_every_kernel_result_and_the_periodic_image_shifts(d):
    x = np.random.default_rng(0).random((150, d))
    tess = jaxgeom.delaunay(x, box=np.array([[0.0] * d, [1.0] * d]), periodic=True)
    cap = jaxgeom.Capacity(tess.capacity.simplices + 40, tess.capacity.neighbors + 16)
    padded = pad_to_capacity(tess, cap)
    assert padded.capacity == cap
    assert padded.neighbor_shifts.shape == padded.neighbors.shape + (d,)
    assert padded.simplex_shifts.shape == padded.simplices.shape + (d,)
    np.testing.assert_allclose(jaxgeom.voronoi_volumes(padded), jaxgeom.voronoi_volumes(tess), rtol=1e-12)
    np.testing.assert_allclose(
        np.sort(np.asarray(jaxgeom.edge_lengths(padded)), axis=1)[:, -tess.capacity.neighbors :],
        np.sort(np.asarray(jaxgeom.edge_lengths(tess)), axis=1),
        rtol=1e-12,
    )
    assert float(np.sum(jaxgeom.voronoi_volumes(padded))) == pytest.approx(1.0, rel=1e-12)


def test_one_growth_rule_for_allocation_and_overflow():
    x = np.random.default_rng(1).random((400, 3))
    fresh = jaxgeom.delaunay(x)
    cap = capacity_with_headroom(fresh)
    degree, count = int(np.max(fresh.degree)), int(np.sum(fresh.simplex_mask))
    assert cap == (
        bucket_simplices(int(np.ceil(SIMPLEX_HEADROOM * count))),
        bucket_neighbors(degree + NEIGHBOR_HEADROOM),
    )
    tess, grew, _, moved, _ = allocate_graph(x, "delaunay", 12, None)
    assert tess.capacity == cap and not grew and moved == 0
    bigger = grown(tess)
    assert bigger.capacity.neighbors >= cap.neighbors + NEIGHBOR_HEADROOM
    assert bigger.capacity.simplices >= SIMPLEX_HEADROOM * cap.simplices
    assert not bool(bigger.overflow)
    # A graph that does not fit the previous capacity grows by the same rule, never below it.
    small = jaxgeom.Capacity(cap.simplices // 2, 8)
    regrown, grew, _, _, _ = allocate_graph(x, "delaunay", 12, small)
    assert grew and regrown.capacity == cap
    np.testing.assert_allclose(jaxgeom.voronoi_volumes(regrown), jaxgeom.voronoi_volumes(fresh), rtol=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_a_graph_that_outgrows_its_capacity_is_triangulated_once(d, monkeypatch):
    x = np.random.default_rng(3).random((400, d))
    fresh = allocate_graph(x, "delaunay", 12, None).tess
    calls = []
    triangulate = delaunay_module.triangulate
    monkeypatch.setattr(delaunay_module, "triangulate", lambda *a, **k: calls.append(1) or triangulate(*a, **k))
    small = jaxgeom.Capacity(fresh.capacity.simplices // 2 if d == 3 else fresh.capacity.simplices, 4)
    regrown, grew, _, _, _ = allocate_graph(x, "delaunay", 12, small)
    assert len(calls) == 1 and grew
    assert regrown.capacity == capacity_with_headroom(fresh, small)
    assert np.array_equal(np.asarray(regrown.neighbors), np.asarray(fresh.neighbors))
    assert np.array_equal(np.asarray(regrown.tier), np.asarray(fresh.tier))
    calls.clear()
    same, grew, _, _, _ = allocate_graph(x, "delaunay", 12, regrown)
    assert len(calls) == 1 and not grew and same.capacity == regrown.capacity


def test_planar_graphs_keep_the_exact_simplex_bound():
    x = np.random.default_rng(2).random((300, 2))
    tess = allocate_graph(x, "delaunay", 12, None).tess
    assert tess.capacity.simplices == jaxgeom.delaunay(x).capacity.simplices
    assert grown(tess).capacity.simplices == tess.capacity.simplices
    assert jnp.all(grown(tess).neighbors[:, tess.capacity.neighbors :] == 300)
