import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom


def test_nan_and_inf_rejected(rng):
    x = rng.random((20, 2))
    x[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"`points` has NaN or inf.*\[3\]"):
        jaxgeom.delaunay(x)
    x[3, 1] = np.inf
    with pytest.raises(ValueError, match="NaN or inf"):
        jaxgeom.knn_graph(x, 3)


@pytest.mark.parametrize("shape", [(20,), (2, 3, 4), (20, 0)])
def test_wrong_shape_rejected(rng, shape):
    with pytest.raises(ValueError, match=r"`points` must have shape \(N, d\)"):
        jaxgeom.delaunay(np.zeros(shape))


@pytest.mark.parametrize("dtype", [np.int64, np.int32, bool, np.complex128])
def test_non_float_dtype_rejected(dtype):
    x = np.arange(20).reshape(10, 2).astype(dtype)
    with pytest.raises(TypeError, match="must be a float array.*astype"):
        jaxgeom.delaunay(x)


@pytest.mark.parametrize("d", [2, 3])
def test_too_few_points_rejected(rng, d):
    with pytest.raises(ValueError, match=rf"has {d + 1} walker\(s\).*at least {d + 2}"):
        jaxgeom.delaunay(rng.random((d + 1, d)))


def test_duplicate_points_rejected(rng):
    x = rng.random((30, 2))
    x[17] = x[4]
    with pytest.raises(ValueError, match=r"rows (4 and 17|17 and 4) are duplicates.*np.unique"):
        jaxgeom.delaunay(x)


def test_collinear_2d_rejected():
    t = np.linspace(0, 1, 12)
    with pytest.raises(ValueError, match="degenerate: all walkers are collinear"):
        jaxgeom.delaunay(np.stack([t, 2 * t + 1], axis=1))


def test_coplanar_3d_rejected(rng):
    uv = rng.random((30, 2))
    x = np.stack([uv[:, 0], uv[:, 1], uv[:, 0] + uv[:, 1]], axis=1)
    with pytest.raises(ValueError, match="degenerate: all walkers are coplanar"):
        jaxgeom.delaunay(x)


def test_qhull_errors_are_wrapped(monkeypatch, rng):
    from scipy.spatial import QhullError

    import jaxgeom.tessellation._triangulators as backends

    def failing(*args, **kwargs):
        raise QhullError("QH6154 Qhull precision error: initial simplex is flat")

    monkeypatch.setattr(backends, "Delaunay", failing)
    with pytest.raises(ValueError, match="degenerate for Delaunay.*QH6154"):
        jaxgeom.delaunay(rng.random((10, 2)), triangulator="qhull")


def test_points_outside_box_rejected(rng):
    x = rng.random((20, 2))
    x[5] = [1.5, 0.5]
    with pytest.raises(ValueError, match=r"1 walker\(s\) lie outside `box`.*\[5\]"):
        jaxgeom.delaunay(x, box=(0.0, 1.0))
    x[5] = [1.0, 0.5]
    jaxgeom.delaunay(x, box=(0.0, 1.0))  # closed box: the upper face is inside
    with pytest.raises(ValueError, match=r"outside `box` \[lower, upper\).*wrap periodic"):
        jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)


def test_bad_box_rejected(rng):
    x = rng.random((20, 2))
    with pytest.raises(ValueError, match="lower < upper"):
        jaxgeom.delaunay(x, box=(1.0, 0.0))
    with pytest.raises(ValueError, match="`box` must be \\(lower, upper\\)"):
        jaxgeom.delaunay(x, box=np.zeros((2, 3)))


def test_periodic_needs_box(rng):
    with pytest.raises(ValueError, match=r"`periodic=True` needs `box"):
        jaxgeom.delaunay(rng.random((20, 2)), periodic=True)
    with pytest.raises(ValueError, match=r"`periodic=True` needs `box"):
        jaxgeom.knn_graph(rng.random((20, 2)), 3, periodic=True)


@pytest.mark.parametrize("d", [1, 5, 8])
def test_dimension_out_of_range_points_to_knn(rng, d):
    with pytest.raises(ValueError, match=rf"dimension d={d}.*jaxgeom.knn_graph"):
        jaxgeom.delaunay(rng.random((40, d)))


@pytest.mark.parametrize("k", [0, -2, 20, 25])
def test_knn_k_out_of_range(rng, k):
    with pytest.raises(ValueError, match=rf"1 <= k < N = 20; got k={k}"):
        jaxgeom.knn_graph(rng.random((20, 3)), k)


def test_knn_k_must_be_int(rng, own_messages):
    with pytest.raises(TypeError, match="`k` must be a Python int"):
        jaxgeom.knn_graph(rng.random((20, 3)), 3.0)


def test_knn_unknown_method(rng):
    with pytest.raises(ValueError, match="unknown method 'fast'; valid values are 'auto', 'kdtree', 'brute'"):
        jaxgeom.knn_graph(rng.random((20, 3)), 3, method="fast")


def test_pinned_capacity_too_small(rng):
    x = rng.random((100, 2))
    with pytest.raises(ValueError, match=r"`capacity` \(50, 8\) is too small.*simplices >= \d+.*capacity=None"):
        jaxgeom.delaunay(x, capacity=(50, 8))
    with pytest.raises(TypeError, match="`capacity` must be"):
        jaxgeom.delaunay(x, capacity="big")


def test_delaunay_rejects_tracers(rng):
    x = jnp.asarray(rng.random((20, 2)))
    with pytest.raises(TypeError, match="runs on the host.*cannot be traced"):
        jax.jit(jaxgeom.delaunay)(x)


def test_degenerate_lattice_is_not_flagged_as_duplicate():
    """Cocircular lattice points are degenerate for Qhull but valid input."""
    i, j = np.meshgrid(np.arange(8.0), np.arange(6.0))
    x = np.stack([i.ravel(), 1.5 * j.ravel()], axis=1)
    tess = jaxgeom.delaunay(x)
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    np.testing.assert_allclose(vol[np.asarray(tess.tier) == 2], 1.5, rtol=1e-12)
