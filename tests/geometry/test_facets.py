"""voronoi_facets against scipy's half-space intersection, the divergence theorem, and freud."""

import numpy as np
import pytest
from scipy.spatial import ConvexHull, HalfspaceIntersection

import jaxgeom


def halfspace_cells(x, neighbors, box=None):
    """Per walker, from scipy: ({neighbour: face measure}, {wall: face measure}, volume, centroid,
    vertex count), or None for an unbounded cell. Walls ordered as VoronoiFacets.wall_areas."""
    n, d = x.shape
    cells = []
    for i in range(n):
        planes = [(x[j] - x[i], (x[j] - x[i]) @ (x[i] + x[j]) / 2) for j in neighbors[i] if j < n]
        walls = []
        if box is not None:
            walls = [(np.eye(d)[k], box[1][k]) for k in range(d)] + [(-np.eye(d)[k], -box[0][k]) for k in range(d)]
        try:
            cut = HalfspaceIntersection(np.array([np.r_[a, -c] for a, c in planes + walls]), x[i])
            v = cut.intersections
            hull = ConvexHull(v)
        except Exception:  # noqa: BLE001 - unbounded: qhull reports it in several ways
            cells.append(None)
            continue
        if not np.all(np.isfinite(v)) or np.abs(v).max() > 1e6:
            cells.append(None)
            continue

        def measure(a, c):
            on = v[np.abs(v @ a - c) <= 1e-9 * np.linalg.norm(a) * max(1.0, np.abs(v).max())]
            if d == 2:
                return float(np.ptp(on @ np.array([-a[1], a[0]])) / np.linalg.norm(a)) if len(on) >= 2 else 0.0
            if len(on) < 3:
                return 0.0
            basis = np.linalg.svd(on - on.mean(0))[2][:2]
            try:
                return float(ConvexHull((on - on.mean(0)) @ basis.T).volume)
            except Exception:  # noqa: BLE001 - collinear: zero area
                return 0.0

        faces = {j: measure(x[j] - x[i], c) for j, (_, c) in zip([j for j in neighbors[i] if j < n], planes)}
        centre = v.mean(0)
        pieces = [abs(np.linalg.det(v[s] - centre)) for s in hull.simplices]
        moment = sum(w * (centre + v[s].sum(0)) / (d + 1) for w, s in zip(pieces, hull.simplices))
        cells.append((faces, [measure(a, c) for a, c in walls], hull.volume, moment / sum(pieces), len(v)))
    return cells


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("boxed", [False, True])
def test_facets_equal_scipy_half_space_intersection(rng, d, boxed):
    x = rng.uniform(0.0, 1.0, (150 if d == 2 else 100, d))
    box = (np.zeros(d), np.ones(d)) if boxed else None
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0) if boxed else None)
    facets = jaxgeom.voronoi_facets(tess)
    neighbors, n = np.asarray(tess.neighbors), len(x)
    areas, walls = np.asarray(facets.areas), np.asarray(facets.wall_areas)
    checked = 0
    for i, cell in enumerate(halfspace_cells(x, neighbors, box)):
        if cell is None or (not boxed and tess.hull[i]):  # a hull walker's cell is unbounded
            assert np.isnan(facets.volumes[i]) and facets.n_vertices[i] == -1 and np.isinf(areas[i]).any()
            continue
        faces, wall_faces, volume, centroid, vertices = cell
        for k, j in enumerate(neighbors[i]):
            expected = faces[j] if j < n else 0.0
            np.testing.assert_allclose(areas[i, k], expected, atol=1e-10)
        np.testing.assert_allclose(walls[i], wall_faces if boxed else 0.0, atol=1e-10)
        np.testing.assert_allclose(facets.volumes[i], volume, rtol=1e-10)
        np.testing.assert_allclose(facets.centroids[i], centroid, atol=1e-10)
        assert int(facets.n_vertices[i]) == vertices
        checked += 1
    assert checked >= (n if boxed else n // 2)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("kind", ["open", "box", "torus"])
def test_divergence_theorem_ties_faces_to_volumes(rng, d, kind):
    """sum_j a_ij |x_j - x_i| / (2d) (+ sum_walls a_w h_w / d) = V_i for every bounded cell."""
    x = rng.uniform(0.0, 1.0, (300 if d == 2 else 150, d))
    tess = jaxgeom.delaunay(x, box=None if kind == "open" else (0.0, 1.0), periodic=kind == "torus")
    facets = jaxgeom.voronoi_facets(tess)
    real = np.asarray(tess.neighbor_mask)
    half = np.linalg.norm(np.asarray(jaxgeom.neighbor_displacements(tess)), axis=-1) / 2
    total = np.sum(np.where(real, np.asarray(facets.areas) * half, 0.0), axis=1) / d
    if kind == "box":
        total += np.sum(np.asarray(facets.wall_areas) * np.c_[1.0 - x, x], axis=1) / d
    volumes = np.asarray(jaxgeom.voronoi_volumes(tess))
    bounded = np.isfinite(volumes)
    assert bounded.sum() >= (len(x) if kind != "open" else len(x) // 2)
    np.testing.assert_allclose(total[bounded], volumes[bounded], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(np.asarray(facets.volumes)[bounded], volumes[bounded], rtol=1e-10, atol=1e-14)
    if kind != "open":
        np.testing.assert_allclose(volumes.sum(), 1.0, rtol=1e-9)


def test_a_square_lattice_has_unit_faces_and_four_vertices():
    i, j = np.meshgrid(np.arange(8), np.arange(8))
    x = (np.c_[i.ravel(), j.ravel()] + 0.5) / 8
    facets = jaxgeom.voronoi_facets(jaxgeom.delaunay(x, box=(0.0, 1.0)))
    areas = np.asarray(facets.areas)
    np.testing.assert_allclose(areas[areas > 0], 1 / 8)
    assert (np.asarray(facets.n_vertices) == 4).all()
    np.testing.assert_allclose(np.asarray(facets.centroids), x, atol=1e-14)
    corner = int(np.flatnonzero((x[:, 0] < 0.1) & (x[:, 1] < 0.1))[0])
    np.testing.assert_allclose(np.asarray(facets.wall_areas)[corner], [0, 0, 1 / 8, 1 / 8])


def test_facets_refuse_graphs_without_cells(rng):
    with pytest.raises(ValueError, match="needs a Delaunay graph"):
        jaxgeom.voronoi_facets(jaxgeom.knn_graph(rng.random((50, 2)), 6))


@pytest.mark.parametrize("d", [2, 3])
def test_facet_areas_are_freuds_voronoi_neighbour_weights(rng, d):
    """freud (bench extra) weights its Voronoi neighbour list by the shared face's area (length in
    2D). freud holds positions in float32 (~3e-8 in this unit box): faces agree to ~3e-7
    (median), and to 1e-6 absolute where a small face loses its leading digits."""
    freud = pytest.importorskip("freud")
    x = rng.uniform(-0.5, 0.5, (400, d))
    tess = jaxgeom.delaunay(x, box=(-0.5, 0.5), periodic=True)
    voro = freud.locality.Voronoi()
    box = freud.box.Box.cube(1.0) if d == 3 else freud.box.Box.square(1.0)
    voro.compute((box, x if d == 3 else np.c_[x, np.zeros(len(x))]))
    nlist = voro.nlist
    ours = {(int(i), int(j)): float(a) for i, row, arow in zip(range(len(x)), np.asarray(tess.neighbors),
                                                              np.asarray(jaxgeom.voronoi_facets(tess).areas))
            for j, a in zip(row, arow) if j < len(x)}
    theirs = {(int(i), int(j)): float(w) for i, j, w in zip(nlist.query_point_indices, nlist.point_indices,
                                                           nlist.weights) if w > 1e-12}
    assert set(theirs) <= set(ours)
    for pair, w in theirs.items():
        assert ours[pair] == pytest.approx(w, rel=1e-5, abs=1e-6)
