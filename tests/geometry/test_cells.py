import numpy as np
import pytest
from helpers import scipy_voronoi_volumes
from scipy.spatial import Voronoi

import jaxgeom


@pytest.mark.parametrize("a, b", [(1.0, 1.0), (1.0, 1.7), (0.4, 2.0)])
def test_shape_distortion_of_rectangular_lattice(a, b):
    i, j = np.meshgrid(np.arange(12.0), np.arange(10.0))
    tess = jaxgeom.delaunay(np.stack([a * i.ravel(), b * j.ravel()], axis=1))
    rho = np.asarray(jaxgeom.shape_distortion(tess))
    interior = np.asarray(tess.tier) == 2
    assert interior.sum() > 40
    np.testing.assert_allclose(rho[interior], a / np.hypot(a, b), rtol=1e-12)
    assert np.all(np.isnan(rho[np.asarray(tess.tier) == 0]))


def test_shape_distortion_of_hexagonal_lattice():
    i, j = np.meshgrid(np.arange(14), np.arange(14))
    x = np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2], -1).reshape(-1, 2).astype(float)
    tess = jaxgeom.delaunay(2.5 * x)
    rho = np.asarray(jaxgeom.shape_distortion(tess))
    interior = np.asarray(tess.tier) == 2
    np.testing.assert_allclose(rho[interior], np.sqrt(3) / 2, rtol=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_shape_distortion_and_vertex_variance_match_scipy_voronoi(rng, d):
    x = rng.random((300, d))
    tess = jaxgeom.delaunay(x)
    vor = Voronoi(x)
    rho = np.asarray(jaxgeom.shape_distortion(tess))
    var = np.asarray(jaxgeom.vertex_distance_variance(tess))
    nbrs = np.asarray(tess.neighbors)
    for i in np.flatnonzero(np.asarray(tess.tier) > 0)[:60]:
        verts = vor.vertices[vor.regions[vor.point_region[i]]]
        dist = np.linalg.norm(verts - x[i], axis=1)
        r_in = 0.5 * np.min(np.linalg.norm(x[nbrs[i][nbrs[i] < 300]] - x[i], axis=1))
        assert abs(rho[i] - r_in / dist.max()) < 1e-10
        assert abs(var[i] - dist.var()) < 1e-10 * dist.max() ** 2


def test_volume_distortion_matches_numpy(rng):
    x = rng.random((500, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0))
    ref = scipy_voronoi_volumes(x)[np.asarray(tess.tier) == 2]
    expected = np.var(ref / ref.mean())
    assert abs(float(jaxgeom.volume_distortion(tess)) - expected) < 1e-12
    weights = rng.random(500) + 0.5
    riem = np.asarray(jaxgeom.voronoi_volumes(tess)) * weights
    ref_riem = riem[np.asarray(tess.tier) == 2]
    assert abs(float(jaxgeom.volume_distortion(tess, riem)) - np.var(ref_riem / ref_riem.mean())) < 1e-12


@pytest.mark.parametrize("d", [2, 3])
def test_raychaudhuri_under_uniform_scaling_is_exact(rng, d):
    x = rng.random((400, d))
    s, dt = 1.05, 0.1
    before, after = jaxgeom.delaunay(x), jaxgeom.delaunay(s * x)
    valid = (before.tier == 2) & (after.tier == 2)
    theta = np.asarray(
        jaxgeom.raychaudhuri_expansion(jaxgeom.voronoi_volumes(before), jaxgeom.voronoi_volumes(after), dt, valid=valid)
    )
    ok = np.asarray(valid)
    np.testing.assert_allclose(theta[ok], (s**d - 1) / dt, rtol=1e-10)
    assert np.all(np.isnan(theta[~ok]))
    estimate = float(jaxgeom.mean_curvature_estimate(theta))
    assert abs(estimate + (s**d - 1) / dt) < 1e-9 * (s**d - 1) / dt, "masked walkers are excluded, not zero"


def test_raychaudhuri_bad_input():
    with pytest.raises(ValueError, match="`dt` must be a finite number > 0"):
        jaxgeom.raychaudhuri_expansion(np.ones(3), np.ones(3), 0.0)
    with pytest.raises(ValueError, match="differ in shape"):
        jaxgeom.raychaudhuri_expansion(np.ones(3), np.ones(4), 0.1)
