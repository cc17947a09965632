import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg

import jaxgeom


def dense_normalized_laplacian(tess, length_scale):
    """Independent dense reference: W from all listed edges, symmetrised, then I - D^-1/2 W D^-1/2."""
    x, nbrs, n = np.asarray(tess.points), np.asarray(tess.neighbors), tess.n_points
    w = np.zeros((n, n))
    for i in range(n):
        for j in nbrs[i][nbrs[i] < n]:
            w[i, j] = np.exp(-np.sum((x[j] - x[i]) ** 2) / (2 * length_scale**2))
    w = 0.5 * (w + w.T) if tess.simplices is None else w
    s = 1 / np.sqrt(w.sum(axis=1))
    return np.eye(n) - s[:, None] * w * s[None, :]


@pytest.mark.parametrize("d, n", [(2, 1500), (3, 800)])
def test_spectral_gap_equals_dense_eigvalsh(rng, d, n):
    tess = jaxgeom.delaunay(rng.random((n, d)))
    ell = 3.0 * float(
        np.mean(
            np.min(np.where(np.asarray(tess.neighbor_mask), np.asarray(jaxgeom.edge_lengths(tess)), np.inf), axis=1)
        )
    )
    ref = np.linalg.eigvalsh(dense_normalized_laplacian(tess, ell))[:6]
    np.testing.assert_allclose(np.asarray(jaxgeom.spectral_gap(tess)), ref, atol=1e-8)
    np.testing.assert_allclose(np.asarray(jaxgeom.spectral_gap(tess, length_scale=ell)), ref, atol=1e-8)


def test_spectral_gap_of_a_knn_graph_uses_the_symmetrised_weights(rng):
    tess = jaxgeom.knn_graph(rng.random((600, 3)), 7)
    ref = np.linalg.eigvalsh(dense_normalized_laplacian(tess, 0.2))[:4]
    np.testing.assert_allclose(np.asarray(jaxgeom.spectral_gap(tess, k=4, length_scale=0.2)), ref, atol=1e-8)


def test_cycle_graph_closed_form():
    n = 60
    theta = 2 * np.pi * np.arange(n) / n
    tess = jaxgeom.knn_graph(np.stack([np.cos(theta), np.sin(theta)], axis=1), 2)
    expected = np.sort(1 - np.cos(2 * np.pi * np.arange(n) / n))[:7]
    np.testing.assert_allclose(np.asarray(jaxgeom.spectral_gap(tess, k=7, weights="uniform")), expected, atol=1e-12)


def test_laplacian_matvec_matches_scipy_operator(rng):
    tess = jaxgeom.knn_graph(rng.random((300, 2)), 5)
    lap = jaxgeom.graph_laplacian(tess)
    v = rng.random((300, 3))
    product = jax.jit(lambda op, u: op.matvec(u))(lap, jnp.asarray(v))  # the operator is a pytree
    np.testing.assert_allclose(np.asarray(product), lap.to_scipy() @ v, atol=1e-14)


@pytest.mark.slow
def test_lobpcg_agrees_with_scipy_at_1e4_in_float64():
    tess = jaxgeom.delaunay(np.random.default_rng(7).random((10_000, 2)))
    ref = np.asarray(jaxgeom.spectral_gap(tess))
    ours = np.asarray(jaxgeom.spectral_gap(tess, method="lobpcg"))
    assert np.isfinite(ours).all()
    np.testing.assert_allclose(ours[1:], ref[1:], rtol=1e-6)


def test_lobpcg_flags_non_convergence_with_nan(rng):
    tess = jaxgeom.delaunay(rng.random((2000, 2)))
    out = np.asarray(jaxgeom.spectral_gap(tess, method="lobpcg", maxiter=5))
    assert out[0] == 0.0 and np.isnan(out[1:]).any()


@pytest.mark.parametrize("d", [2, 3])
def test_nested_dissection_eliminates_every_separator_after_its_pieces(rng, d):
    """Fill-reducing invariant: an edge never joins two different pieces of the same
    level, and a separator vertex comes after every vertex of the piece it splits."""
    from jaxgeom.geometry._spectral import _separator_levels, nested_dissection_order
    from jaxgeom.tessellation._triangulators import morton_codes

    x = rng.random((5000, d))
    matrix = jaxgeom.graph_laplacian(jaxgeom.delaunay(x)).to_scipy()
    order = nested_dissection_order(x, matrix)
    assert np.array_equal(np.sort(order), np.arange(len(x)))
    position = np.argsort(order)
    code, n_bits = morton_codes(x)
    edges = scipy.sparse.triu(matrix, 1).tocoo()
    depth = int(np.ceil(np.log2(len(x) / 32)))
    level = _separator_levels(code, n_bits, depth, edges.row, edges.col)
    assert 0 < np.sum(level < depth) < len(x)
    a, b = np.where(level[edges.row] <= level[edges.col], (edges.row, edges.col), (edges.col, edges.row))
    shift = (n_bits - level[a]).astype(np.uint64)
    assert np.array_equal(code[a] >> shift, code[b] >> shift)
    ancestor = level[a] < level[b]
    assert np.all(position[a][ancestor] > position[b][ancestor])


def test_nested_dissection_factor_has_less_fill_than_colamd(rng):
    x = rng.random((20_000, 2))
    matrix = jaxgeom.graph_laplacian(jaxgeom.delaunay(x)).to_scipy()
    shifted = (matrix + 1e-3 * scipy.sparse.identity(len(x))).tocsc()
    order = jaxgeom.geometry._spectral.nested_dissection_order(x, matrix)
    ours = scipy.sparse.linalg.splu(shifted[order][:, order].tocsc(), permc_spec="NATURAL", diag_pivot_thresh=0.0)
    colamd = scipy.sparse.linalg.splu(shifted)
    assert ours.L.nnz + ours.U.nnz < 0.9 * (colamd.L.nnz + colamd.U.nnz)


def test_disconnected_knn_graph_has_zero_gap(rng):
    x = np.concatenate([rng.random((200, 2)), rng.random((200, 2)) + 50.0])
    gaps = np.asarray(jaxgeom.spectral_gap(jaxgeom.knn_graph(x, 6), k=3))
    assert abs(gaps[1]) < 1e-10 and gaps[2] > 1e-4


@pytest.mark.parametrize("graph", ["delaunay", "knn"])
def test_geodesic_methods_agree_and_dominate_straight_lines(rng, graph):
    x = rng.random((1500, 2))
    tess = jaxgeom.delaunay(x) if graph == "delaunay" else jaxgeom.knn_graph(x, 8)
    sources = [0, 17, 999]
    dijkstra = np.asarray(jaxgeom.geodesic_distances(tess, sources, method="dijkstra"))
    bellman = np.asarray(jaxgeom.geodesic_distances(tess, sources, method="bellman_ford"))
    np.testing.assert_allclose(bellman, dijkstra, rtol=1e-10, atol=0)
    straight = np.linalg.norm(x[None, :, :] - x[sources][:, None, :], axis=-1)
    assert np.all(dijkstra >= straight - 1e-12)
    assert np.isfinite(dijkstra).all()


def test_geodesics_with_a_metric_and_unreachable_walkers(rng):
    x = np.concatenate([rng.random((150, 2)), rng.random((150, 2)) + 30.0])
    tess = jaxgeom.knn_graph(x, 5)

    def metric(p):
        return jnp.diag(jnp.array([1.0 + p[1] ** 2, 2.0]))

    dij = np.asarray(jaxgeom.geodesic_distances(tess, 3, metric=metric, method="dijkstra"))
    bf = np.asarray(jaxgeom.geodesic_distances(tess, 3, metric=metric, method="bellman_ford"))
    assert np.isinf(dij[0, 150:]).all() and np.isinf(bf[0, 150:]).all()
    np.testing.assert_allclose(bf[0, :150], dij[0, :150], rtol=1e-10)


def test_grad_through_bellman_ford_matches_finite_difference(rng):
    tess = jaxgeom.delaunay(rng.random((400, 2)))

    def total(a):
        metric = lambda p: (1.0 + a * p[0] ** 2) * jnp.eye(2) + 0.3 * a * jnp.array([[0.0, 1.0], [1.0, 0.0]])  # noqa: E731
        return jnp.sum(jaxgeom.geodesic_distances(tess, jnp.array([5, 40]), metric=metric, method="bellman_ford"))

    grad = float(jax.grad(total)(0.4))
    h = 1e-6
    fd = (float(total(0.4 + h)) - float(total(0.4 - h))) / (2 * h)
    assert np.isfinite(grad) and abs(grad - fd) < 1e-6 * abs(fd)


def test_graph_proxy_bad_input(rng):
    tess = jaxgeom.delaunay(rng.random((40, 2)))
    with pytest.raises(ValueError, match=r"`sources` must lie in \[0, N\) = \[0, 40\)"):
        jaxgeom.geodesic_distances(tess, [3, 40])
    with pytest.raises(ValueError, match="`sources` must be an int or a 1-D sequence"):
        jaxgeom.geodesic_distances(tess, [0.5])
    with pytest.raises(ValueError, match="unknown method 'astar'; valid values are 'heat', 'dijkstra', 'bellman_ford'"):
        jaxgeom.geodesic_distances(tess, 0, method="astar")
    with pytest.raises(ValueError, match="unknown mode 'half'"):
        jaxgeom.geodesic_distances(tess, 0, mode="half")
    with pytest.raises(ValueError, match=r"1 <= k < N = 40; got 40"):
        jaxgeom.spectral_gap(tess, k=40)
    with pytest.raises(ValueError, match="`length_scale` must be a finite number > 0"):
        jaxgeom.spectral_gap(tess, length_scale=0.0)
    with pytest.raises(ValueError, match="unknown weights 'gauss'; valid values are 'kernel', 'uniform'"):
        jaxgeom.graph_laplacian(tess, weights="gauss")
    with pytest.raises(ValueError, match="unknown method 'arpack'"):
        jaxgeom.spectral_gap(tess, method="arpack")
