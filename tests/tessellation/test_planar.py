"""The 2D fan walk (jaxgeom.tessellation._planar) against scipy's vertex_neighbor_vertices and hull."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import ConvexHull, Delaunay

from jaxgeom.tessellation._delaunay import planar_tessellation, planar_triangles
from jaxgeom.tessellation._planar import _merge_network, fan_neighbors, sort_rows
from jaxgeom.tessellation._triangulators import QHULL_OPTIONS


def scipy_rows(tri, n, k_cap):
    indptr, indices = tri.vertex_neighbor_vertices
    rows = np.full((n, k_cap), n, np.int64)
    for i in range(n):
        row = np.sort(indices[indptr[i] : indptr[i + 1]])[:k_cap]
        rows[i, : len(row)] = row
    return rows


def padded(tri, n, s_cap):
    simplices = np.full((s_cap, 3), n, np.int32)
    simplices[: len(tri.simplices)] = tri.simplices
    adjacency = np.full((s_cap, 3), -1, np.int32)
    adjacency[: len(tri.simplices)] = tri.neighbors
    return jnp.asarray(simplices), jnp.asarray(adjacency)


@pytest.mark.parametrize("layout", ["random", "grid", "clustered", "random, rows sorted by the network"])
def test_fan_walk_equals_scipy_rows_and_hull(rng, layout):
    """Random points; a square grid (cocircular quadruples, collinear hull points); tight pairs."""
    if layout == "random":
        x = rng.random((500, 2))
    elif "network" in layout:
        from jaxgeom.tessellation._planar import MERGE_NETWORK_MIN_ROWS

        x = rng.random((MERGE_NETWORK_MIN_ROWS + 1, 2))
    elif layout == "grid":
        x = np.stack(np.meshgrid(np.arange(15.0), np.arange(12.0)), axis=-1).reshape(-1, 2)
    else:
        centres = rng.random((150, 2))
        x = np.concatenate([centres, centres + 1e-3 * rng.normal(size=centres.shape)])
    n = len(x)
    tri = Delaunay(x, qhull_options=QHULL_OPTIONS)
    simplices, adjacency = padded(tri, n, 2 * n + 7)
    rows, hull, complete = jax.jit(fan_neighbors, static_argnums=(2, 3))(simplices, adjacency, n, 24)
    np.testing.assert_array_equal(np.asarray(rows), scipy_rows(tri, n, 24))
    expected_hull = np.zeros(n, bool)
    expected_hull[tri.convex_hull.ravel()] = True  # vertices of boundary edges, collinear ones included
    np.testing.assert_array_equal(np.asarray(hull), expected_hull)
    assert np.asarray(complete).all()
    if layout == "random":
        np.testing.assert_array_equal(np.flatnonzero(expected_hull), np.sort(ConvexHull(x).vertices))


def test_rows_longer_than_capacity_are_flagged(rng):
    x = rng.random((300, 2))
    x[0] = [0.5, 0.5]
    angles = np.linspace(0, 2 * np.pi, 20, endpoint=False)
    x[1:21] = 0.5 + 0.01 * np.stack([np.cos(angles), np.sin(angles)], axis=1)  # degree 20 at walker 0
    tri = Delaunay(x, qhull_options=QHULL_OPTIONS)
    simplices, adjacency = padded(tri, 300, 600)
    rows, _, complete = fan_neighbors(simplices, adjacency, 300, 16)
    degree = np.diff(tri.vertex_neighbor_vertices[0])
    np.testing.assert_array_equal(np.asarray(complete), degree <= 16)
    fitting = degree <= 16
    np.testing.assert_array_equal(np.asarray(rows)[fitting], scipy_rows(tri, 300, 16)[fitting])
    tess = planar_tessellation(jnp.asarray(x), simplices, adjacency, None, k_cap=16)
    assert bool(tess.overflow)


def test_walker_in_no_triangle_is_incomplete(rng):
    x = rng.random((40, 2))
    tri = Delaunay(x, qhull_options=QHULL_OPTIONS)
    keep = ~np.any(tri.simplices == 7, axis=1)  # drop walker 7's fan (adjacency left as is)
    simplices = np.where(keep[:, None], tri.simplices, 40).astype(np.int32)
    adjacency = np.asarray(tri.neighbors, np.int32)
    rows, hull, complete = fan_neighbors(jnp.asarray(simplices), jnp.asarray(adjacency), 40, 16)
    assert not bool(complete[7]) and not bool(hull[7])
    assert np.all(np.asarray(rows)[7] == 40)


@pytest.mark.parametrize("k", range(1, 13))
def test_merge_network_sorts_every_zero_one_input(k):
    """0-1 principle: a comparator network sorts everything iff it sorts all 2^k 0-1 inputs."""
    bits = np.array(list(itertools.product([0, 1], repeat=k)), np.int32).reshape(-1, k)
    out = np.asarray(sort_rows([jnp.asarray(bits[:, j]) for j in range(k)], network=True))
    np.testing.assert_array_equal(out, np.sort(bits, axis=1))
    assert all(0 <= i < j < k for i, j in _merge_network(k))


@pytest.mark.parametrize("network", [True, None])
@pytest.mark.parametrize("k", [16, 24, 32])
def test_sort_rows_on_random_rows(rng, k, network):
    a = rng.integers(0, 50, size=(2000, k)).astype(np.int32)
    out = jax.jit(lambda a: sort_rows([a[:, j] for j in range(k)], network=network))(jnp.asarray(a))
    np.testing.assert_array_equal(np.asarray(out), np.sort(a, axis=1))


def test_the_network_sorts_from_its_row_count_on(monkeypatch):
    from jaxgeom.tessellation import _planar

    monkeypatch.setattr(_planar, "MERGE_NETWORK_MIN_ROWS", 100)
    ops = lambda n: len(jax.make_jaxpr(lambda c: sort_rows(c))(jnp.zeros((16, n), jnp.int32)).eqns)  # noqa: E731
    assert ops(99) < 10 < 100 < ops(100)  # one sort, against the network's min/max pairs


def test_planar_triangles_pads_and_checks_capacity(rng):
    from jaxgeom.tessellation._delaunay import CapacityError

    x = rng.random((100, 2))
    simplices, adjacency, cap, _ = planar_triangles(x)
    assert cap.simplices == 200 and simplices.shape == adjacency.shape == (200, 3)
    n_real = len(Delaunay(x).simplices)
    assert np.all(simplices[n_real:] == 100) and np.all(adjacency[n_real:] == -1)
    degree = np.diff(Delaunay(x).vertex_neighbor_vertices[0])
    with pytest.raises(CapacityError, match=f"neighbors >= {degree.max()}"):
        planar_triangles(x, (200, int(degree.max()) - 1))


def test_delaunay_pads_walkers_to_a_bucket_and_equals_the_unpadded_program(rng):
    """`jaxgeom.delaunay` in 2D runs `planar_tessellation` over walkers padded to
    `bucket_walkers(N)`: field for field the unpadded program's graph, also with a box, a
    pinned capacity, float32 and a square grid, and overflow for rows past the capacity; swarms in one bucket
    compile it once."""
    import jaxgeom
    from jaxgeom.tessellation._delaunay import _planar_from_host, _planar_rows
    from jaxgeom.tessellation._graph import bucket_walkers

    grid = np.c_[np.repeat(np.arange(8), 8), np.tile(np.arange(8), 8)][:57] * 0.1 + 0.01
    cases = [
        (rng.random((113, 2)), None, None),
        (rng.random((120, 2)), (0.0, 1.0), None),
        (grid, None, None),
        (rng.random((117, 2)).astype(np.float32), None, None),
        (rng.random((115, 2)), None, (240, 16)),
    ]
    assert bucket_walkers(113) == bucket_walkers(120) == 120 and bucket_walkers(57) == 60
    for x, box, capacity in cases:
        tess = jaxgeom.delaunay(x, box=box, capacity=capacity, triangulator="qhull")
        simplices, adjacency, cap, _ = planar_triangles(x, capacity)
        b = None if box is None else jnp.asarray(np.array(box)[:, None] * np.ones(2), tess.points.dtype)
        ref = planar_tessellation(
            jnp.asarray(x), jnp.asarray(simplices), jnp.asarray(adjacency), b, k_cap=cap.neighbors
        )
        for field in ("points", "neighbors", "tier", "hull", "simplices", "box", "overflow"):
            got, want = getattr(tess, field), getattr(ref, field)
            assert (got is None) == (want is None), field
            if want is not None:
                assert got.shape == want.shape and got.dtype == want.dtype, field
                np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=field)
        assert not bool(tess.overflow)
    x = rng.random((113, 2))
    simplices, adjacency, _, _ = planar_triangles(x)
    assert bool(_planar_from_host(x, simplices, adjacency, None, 4).overflow)  # rows of degree > 4
    misses = _planar_rows._cache_size()
    jaxgeom.delaunay(rng.random((118, 2)))
    jaxgeom.delaunay(rng.random((114, 2)))
    assert _planar_rows._cache_size() == misses  # 113 and 120 walkers compiled the program for their bucket
