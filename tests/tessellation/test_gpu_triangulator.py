"""triangulator="cupy": the adapter and the device-side check on the CPU (scipy standing in for
CuPy's Delaunay), and, marked `gpu`, CuPy's gDel2D against CDT with exact in-circle arbitration."""

from fractions import Fraction

import jax
import numpy as np
import pytest
from scipy.spatial import Delaunay

import jaxgeom
from jaxgeom.tessellation import _triangulators as triangulators
from jaxgeom.tessellation._device_check import EULER, FLAT, LEFT_OUT, OK, OUT_OF_RANGE, planar_triangulation_status


def point_sets(rng):
    swarm = rng.normal(size=(40, 2))[rng.integers(0, 40, 3000)] + 1e-3 * rng.normal(size=(3000, 2))  # clones
    i, j = np.meshgrid(np.arange(30), np.arange(30))
    return {"uniform": rng.random((3000, 2)), "gaussian": rng.normal(size=(3000, 2)), "clustered": swarm,
            "lattice": np.c_[i.ravel(), j.ravel()].astype(float) + 0.25 * (j.ravel() % 2)[:, None]}


def test_the_adapter_reads_simplices_checks_them_and_derives_the_adjacency(rng):
    x = rng.random((2000, 2))
    tri = triangulators.gpu_triangulation(x, Delaunay, np)
    ref = Delaunay(x)
    np.testing.assert_array_equal(tri.simplices, ref.simplices)
    np.testing.assert_array_equal(tri.neighbors, ref.neighbors)  # our adjacency: scipy's
    assert tri.checked and triangulators.check_triangulation(tri, x) is None


def test_the_device_check_finds_each_defect(rng):
    x = rng.random((500, 2))
    s = Delaunay(x).simplices
    assert int(planar_triangulation_status(x, s)[0]) == OK
    assert int(planar_triangulation_status(x, s[:, [0, 2, 1]])[0]) == FLAT  # clockwise
    assert int(planar_triangulation_status(x, s[:-1])[0]) == EULER  # a triangle missing
    assert int(planar_triangulation_status(x, np.where(s == 7, 8, s))[0]) == LEFT_OUT
    assert int(planar_triangulation_status(x, np.where(s == 7, 500, s))[0]) == OUT_OF_RANGE
    doubled = np.vstack([s, s[:1]])  # an edge in three triangles, the count off
    assert int(planar_triangulation_status(x, doubled)[0]) == EULER


@pytest.mark.parametrize("name", ["uniform", "lattice"])
def test_the_device_check_accepts_cdt_on_every_point_set(rng, name):
    x = point_sets(rng)[name]
    tri = triangulators._cdt(x)
    assert int(planar_triangulation_status(x, tri.simplices)[0]) == OK


def test_a_failed_gpu_build_falls_back_to_cdt_and_says_so(rng, monkeypatch):
    x = rng.random((300, 2))

    def broken(points):
        raise RuntimeError("Euler's formula fails")

    monkeypatch.setitem(triangulators.BUILDERS, "cupy", broken)
    built = triangulators.triangulate(x, "cupy")
    assert "cupy raised RuntimeError" in built.fallback
    assert sorted(map(tuple, np.sort(built.tri.simplices, axis=1))) == sorted(
        map(tuple, np.sort(triangulators._cdt(x).simplices, axis=1)))


def test_cupy_is_refused_clearly_without_a_gpu_and_auto_passes_it_by():
    if triangulators.cuda_cupy_available():
        pytest.skip("this machine has a GPU with CuPy")
    with pytest.raises(ValueError, match=r"triangulator='cupy' is not installed: pip install \"jaxgeom\[cuda12\]\""):
        jaxgeom.delaunay(np.random.default_rng(0).random((50, 2)), triangulator="cupy")
    assert triangulators.resolve_triangulator("auto", 2) != "cupy"


def incircle(a, b, c, d) -> Fraction:
    """> 0 when d lies inside the circle through the counter-clockwise a, b, c; exact."""
    rows = [[Fraction(p[0]) - Fraction(d[0]), Fraction(p[1]) - Fraction(d[1])] for p in (a, b, c)]
    m = [[u, v, u * u + v * v] for u, v in rows]
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def locally_delaunay_everywhere(x, simplices, adjacency) -> bool:
    for t, (tri, across) in enumerate(zip(simplices, adjacency)):
        for k, other in enumerate(across):
            if other > t:
                opposite = next(v for v in simplices[other] if v not in tri)
                if incircle(*x[tri], x[opposite]) > 0:
                    return False
    return True


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["uniform", "gaussian", "clustered", "lattice"])
def test_cupy_gives_cdts_graph_or_an_equally_delaunay_one(rng, name):
    if not triangulators.cuda_cupy_available():
        pytest.skip("needs a CUDA GPU with CuPy (pip install \"jaxgeom[cuda12]\")")
    x = point_sets(rng)[name]
    gpu, cdt = triangulators._cupy(jax.numpy.asarray(x)), triangulators._cdt(x)
    ours, theirs = (set(map(tuple, np.sort(t.simplices, axis=1))) for t in (gpu, cdt))
    if ours != theirs:  # only co-circular quadruples may differ: both must be Delaunay, exactly
        assert locally_delaunay_everywhere(x, gpu.simplices, gpu.neighbors)
        assert locally_delaunay_everywhere(x, cdt.simplices, cdt.neighbors)
    a, b = jaxgeom.delaunay(x, triangulator="cupy"), jaxgeom.delaunay(x, triangulator="cdt")
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(a)), np.asarray(jaxgeom.voronoi_volumes(b)),
                               rtol=1e-9, equal_nan=True)
