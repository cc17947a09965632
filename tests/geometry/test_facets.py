"""voronoi_facets against scipy's half-space intersection, the divergence theorem, and freud."""

import jax
import jax.numpy as jnp
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

        faces = {
            j: measure(x[j] - x[i], c) for j, (_, c) in zip([j for j in neighbors[i] if j < n], planes, strict=True)
        }
        centre = v.mean(0)
        pieces = [abs(np.linalg.det(v[s] - centre)) for s in hull.simplices]
        moment = sum(w * (centre + v[s].sum(0)) / (d + 1) for w, s in zip(pieces, hull.simplices, strict=True))
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


def test_boxed_3d_pieces_cut_by_their_one_wall_equal_scipy(rng, monkeypatch):
    """Chunks of 4 faces, so that many hold only pieces that reach one wall each: those are cut
    by that wall alone (counted as they run), and the cells still equal scipy's."""
    import jax

    from jaxgeom.geometry import _dualclip

    one_wall_cuts = []
    real_clip = _dualclip.clip_polygon

    def counted_clip(verts, count, lower, upper, tol, wall=None):
        if wall is not None:
            jax.debug.callback(lambda: one_wall_cuts.append(1))
        return real_clip(verts, count, lower, upper, tol, wall)

    monkeypatch.setattr(_dualclip, "FACE_CHUNK", 4)
    monkeypatch.setattr(_dualclip, "clip_polygon", counted_clip)
    jax.clear_caches()
    try:
        x = rng.uniform(0.0, 1.0, (120, 3))
        tess = jaxgeom.delaunay(x, box=(0.0, 1.0))
        facets = jaxgeom.voronoi_facets(tess)
        jax.block_until_ready(facets.areas)
    finally:
        jax.clear_caches()
    assert len(one_wall_cuts) > 0
    neighbors, n = np.asarray(tess.neighbors), len(x)
    for i, (faces, wall_faces, volume, centroid, vertices) in enumerate(halfspace_cells(x, neighbors, tess_box(3))):
        expected = [faces[j] if j < n else 0.0 for j in neighbors[i]]
        np.testing.assert_allclose(np.asarray(facets.areas)[i], expected, atol=1e-10)
        np.testing.assert_allclose(np.asarray(facets.wall_areas)[i], wall_faces, atol=1e-10)
        np.testing.assert_allclose(facets.volumes[i], volume, rtol=1e-10)
        np.testing.assert_allclose(facets.centroids[i], centroid, atol=1e-10)
        assert int(facets.n_vertices[i]) == vertices


def tess_box(d):
    return np.zeros(d), np.ones(d)


@pytest.mark.parametrize("length", [0, 1, 6, 16])
def test_running_count_is_the_cumulative_sum(length):
    """Sutherland-Hodgman's running count of kept vertices (additions, not XLA's
    reduce-window) equals jnp.cumsum, alone and under vmap as the clipping calls it."""
    from jaxgeom.geometry._dualclip import running_count

    flags = np.random.default_rng(length).random((50, length)) < 0.5
    expected = np.cumsum(flags, axis=1)
    np.testing.assert_array_equal(jax.vmap(running_count)(jnp.asarray(flags)), expected)
    if length:
        np.testing.assert_array_equal(running_count(jnp.asarray(flags[0])), expected[0])


def test_one_wall_cut_equals_the_cut_by_every_wall(rng):
    """`clip_polygon` by the one wall a triangle reaches equals the cut by all six walls."""
    import jax

    from jaxgeom.geometry._dualclip import clip_polygon, clip_tolerance, walls_reached

    lower, upper = jnp.asarray([-0.3, -0.5, -0.2]), jnp.asarray([0.7, 0.5, 0.8])
    tol = clip_tolerance(lower, upper)
    compared = 0
    for _ in range(60):
        triangle = jnp.asarray(rng.uniform(-0.25, 0.45, (3, 3)) + rng.normal(0, 0.2, 3))
        reached = np.asarray(walls_reached(triangle, 3, lower, upper, tol))
        if reached.sum() != 1:
            continue
        every = jax.jit(clip_polygon)(triangle, 3, lower, upper, tol)
        one = jax.jit(clip_polygon)(triangle, 3, lower, upper, tol, int(np.argmax(reached)))
        count = int(every[1])
        assert int(one[1]) == count
        np.testing.assert_allclose(np.asarray(one[0])[:count], np.asarray(every[0])[:count], atol=1e-15)
        np.testing.assert_array_equal(
            np.asarray(one[2])[:count, 0], np.asarray(every[2])[:count, int(np.argmax(reached))]
        )
        assert not np.asarray(every[2])[:count, reached == 0].any()  # on no other wall
        compared += 1
    assert compared >= 10


@pytest.mark.parametrize("kind", ["uniform", "lattice"])
def test_box_edges_are_measured_in_every_cell_that_holds_one(rng, kind):
    """`cells_near_box_edges` (the cells whose centres' bounding box reaches two walls of an
    edge) leaves out no cell that holds a piece of a box edge or a corner, and leaves out most
    of a uniform swarm's cells at the boundary; the box edges' measures equal those over every
    tier-0 cell."""
    import jax

    from jaxgeom.geometry import _dualclip
    from jaxgeom.tessellation._graph import simplex_vertices

    if kind == "uniform":
        x = rng.uniform(0.0, 1.0, (1500, 3))
    else:  # co-spherical walkers: vertices on the box edges and corners
        x = (np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / 8
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0))
    centres, ok, *_ = jax.jit(lambda t: _dualclip.dual_centres(simplex_vertices(t)))(tess)
    near = np.asarray(_dualclip.cells_near_box_edges(tess, centres, ok))
    every = jax.jit(_dualclip.box_edge_faces)(tess, tess.tier == 0)
    chosen = jax.jit(_dualclip.box_edge_faces)(tess, jnp.asarray(near))
    holds = np.asarray(every[2]).any(axis=1) | np.asarray(every[4]).any(axis=1)
    assert holds.any() and not (holds & ~near).any()
    if kind == "uniform":  # a lattice's flat simplices (centres anywhere) take every cell beside them
        assert near.sum() < 0.5 * int((tess.tier == 0).sum())
    for a, b in zip(every, chosen, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_boxed_cells_of_co_spherical_walkers_at_the_walls_equal_scipy():
    """3D cells clipped by the dual's pieces where degenerate configurations meet the walls:
    an FCC lattice with walkers on the walls (their cells' wall faces hold them; flat hull
    simplices in the walls' planes) and shifted off them (non-simple vertices at the walls,
    cells touching a wall or a corner at one vertex), and walkers crowded into a corner (hull
    far from three walls). Against scipy's half-space intersection, its duplicate vertices
    merged (scipy lists a vertex once per facet of the dual hull)."""
    m = 3
    cubic = (np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / m
    basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) / m
    cases = [((cubic[:, None, :] + basis[None] + shift).reshape(-1, 3)) % 1.0 for shift in (0.0, 0.1 / m)]
    cases.append(np.random.default_rng(1).uniform(0, 1, (60, 3)) ** 3)
    for x in cases:
        facets = jaxgeom.voronoi_facets(jaxgeom.delaunay(x, box=(0.0, 1.0)))
        n = len(x)
        for i in range(n):
            planes = [np.r_[x[j] - x[i], -(x[j] - x[i]) @ (x[i] + x[j]) / 2] for j in range(n) if j != i]
            planes += [np.r_[s * np.eye(3)[k], -max(s, 0.0)] for k in range(3) for s in (1.0, -1.0)]
            inner = x[i] + 1e-3 * (0.5 - x[i])  # scipy needs a point strictly inside
            found = HalfspaceIntersection(np.array(planes), inner).intersections
            vertices = found[np.unique(np.round(found, 9), axis=0, return_index=True)[1]]
            np.testing.assert_allclose(float(facets.volumes[i]), ConvexHull(vertices).volume, rtol=1e-10)
            assert int(facets.n_vertices[i]) == len(vertices), (i, x[i])
            walls = []
            for w in range(6):
                k, bound = w % 3, 1.0 if w < 3 else 0.0
                on = vertices[np.abs(vertices[:, k] - bound) < 1e-9][:, [a for a in range(3) if a != k]]
                walls.append(ConvexHull(on).volume if len(on) >= 3 and np.ptp(on, axis=0).min() > 1e-9 else 0.0)
            np.testing.assert_allclose(np.asarray(facets.wall_areas[i]), walls, atol=1e-12)


def test_boxed_cells_of_clustered_walkers_equal_scipy():
    """Five clusters with spacings 1e-4 .. 1 in a box 1 beyond them: needles from a tight
    cluster to a far walker are Delaunay simplices, not flat ones (measured by the longest
    edge cubed they were, and the hull's faces around them went wrong by up to 1e4x)."""
    rng = np.random.default_rng(12345)
    scales = np.array([1e-4, 1e-3, 1e-2, 1e-1, 1.0]) * 100 ** (1 / 3)
    x = np.concatenate(
        [c + s * rng.random((100, 3)) for c, s in zip(rng.uniform(-50, 50, (5, 3)), scales, strict=True)]
    )
    box = (x.min(axis=0) - 1.0, x.max(axis=0) + 1.0)
    tess = jaxgeom.delaunay(x, box=box)
    volumes = np.asarray(jaxgeom.voronoi_volumes(tess))
    expected = np.array([cell[2] for cell in halfspace_cells(x, np.asarray(tess.neighbors), box)])
    np.testing.assert_allclose(volumes.sum(), np.prod(box[1] - box[0]), rtol=1e-9)
    # slivers of the 1e-4 cluster cost their circumcentres digits (both sides)
    np.testing.assert_allclose(volumes, expected, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_facets(tess).volumes), volumes, rtol=1e-7)


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


@pytest.mark.parametrize(
    "kind", ["cubic periodic", "cubic periodic 8", "cubic boxed", "fcc periodic", "cubic jittered 1e-9"]
)
def test_3d_lattices_have_their_exact_cells(kind):
    """Co-spherical walkers: a cube's eight (and the FCC lattice's rhombic dodecahedron's
    fourteen) Voronoi vertices are shared by several Delaunay simplices, flat ones among them.
    Cubes of side 1/m: six faces of area 1/m^2, eight vertices, the centroid at the walker;
    the rhombic dodecahedron: twelve faces of area sqrt(2) a^2 / 8 (a the cubic cell's side
    over the 4 points of the FCC basis), fourteen vertices, volume a^3 / 4. A 1e-9 jitter splits
    each cube vertex into three (a simple polytope, 24 vertices, with tiny faces). At m = 8
    the periodic tie-break of 1e-9 spacings was once unresolved by Qhull: two slabs split
    cubes unalike and four cells lost 2-6% (`_tiles_the_box` and `_star_mismatch` now retry a
    larger one)."""
    m = 8 if kind.endswith(" 8") else 5
    g = (np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / m
    if kind.startswith("fcc"):
        basis = np.array([[0, 0, 0], [0.5, 0.5, 0], [0.5, 0, 0.5], [0, 0.5, 0.5]]) / m
        g = ((g[:, None, :] + basis[None]).reshape(-1, 3)) % 1.0
    if "jittered" in kind:
        g = g + 1e-9 * np.random.default_rng(0).normal(size=g.shape)
    tess = jaxgeom.delaunay(g, box=(0.0, 1.0), periodic="periodic" in kind)
    facets = jaxgeom.voronoi_facets(tess)
    rows = np.asarray(tess.tier) == 2 if "jittered" in kind else np.ones(len(g), bool)
    areas = np.concatenate([np.asarray(facets.areas), np.asarray(facets.wall_areas)], axis=1)[rows]
    counts = np.asarray(facets.n_vertices)[rows]
    if kind.startswith("fcc"):
        expected_area, faces, vertices, volume = np.sqrt(2) / 8 / m**2, 12, 14, 1 / (4 * m**3)
    else:
        expected_area, faces, vertices, volume = 1 / m**2, 6, 24 if "jittered" in kind else 8, 1 / m**3
    tol = 1e-6 if "jittered" in kind else 1e-10
    np.testing.assert_allclose(np.sort(areas, axis=1)[:, -faces:], expected_area, rtol=tol)
    np.testing.assert_allclose(np.sort(areas, axis=1)[:, :-faces], 0.0, atol=tol * expected_area)
    np.testing.assert_allclose(np.asarray(facets.volumes)[rows], volume, rtol=tol)
    np.testing.assert_allclose(np.asarray(facets.centroids)[rows], g[rows], atol=tol / m)
    assert (counts == vertices).all(), np.unique(counts, return_counts=True)


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
    ours = {
        (int(i), int(j)): float(a)
        for i, row, arow in zip(
            range(len(x)), np.asarray(tess.neighbors), np.asarray(jaxgeom.voronoi_facets(tess).areas), strict=True
        )
        for j, a in zip(row, arow, strict=True)
        if j < len(x)
    }
    theirs = {
        (int(i), int(j)): float(w)
        for i, j, w in zip(nlist.query_point_indices, nlist.point_indices, nlist.weights, strict=True)
        if w > 1e-12
    }
    assert set(theirs) <= set(ours)
    for pair, w in theirs.items():
        assert ours[pair] == pytest.approx(w, rel=1e-5, abs=1e-6)


@pytest.mark.parametrize(
    "kind, d",
    [
        ("periodic", 2),
        ("periodic", 3),
        ("open", 2),
        ("open", 3),
        ("boxed", 2),
        pytest.param("boxed", 3, marks=pytest.mark.slow),
    ],
)
def test_facet_gradients_equal_central_differences(rng, kind, d):
    """The dual's areas, volumes and centroids are smooth in the positions on a fixed graph:
    jax.grad of a weighted sum of them equals central differences (bounded cells only; in a
    box every cell, the clipped ones and their wall faces included; 3D boxed, ~75 s of
    reverse-mode compilation through the clipped pieces' chunks, in the slow tier)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    x = rng.random((150, d))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=kind == "periodic") if kind != "open" else jaxgeom.delaunay(x)
    inside = ~np.asarray(tess.hull) if kind == "open" else np.ones(len(x), bool)
    mask = np.asarray(tess.neighbor_mask) & inside[:, None] & inside[np.minimum(np.asarray(tess.neighbors), len(x) - 1)]
    w = np.random.default_rng(1).normal(size=mask.shape) * mask
    w_walls = np.random.default_rng(2).normal(size=(len(x), 2 * d))

    def total(points):
        f = jaxgeom.voronoi_facets(eqx.tree_at(lambda t: t.points, tess, points))
        return (
            jnp.sum(jnp.where(mask, f.areas, 0.0) * w)
            + jnp.sum(jnp.where(inside, f.volumes, 0.0))
            + jnp.sum(jnp.where(inside[:, None], f.centroids, 0.0) ** 2)
            + jnp.sum(f.wall_areas * w_walls)
        )

    p = jnp.asarray(x)
    grad = np.asarray(jax.grad(total)(p))
    # in a box, the walkers at the walls (their cells clipped, hull walkers among them) first
    order = np.argsort(np.asarray(tess.tier), kind="stable") if kind == "boxed" else np.arange(len(x))
    picks = [(i, c) for i in order[inside[order]][:6] for c in range(d)]
    h = 1e-6
    for i, c in picks:
        step = jnp.zeros_like(p).at[i, c].set(h)
        fd = (float(total(p + step)) - float(total(p - step))) / (2 * h)
        np.testing.assert_allclose(grad[i, c], fd, rtol=1e-5, atol=1e-7 * max(1.0, abs(fd)))


@pytest.mark.parametrize("d, periodic", [(2, False), (3, True), (3, False)])
def test_facets_of_rows_in_any_order_follow_their_slots(rng, d, periodic):
    """`delaunay` hands the dual rows sorted by neighbour (its slot search then skips the slot
    gather); a graph whose rows were shuffled (neighbours with their images) is sorted there
    first: each face follows its neighbour's slot, and every cell is unchanged."""
    import equinox as eqx

    x = rng.random((300, d))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=periodic) if periodic else jaxgeom.delaunay(x)
    order = np.argsort(rng.random(tess.neighbors.shape), axis=1)
    shuffled = eqx.tree_at(lambda t: t.neighbors, tess, jnp.take_along_axis(tess.neighbors, jnp.asarray(order), axis=1))
    if periodic:
        shifts = np.take_along_axis(np.asarray(tess.neighbor_shifts), order[..., None], axis=1)
        shuffled = eqx.tree_at(lambda t: t.neighbor_shifts, shuffled, jnp.asarray(shifts))
    before, after = jaxgeom.voronoi_facets(tess), jaxgeom.voronoi_facets(shuffled)
    np.testing.assert_array_equal(np.take_along_axis(np.asarray(before.areas), order, axis=1), after.areas)
    for name in ("volumes", "centroids", "n_vertices"):
        np.testing.assert_allclose(getattr(after, name), getattr(before, name), rtol=1e-12, atol=1e-15)


def test_boxed_rows_past_the_packed_wall_table_count_minus_one(rng):
    """Boxed 3D vertex counts read the faces' wall segments from a table packed to the rows'
    used widths, as many places as a triangulation has directed edges, 2 (2 N + S)
    (`_dual.packed_slots`). Rows shuffled (padding between neighbours: each row as wide as its
    last neighbour's slot) overflow it: the walkers whose rows lie past it count -1, the others
    their cell's vertices as before; faces, volumes and centroids are unchanged."""
    import equinox as eqx

    tess = jaxgeom.delaunay(rng.random((300, 3)), box=(0.0, 1.0))
    n, k = tess.neighbors.shape
    order = np.argsort(rng.random(tess.neighbors.shape), axis=1)
    shuffled = eqx.tree_at(lambda t: t.neighbors, tess, jnp.take_along_axis(tess.neighbors, jnp.asarray(order), axis=1))
    width = np.max(np.where(np.asarray(shuffled.neighbors) < n, np.arange(1, k + 1), 0), axis=1)
    fits = np.cumsum(width) <= min(n * k, 2 * (2 * n + tess.simplices.shape[0]))
    assert fits.any() and not fits.all()
    before, after = jaxgeom.voronoi_facets(tess), jaxgeom.voronoi_facets(shuffled)
    np.testing.assert_array_equal(after.n_vertices, np.where(fits, before.n_vertices, -1))
    assert (np.asarray(before.n_vertices)[fits] > 4).all()
    np.testing.assert_array_equal(np.take_along_axis(np.asarray(before.areas), order, axis=1), after.areas)
    for name in ("volumes", "centroids", "wall_areas"):
        np.testing.assert_allclose(getattr(after, name), getattr(before, name), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("bits", [1, 12, 20])
def test_the_cpu_order_is_numpys_stable_lexsort_under_jit_and_vmap(rng, bits):
    """`_order_by_key` (cell, quantum and entry packed in one uint64, sorted by numpy through a
    callback) gives the stable lexsort of (cell, quantum) pairs full of ties, quanta up to
    2^bits - 1 and cells up to what the 64 bits leave, and both in that order, jitted and
    vmapped."""
    import jax

    from jaxgeom.geometry import _dual

    m = 5000
    top = min(2**31, 2 ** (64 - bits - (m - 1).bit_length()))
    cells = rng.integers(0, top, (3, m), dtype=np.int64).astype(np.int32)
    quanta = rng.integers(0, 2**bits, (3, m), dtype=np.int64).astype(np.int32)
    cells[:, ::3], quanta[:, ::3] = cells[:, 1::3].max(), quanta[:, 1::3].max()  # ties
    want = np.stack([np.lexsort((quanta[b], cells[b])) for b in range(3)])
    batched = jax.jit(jax.vmap(lambda c, q: _dual._order_by_key(c, q, bits)))(jnp.asarray(cells), jnp.asarray(quanta))
    single = jax.jit(lambda c, q: _dual._order_by_key(c, q, bits))(jnp.asarray(cells[0]), jnp.asarray(quanta[0]))
    for got, c, q, wanted in [(batched, cells, quanta, want), (single, cells[0], quanta[0], want[0])]:
        np.testing.assert_array_equal(got[0], wanted)
        np.testing.assert_array_equal(got[1], np.take_along_axis(c, wanted, axis=-1))
        np.testing.assert_array_equal(got[2], np.take_along_axis(q, wanted, axis=-1))


@pytest.mark.parametrize("backend", ["cpu", "gpu"])
def test_the_order_sorts_by_cell_then_quantum_then_entry(rng, monkeypatch, backend):
    """`_order_by_cell_and_projection` against numpy's lexsort (and the cells and quanta it
    returns in that order), on keys full of ties (few cells,
    projections from a handful of values) and at the sizes where the radix passes' digit width
    changes: on the CPU one packed sort (`_order_by_key`, a callback), elsewhere the one-operand
    radix passes (`lax.sort`, run here on the CPU with the backend's name patched)."""
    import jax

    from jaxgeom.geometry import _dual

    monkeypatch.setattr(_dual.jax, "default_backend", lambda: backend)
    traced = str(
        jax.make_jaxpr(lambda c, p, r: _dual._order_by_cell_and_projection(c, p, r, 20))(
            jnp.zeros(1000, jnp.int32), jnp.zeros(1000), jnp.ones(1000)
        )
    )
    assert ("callback" in traced) == (backend == "cpu") and ("sort" in traced) == (backend == "gpu")
    for m, n in [(7, 3), (1000, 20), (70_000, 5_000), (300_000, 40_000)]:
        cells = rng.integers(0, n + 1, m).astype(np.int32)
        reach = np.where(cells < n, rng.uniform(0.5, 2.0, n + 1)[cells], 0.0)
        projection = rng.choice([-1.0, 0.0, 0.3, 1.0], m) * reach + rng.normal(0, 1e-3, m) * (rng.random(m) < 0.5)
        projection = np.clip(projection, -reach, reach)
        *arrays, bits = _dual._order_by_cell_and_projection(cells, projection, reach, n)
        order, quanta, quantum, sorted_cells, sorted_quanta = (np.asarray(a) for a in arrays)
        np.testing.assert_array_equal(order, np.lexsort((np.arange(m), quanta, cells)))
        np.testing.assert_array_equal(sorted_cells, cells[order])
        np.testing.assert_array_equal(sorted_quanta, quanta[order])
        assert quanta.max() < 2**bits
        same = cells[:, None] == cells[None, :100]  # quanta follow the projections within a cell
        below = projection[:, None] < projection[None, :100]
        assert not np.any(same & below & (quanta[:, None] > quanta[None, :100]))
        share = quantum / (2 * np.where(reach > 0, reach, 1.0))  # one quantum's share of its cell's range
        np.testing.assert_allclose(share, share[0], rtol=1e-12)
        assert np.log2(share[0]) == round(np.log2(share[0])) <= -10  # 2^-b, b >= QUANTUM_BITS[0]


@pytest.mark.parametrize("chunk", [4096, 7])
def test_vertex_counts_merge_every_close_centre_however_crowded(rng, monkeypatch, chunk):
    """`_vertex_counts` against a brute force: per cell, a centre within the tolerance (Chebyshev)
    of an earlier one (entry order) is not counted. Clusters of equal centres (1e-15 apart) are
    mixed with distinct centres whose projections crowd within the tolerance's quanta (they differ
    across the projection only), so close pairs lie far apart in the sorted order and the window
    alone would miss them; cells past the pairwise table (2 K + 8 entries) are -1. The entries
    near in the window compared in one chunk, and in chunks of 7 (the last part padding)."""
    from jaxgeom.geometry import _dual
    from jaxgeom.geometry._dual import MERGE_ULPS, PROJECTION, _vertex_counts

    monkeypatch.setattr(_dual, "NEAR_CHUNK", chunk)
    n, k, per_simplex = 40, 6, 4
    s = 150
    simplices = rng.integers(0, n, (s, per_simplex)).astype(np.int32)
    base = rng.normal(size=(6, 3))
    across = np.cross(PROJECTION, [0.0, 0.0, 1.0])  # projects to 0
    pick = rng.integers(0, 6, (s, per_simplex))
    offsets = base[pick] + rng.normal(0, 1e-15, (s, per_simplex, 3))
    crowd = rng.random((s, per_simplex)) < 0.4
    offsets[crowd] = base[0] + rng.integers(1, 30, crowd.sum())[:, None] * 1e-6 * across
    proper = rng.random((s, per_simplex)) < 0.95
    tess = jaxgeom.Tessellation(  # `_vertex_counts` reads the simplices and the capacity K alone
        points=jnp.zeros((n, 3)),
        neighbors=jnp.zeros((n, k), jnp.int32),
        tier=jnp.zeros(n, jnp.int8),
        hull=jnp.zeros(n, bool),
        simplices=jnp.asarray(simplices),
        neighbor_shifts=None,
        simplex_shifts=None,
        box=None,
        overflow=jnp.asarray(False),
    )
    counts = np.asarray(_vertex_counts(tess, jnp.asarray(offsets), jnp.asarray(proper)))

    cells, flat = np.where(proper, simplices, n).ravel(), offsets.reshape(-1, 3)
    for i in range(n):
        rows = flat[cells == i]
        limit = MERGE_ULPS * np.finfo(float).eps * np.abs(rows).max()
        distinct = sum(not any(np.abs(rows[b] - rows[a]).max() <= limit for a in range(b)) for b in range(len(rows)))
        assert counts[i] == (distinct if len(rows) <= 2 * k + 8 else -1), (i, len(rows))
    assert (counts == -1).any() and (counts > 0).any()


@pytest.mark.slow  # compile-bound (each program twice, ~10 s a kind): an internal equality, run by CI's slow tier
@pytest.mark.parametrize("kind", ["open", "boxed", "periodic"])
def test_3d_dual_in_blocks_equals_it_in_one(rng, kind, monkeypatch):
    """`_in_blocks` (the 3D dual's per-simplex stage SIMPLEX_BLOCK simplices at a time, the last
    block padded) gives every output and (open, periodic) the gradient of the unblocked stage:
    blocks of about 100 simplices whose count does not divide S, against one block of them all."""
    import equinox as eqx
    import jax

    from jaxgeom.geometry import _dual

    x = rng.random((120, 3))
    box = None if kind == "open" else (0.0, 1.0)
    tess = jaxgeom.delaunay(x, box=box, periodic=kind == "periodic")
    s = tess.simplices.shape[0]
    block = next(b for b in range(90, 130) if np.prod(_dual.block_layout(s, b)) > s)  # the last block padded
    assert s > 2 * block

    def run(points):
        f = jaxgeom.voronoi_facets(eqx.tree_at(lambda t: t.points, tess, points))
        finite = lambda a: jnp.where(jnp.isfinite(a), a, 0.0)  # noqa: E731
        total = jnp.sum(finite(f.areas) ** 2) + jnp.sum(finite(f.volumes)) + jnp.sum(finite(f.centroids) ** 2)
        return total, f

    outputs = {}
    for size in (s, block):
        monkeypatch.setattr(_dual, "SIMPLEX_BLOCK", size)
        jax.clear_caches()
        if kind == "boxed":  # the gradient's compilation through the clipped pieces takes ~40 s
            outputs[size] = (run(jnp.asarray(x))[1], np.zeros(1))
        else:
            (_, facets), grad = jax.value_and_grad(run, has_aux=True)(jnp.asarray(x))
            outputs[size] = (facets, np.asarray(grad))
    (one, grad_one), (blocked, grad_blocked) = outputs[s], outputs[block]
    assert_same_cells(blocked, one)
    np.testing.assert_allclose(grad_blocked, grad_one, rtol=1e-10, atol=1e-12)


@pytest.mark.slow  # compile-bound (the boxed program twice, ~13 s): an internal equality, run by CI's slow tier
def test_hull_sums_over_few_faces_equal_those_over_every_face(rng, monkeypatch):
    """`_few_or_all` sums the hull's faces alone when they are few (a uniform sample) and walks
    every face otherwise (a lattice's flat outer layer): both give the same boxed cells, forced
    one way (HULL_SHARE = 1: always few) and the other (HULL_SHARE huge and FEW_AT_LEAST 1:
    never few)."""
    import jax

    from jaxgeom.geometry import _dual

    tess = jaxgeom.delaunay(rng.random((150, 3)), box=(0.0, 1.0))
    cells = {}
    for share in (1, 10**9):
        monkeypatch.setattr(_dual, "HULL_SHARE", share)
        monkeypatch.setattr(_dual, "FEW_AT_LEAST", 1 if share > 1 else _dual.FEW_AT_LEAST)
        jax.clear_caches()
        cells[share] = jaxgeom.voronoi_facets(tess)
    assert_same_cells(cells[1], cells[10**9])


def assert_same_cells(got, want):
    """Two `VoronoiFacets` equal to rounding (1e-12), field by field."""
    for name in ("areas", "wall_areas", "volumes", "centroids", "n_vertices"):
        np.testing.assert_allclose(
            np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), rtol=1e-12, atol=1e-15
        )
