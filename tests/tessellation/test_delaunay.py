import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import brute_force_tiers, padded_sets, periodic_neighbor_sets, scipy_neighbor_sets

import jaxgeom
from jaxgeom.tessellation._graph import bucket_neighbors, bucket_simplices


@pytest.mark.parametrize("d, n", [(2, 400), (3, 300), (4, 120)])
def test_neighbors_equal_scipy(rng, d, n):
    x = rng.random((n, d))
    tess = jaxgeom.delaunay(x)
    assert padded_sets(tess.neighbors, n) == scipy_neighbor_sets(x)
    nbrs = np.asarray(tess.neighbors)
    assert np.all(np.diff(nbrs, axis=1) >= 0), "rows are sorted, padding last"
    assert tess.neighbors.dtype == jnp.int32 and tess.simplices.dtype == jnp.int32


@pytest.mark.parametrize("d", [2, 3])
def test_simplices_are_scipy_simplices(rng, d):
    from scipy.spatial import Delaunay

    x = rng.random((200, d))
    tess = jaxgeom.delaunay(x)
    simp = np.asarray(tess.simplices)
    real = simp[simp[:, 0] < 200]
    assert np.all(simp[len(real) :] == 200), "padding rows hold the sentinel"
    ours = {tuple(sorted(s)) for s in real.tolist()}
    theirs = {tuple(sorted(s)) for s in Delaunay(x).simplices.tolist()}
    assert ours == theirs
    assert int(tess.simplex_mask.sum()) == len(real)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("with_box", [False, True])
def test_tiers_match_brute_force(rng, d, with_box):
    x = rng.random((300, d))
    box = (np.zeros(d), np.ones(d)) if with_box else None
    tess = jaxgeom.delaunay(x, box=box)
    np.testing.assert_array_equal(np.asarray(tess.tier), brute_force_tiers(x, box))
    assert tess.tier.dtype == jnp.int8
    counts = np.bincount(np.asarray(tess.tier), minlength=3)
    assert counts.min() > 0, "the test set has walkers in every tier"


@pytest.mark.parametrize("batch", [None, 3])
@pytest.mark.parametrize("d", [2, 3])
def test_circumcentres_outside_the_hull_equal_scipys_point_location(rng, monkeypatch, d, batch):
    """The visibility walk against scipy's find_simplex, with its long walks in batches of the
    default size or of 3 simplices (many batches after one another)."""
    from scipy.spatial import Delaunay

    from jaxgeom.base._simplex import simplex_circumcenter
    from jaxgeom.tessellation import _delaunay

    if batch is not None:
        monkeypatch.setattr(_delaunay, "hull_walk_batch", lambda s_count: batch)
    x = rng.normal(size=(300, d))
    tess = jaxgeom.delaunay(x, triangulator="qhull")
    tri, perm, *_ = _delaunay.triangulate(x, "qhull")  # the same Qhull triangles, with their adjacency
    assert perm is None  # too few walkers to be sorted
    s = len(tri.simplices)
    np.testing.assert_array_equal(np.asarray(tess.simplices)[:s], tri.simplices)
    adjacency = jnp.asarray(_delaunay._pad_adjacency(tri.neighbors, tess.simplices.shape[0]))
    centers = jax.vmap(simplex_circumcenter)(_delaunay.simplex_coords(tess))
    # called eagerly (not under a cached jit), so the patched batch size holds
    outside = np.asarray(_delaunay.circumcenters_outside_hull(tess, adjacency, centers))
    expected = Delaunay(x).find_simplex(np.asarray(centers)[:s]) < 0  # any triangulation has the same hull
    assert 10 < expected.sum() < s - 10
    np.testing.assert_array_equal(outside[:s], expected)


def test_hull_flags_are_unbounded_cells(rng):
    from scipy.spatial import ConvexHull

    x = rng.random((150, 2))
    tess = jaxgeom.delaunay(x)
    expected = np.zeros(150, bool)
    expected[ConvexHull(x).vertices] = True
    np.testing.assert_array_equal(np.asarray(tess.hull), expected)


@pytest.mark.parametrize("d, n", [(2, 150), (3, 120)])
def test_periodic_neighbors_match_tiled_scipy(rng, d, n):
    lower, upper = -np.ones(d), np.linspace(1.0, 2.0, d)
    x = lower + rng.random((n, d)) * (upper - lower)
    tess = jaxgeom.delaunay(x, box=(lower, upper), periodic=True)
    nbrs, shifts = np.asarray(tess.neighbors), np.asarray(tess.neighbor_shifts)
    ours = [{(int(j), tuple(s.tolist())) for j, s in zip(nbrs[i], shifts[i], strict=True) if j < n} for i in range(n)]
    assert ours == periodic_neighbor_sets(x, lower, upper)
    assert np.all(np.asarray(tess.tier) == 2) and not np.asarray(tess.hull).any()


def test_periodic_small_elongated_box_uses_stored_shifts(rng):
    """Few walkers in a thin box: edges span more than half the box, where minimum image fails."""
    lower, upper = np.zeros(2), np.array([3.0, 0.4])
    x = lower + rng.random((9, 2)) * (upper - lower)
    tess = jaxgeom.delaunay(x, box=(lower, upper), periodic=True)
    nbrs, shifts = np.asarray(tess.neighbors), np.asarray(tess.neighbor_shifts)
    ours = [{(int(j), tuple(s.tolist())) for j, s in zip(nbrs[i], shifts[i], strict=True) if j < 9} for i in range(9)]
    assert ours == periodic_neighbor_sets(x, lower, upper, layers=3)
    dx = np.asarray(jaxgeom.neighbor_displacements(tess))[np.asarray(tess.neighbor_mask)]
    assert np.any(np.abs(dx[:, 1]) > 0.2), "some edge is longer than half the box"


def test_periodic_simplices_tile_the_torus(rng):
    x = rng.random((300, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    assert int(tess.simplex_mask.sum()) == 600, "a triangulated torus has exactly 2N triangles"
    assert int(tess.degree.sum()) == 1800, "and 3N edges"


def test_capacity_buckets_and_pinning(rng):
    x = rng.random((500, 3))
    tess = jaxgeom.delaunay(x)
    cap = tess.capacity
    assert cap.neighbors % 8 == 0 and cap.neighbors >= int(tess.degree.max())
    assert cap.simplices == bucket_simplices(int(tess.simplex_mask.sum()))
    same = jaxgeom.delaunay(x, capacity=tess)
    assert same.capacity == cap
    bigger = jaxgeom.delaunay(x, capacity=(cap.simplices + 5, cap.neighbors + 8))
    assert bigger.capacity == (cap.simplices + 5, cap.neighbors + 8)
    np.testing.assert_array_equal(padded_sets(bigger.neighbors, 500), padded_sets(tess.neighbors, 500))
    assert not bool(tess.overflow)


def test_bucket_ladders():
    assert [bucket_neighbors(k) for k in (1, 8, 9, 17, 66)] == [8, 8, 16, 24, 72]
    for n in [17, 100, 1000, 65537, 1_000_000]:
        cap = bucket_simplices(n)
        assert n <= cap <= 1.125 * n + 16
    assert len({bucket_simplices(n) for n in range(6000, 6400)}) <= 2


def test_2d_capacity_depends_on_n_only(rng):
    caps = {jaxgeom.delaunay(rng.random((400, 2))).capacity.simplices for _ in range(3)}
    assert caps == {800}


def test_float32_points_stay_float32(rng):
    x = rng.random((200, 2)).astype(np.float32)
    with jax.enable_x64(False):
        tess = jaxgeom.delaunay(x, box=(0, 1))
        assert tess.points.dtype == jnp.float32
        vol = jaxgeom.voronoi_volumes(tess)
        assert vol.dtype == jnp.float32
    assert padded_sets(tess.neighbors, 200) == scipy_neighbor_sets(x.astype(np.float64))


def test_tessellation_is_a_pytree_usable_under_jit(rng):
    tess = jaxgeom.delaunay(rng.random((100, 2)))
    leaves = jax.tree_util.tree_leaves(tess)
    assert all(isinstance(leaf, jax.Array) for leaf in leaves)
    degree_sum = jax.jit(lambda t: t.degree.sum())(tess)
    assert int(degree_sum) == int(np.sum(np.asarray(tess.neighbors) < 100))


@pytest.mark.parametrize("d, n", [(2, 900), (3, 1000)])
def test_periodic_slabs_and_skin_retries_stay_exact(rng, monkeypatch, d, n):
    """Several slabs and a too-thin first skin (forcing retries) still give the exact graph."""
    import jaxgeom.tessellation._delaunay as dl

    monkeypatch.setattr(dl.os, "cpu_count", lambda: 2)
    monkeypatch.setitem(dl.SKIN_SPACINGS, d, 1.0)
    calls = []
    real_triangulate = dl.triangulate
    monkeypatch.setattr(
        dl, "triangulate", lambda pts, name, **kw: calls.append(len(pts)) or real_triangulate(pts, name, **kw)
    )
    x = rng.random((n, d))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    nbrs, shifts = np.asarray(tess.neighbors), np.asarray(tess.neighbor_shifts)
    ours = [{(int(j), tuple(s.tolist())) for j, s in zip(nbrs[i], shifts[i], strict=True) if j < n} for i in range(n)]
    assert ours == periodic_neighbor_sets(x, np.zeros(d), np.ones(d), layers=1)
    assert len(calls) > 2, "more than one slab, and at least one retry"
    assert abs(float(jaxgeom.voronoi_volumes(tess).sum()) - 1.0) < 1e-9


@pytest.mark.parametrize("skin", [2.4, 2.6, 2.8, 3.0])
def test_periodic_lattice_translates_are_split_alike_at_any_skin(monkeypatch, skin):
    """An 8^3 cubic lattice (one slab): Qhull, not resolving the 1e-9 tie-break, can split
    translates of a co-spherical cube unalike. At a 2.6-spacing skin the kept simplices then
    still tiled the box, so the tiling check passed and 12 faces came out 0.0117-0.0195
    against 1/64; at 3.0 one walker's star lost a simplex. The star check (`_star_mismatch`)
    sees both and retries a larger tie-break: every skin gives the exact cells."""
    import jaxgeom.tessellation._delaunay as dl

    monkeypatch.setitem(dl.SKIN_SPACINGS, 3, skin)
    m = 8
    g = (np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / m
    tess = jaxgeom.delaunay(g, box=(0.0, 1.0), periodic=True, triangulator="qhull")
    facets = jaxgeom.voronoi_facets(tess)
    areas = np.sort(np.asarray(facets.areas), axis=1)
    np.testing.assert_allclose(areas[:, -6:], 1 / m**2, rtol=1e-10)
    np.testing.assert_allclose(areas[:, :-6], 0.0, atol=1e-12)
    assert (np.asarray(facets.n_vertices) == 8).all()
    assert (np.asarray(tess.neighbor_mask).sum(axis=1) == 6).all()


@pytest.mark.parametrize("d, n", [(2, 3000), (3, 3000), (4, 400)])
def test_the_star_check_passes_generic_walkers_at_the_first_tie_break(rng, monkeypatch, d, n):
    """`_star_mismatch` summed over the slabs is 0 mod 2^64 for walkers in general position
    (several slabs in 2D and 3D, every seam simplex checked), so they are triangulated once; a simplex
    dropped from the kept ones, or an owned walker's star simplex missing, makes it non-zero."""
    import jaxgeom.tessellation._delaunay as dl

    monkeypatch.setattr(dl.os, "cpu_count", lambda: 2)
    x = rng.random((n, d))
    y0 = x.copy()
    lengths = np.ones(d)
    spacing = (1.0 / n) ** (1.0 / d)
    slabs = []
    real_mismatch = dl._star_mismatch
    monkeypatch.setattr(dl, "_star_mismatch", lambda *a: slabs.append(a) or real_mismatch(*a))
    raw, volume, stars = dl._periodic_raw(y0, y0, lengths, spacing, "qhull")
    assert stars % 2**64 == 0 and dl._tiles_the_box(volume, lengths)
    assert len(slabs) >= (2 if d < 4 else 1)  # 4D: one slab at this N (its seams are the box's faces)
    ids, shifts, at, kept, owned = slabs[0]
    assert 0 < kept.sum() < len(kept) and (~owned).any()
    others = sum(real_mismatch(*a) for a in slabs[1:])
    assert (real_mismatch(*slabs[0]) + others) % 2**64 == 0
    one = np.flatnonzero(kept)[0]
    dropped = kept.copy()
    dropped[one] = False
    assert (real_mismatch(ids, shifts, at, dropped, owned) + others) % 2**64 != 0
    star = np.argwhere(owned)[0]
    missing = owned.copy()
    missing[tuple(star)] = False
    assert (real_mismatch(ids, shifts, at, kept, missing) + others) % 2**64 != 0


@pytest.mark.parametrize("d", [2, 3, 4])
def test_a_slabs_guards_enclose_its_region_at_their_reach(d):
    """`_guards`: 2^d points, each beyond `reach` of the region on every axis (outside every
    circumball a kept simplex can have when the reach exceeds the skin) and together
    enclosing the whole region (every corner of it inside their hull)."""
    from scipy.spatial import Delaunay

    import jaxgeom.tessellation._delaunay as dl

    lo, hi, reach = -0.1 * np.ones(d), np.array([0.6, 1.1, 1.1, 1.1][:d]), 0.1
    guards = dl._guards(lo, hi, reach)
    assert guards.shape == (2**d, d)
    assert np.all((guards <= lo - reach) | (guards >= hi + reach))
    corners = np.array(list(itertools.product(*zip(lo, hi, strict=True))))
    assert np.all(Delaunay(guards).find_simplex(corners) >= 0)


def test_a_circumball_wider_than_the_box_fails_the_skin_check_at_once(rng):
    """A sliver's circumball wider than the box's diagonal holds a whole period, so an image of
    some walker outside the region lies inside it: the check fails without listing the images
    its bounding box reaches (a clustered swarm's sliver once reached 212 box lengths out:
    int8 shifts overflowed, and slivers a little narrower took 40 s of image loops)."""
    import jaxgeom.tessellation._delaunay as dl

    y, lengths = rng.random((50, 3)), np.ones(3)
    sliver = np.array([[0.5, 0.5, 0.5], [0.6, 0.5, 0.5], [0.5, 0.6, 0.5], [0.56, 0.57, 0.5 + 1e-6]])
    _, radius = dl._circumballs(sliver[None])
    assert radius[0] > 100.0
    lo, hi = np.full(3, -0.1), np.full(3, 1.1)
    empty, widest_inside, _ = dl._check_circumballs(sliver, np.array([[0, 1, 2, 3]]), y, lengths, lo, hi)
    assert empty is False and widest_inside == 0.0


def test_the_skin_check_reports_the_widest_ball_inside_the_region(rng):
    """`_check_circumballs`' second value is the widest circumradius (by scipy's vertices and a
    brute-force equidistant point) among the simplices whose balls lie inside the region: the
    lower bound on the swarm's widest empty ball that sets the next skin after a failed check."""
    from scipy.spatial import ConvexHull, Delaunay

    import jaxgeom.tessellation._delaunay as dl

    y, lengths = rng.random((300, 3)), np.ones(3)
    lo, hi = np.full(3, -0.2), np.full(3, 1.2)
    ext, _, _ = dl._periodic_images(y, lengths, lo, hi)
    simplices = Delaunay(ext).simplices
    corners = ext[simplices]
    edges = corners[:, 1:] - corners[:, :1]
    centres = corners[:, 0] + np.linalg.solve(2.0 * edges, np.sum(edges**2, axis=2)[..., None])[..., 0]
    radii = np.linalg.norm(corners - centres[:, None], axis=2)
    assert np.allclose(radii, radii[:, :1], rtol=1e-8)
    inside = np.all((centres - radii[:, :1] >= lo) & (centres + radii[:, :1] <= hi), axis=1)
    assert 0 < inside.sum() < len(simplices)
    empty, widest_inside, volumes = dl._check_circumballs(ext, simplices, y, lengths, lo, hi)
    assert empty is False  # the hull's simplices hold images outside the region
    assert widest_inside == pytest.approx(radii[inside, 0].max(), rel=1e-9)
    # the third value, the tiling check's volumes: each simplex's, and together the hull's
    np.testing.assert_allclose(volumes, np.abs(np.linalg.det(edges)) / 6, rtol=1e-9)
    assert volumes.sum() == pytest.approx(ConvexHull(ext).volume, rel=1e-9)


@pytest.mark.slow
def test_periodic_clustered_swarm_with_wide_voids_builds_and_tiles_the_box(monkeypatch):
    """20 tight clusters in a periodic box (voids ~10x the mean spacing): the skin grows until
    the check passes (capped at the box's diagonal), and the volumes tile the box. This seed's
    first skins gave slivers with circumballs 212 box lengths wide (an OverflowError before).
    After a failed check the skin grows to the widest ball seen inside the region, so its two
    slabs take 5 triangulations (9 when the skin only grew 1.6x per failure)."""
    import jaxgeom.tessellation._delaunay as dl

    monkeypatch.setattr(dl.os, "cpu_count", lambda: 2)
    calls = []
    real_triangulate = dl.triangulate
    monkeypatch.setattr(
        dl, "triangulate", lambda pts, name, **kw: calls.append(len(pts)) or real_triangulate(pts, name, **kw)
    )
    rng = np.random.default_rng(500)
    n = 10_000
    centres = rng.random((20, 3))
    x = (centres[rng.integers(0, 20, n)] + 0.03 * rng.normal(size=(n, 3))) % 1.0
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True, triangulator="qhull")
    assert len(calls) <= 6
    volumes = np.asarray(jaxgeom.voronoi_volumes(tess))
    assert (volumes > 0).all() and abs(volumes.sum() - 1.0) < 1e-9


@pytest.mark.parametrize("d", [2, 3])
def test_morton_sorted_path_maps_indices_back(d):
    """Above MORTON_MIN_POINTS Qhull sees sorted points; results must be in the caller's order."""
    from scipy.spatial import ConvexHull, Delaunay

    from jaxgeom.tessellation._triangulators import MORTON_MIN_POINTS

    n = MORTON_MIN_POINTS + 5000
    x = np.random.default_rng(3).random((n, d))
    tess = jaxgeom.delaunay(x, triangulator="qhull")
    indptr, indices = Delaunay(x).vertex_neighbor_vertices
    ref = np.full(np.asarray(tess.neighbors).shape, n, np.int64)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    ref[rows, np.arange(len(indices)) - indptr[rows]] = indices
    np.testing.assert_array_equal(np.asarray(tess.neighbors), np.sort(ref, axis=1))
    hull = np.zeros(n, bool)
    hull[ConvexHull(x).vertices] = True
    np.testing.assert_array_equal(np.asarray(tess.hull), hull)
    assert int(tess.simplex_mask.sum()) == len(Delaunay(x).simplices)


@pytest.mark.parametrize("n", [50, 65_536, 65_537])
def test_simplex_edges_are_the_pairs_of_each_simplex(rng, n):
    """The host's neighbour pairs from the simplices against a set of all vertex pairs, with
    walker ids whose pair keys fit 32 bits (up to n = 2^16) and ids that need 64; from keys
    computed before (a triangulation's check), and those from some walkers alone."""
    from jaxgeom.tessellation._triangulators import _pair_keys, simplex_edges

    simplices = np.stack([rng.choice(n, 4, replace=False) for _ in range(300)]).astype(np.int32)
    simplices[0] = [n - 4, n - 3, n - 2, n - 1]  # the largest ids: all their bits in the key
    src, dst = simplex_edges(simplices, n)
    expected = sorted({(int(a), int(b)) for s in simplices for a in s for b in s if a != b})
    assert list(zip(src.tolist(), dst.tolist(), strict=True)) == expected
    src, dst = simplex_edges(simplices, n, _pair_keys(simplices, n))
    assert list(zip(src.tolist(), dst.tolist(), strict=True)) == expected
    sources = rng.random(n) < 0.3
    src, dst = simplex_edges(simplices, n, sources=sources)
    assert list(zip(src.tolist(), dst.tolist(), strict=True)) == [e for e in expected if sources[e[0]]]


@pytest.mark.parametrize("offset", [1e3, 1e6])
def test_float32_walkers_far_from_the_origin_are_refused(offset):
    """5000 walkers in [offset, offset + 1]^2: float32's rounding is 0.8% (1e3) and 840%
    (1e6) of their spacing; once they collapsed silently (17 distinct x at 1e6, tier-2 volumes
    summing to 1.003 instead of 0.875; a negative cell at 1e3). Refused, naming the fixes;
    centred, the same walkers give float64's volumes."""
    u = np.random.default_rng(0).random((5000, 2))
    with pytest.raises(ValueError, match=r"cannot be resolved in float32.*Centre the walkers.*jax_enable_x64"):
        jaxgeom.delaunay((u + offset).astype(np.float32))
    exact = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(u + offset)))  # float64 (the suite's x64)
    tess = jaxgeom.delaunay((u - 0.5).astype(np.float32))
    ours = np.asarray(jaxgeom.voronoi_volumes(tess))
    inner = np.asarray(tess.interior)
    assert ours.dtype == np.float32 and abs(ours[inner].sum() / exact[inner].sum() - 1) < 1e-5
    np.testing.assert_allclose(ours[inner], exact[inner], rtol=2e-3)


@pytest.mark.parametrize("case", ["3d", "3d box float32", "4d", "3d periodic", "2d periodic", "3d lattice"])
def test_host_builds_pad_walkers_to_a_bucket_and_equal_the_unpadded_build(rng, monkeypatch, case):
    """The jitted steps of a host build (circumcentres, tiers) run over walkers padded to
    `bucket_walkers(N)`, so swarms of nearby sizes share their programs; the graph is field
    for field the one built without padding (the 2D planar path: test_planar.py)."""
    from jaxgeom.tessellation import _delaunay

    d = int(case[0])
    x = (
        np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1).reshape(-1, 3) * 0.2 + 0.1
        if "lattice" in case
        else rng.random((301 if d < 4 else 90, d))
    )
    x = x.astype(np.float32) if "float32" in case else x
    kwargs = (
        dict(box=(0.0, 1.0), periodic=True) if "periodic" in case else dict(box=(0.0, 1.0)) if "box" in case else {}
    )
    assert _delaunay.bucket_walkers(len(x)) > len(x)
    padded = jaxgeom.delaunay(x, **kwargs)
    monkeypatch.setattr(_delaunay, "bucket_walkers", lambda n: n)
    plain = jaxgeom.delaunay(x, **kwargs)
    for field in (
        "points",
        "neighbors",
        "tier",
        "hull",
        "simplices",
        "neighbor_shifts",
        "simplex_shifts",
        "box",
        "overflow",
    ):
        got, want = getattr(padded, field), getattr(plain, field)
        assert (got is None) == (want is None), field
        if want is not None:
            assert got.shape == want.shape and got.dtype == want.dtype, field
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want), err_msg=field)


@pytest.mark.parametrize("periodic", [False, True])
def test_contact_filter_near_the_suspects_equals_the_global_one(rng, monkeypatch, periodic):
    """The zero-measure contacts of a co-spherical cube embedded in a random cloud (its face
    diagonals and body diagonals that Qhull adds) are found by testing only the simplices
    around the suspects (those sharing a circumcentre): the same neighbour rows as the test
    over every simplex (`LOCAL_CONTACTS = 0`), and every diagonal of the cube dropped."""
    from jaxgeom.tessellation import _delaunay

    corners = 0.5 + 0.04 * (np.stack(np.meshgrid(*[[-1, 1]] * 3, indexing="ij"), -1).reshape(-1, 3))
    cloud = rng.uniform(0, 1, (400, 3))
    cloud = cloud[np.linalg.norm(cloud - 0.5, axis=1) > 0.2]  # nothing inside the cube's sphere
    x = np.concatenate([corners, cloud])
    local = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=periodic)
    monkeypatch.setattr(_delaunay, "LOCAL_CONTACTS", 0.0)
    every = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=periodic)
    np.testing.assert_array_equal(np.asarray(local.neighbors), np.asarray(every.neighbors))
    rows = np.asarray(local.neighbors)[:8]
    for i in range(8):
        cube = set(rows[i][rows[i] < 8])
        assert cube == {j for j in range(8) if np.sum(np.abs(corners[j] - corners[i]) > 0) == 1}, (i, cube)


@pytest.mark.parametrize("periodic", [False, True])
def test_flat_simplices_centres_count_as_shared_without_a_cast_warning(rng, periodic):
    """A flat simplex's circumcentre is not finite: `_shared_centers` reports it shared (a
    suspect) instead of casting NaN to an integer key (numpy's RuntimeWarning, seen on a jittered
    cubic lattice), and still pairs the finite centres."""
    import warnings

    from jaxgeom.tessellation._delaunay import _shared_centers

    tess = jaxgeom.delaunay(rng.random((30, 3)), box=(0.0, 1.0), periodic=periodic)
    center = np.array([[0.2, 0.3, 0.4], [np.nan, 0.1, 0.1], [0.2, 0.3, 0.4], [np.inf, 0, 0], [0.7, 0.1, 0.5]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        shared = _shared_centers(center, tess)
    np.testing.assert_array_equal(shared, [True, True, True, True, False])


def test_periodic_lattice_split_into_slabs_keeps_its_exact_cells(monkeypatch):
    """Co-spherical walkers (an 8^3 cubic lattice) triangulated in several slabs: the slabs'
    cubes are split alike (the symbolic tie-break), so every cell is its cube: volume 1/512, six
    faces of area 1/64."""
    import jaxgeom.tessellation._delaunay as dl

    monkeypatch.setattr(dl.os, "cpu_count", lambda: 4)
    monkeypatch.setitem(dl.SLABS, 3, (1, 1))
    calls = []
    real_triangulate = dl.triangulate
    monkeypatch.setattr(
        dl, "triangulate", lambda pts, name, **kw: calls.append(len(pts)) or real_triangulate(pts, name, **kw)
    )
    m = 8
    g = (np.stack(np.meshgrid(*[np.arange(m)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) / m
    facets = jaxgeom.voronoi_facets(jaxgeom.delaunay(g, box=(0.0, 1.0), periodic=True, triangulator="qhull"))
    assert len(calls) >= 2, "several slabs"
    np.testing.assert_allclose(np.asarray(facets.volumes), 1 / m**3, rtol=1e-10)
    areas = np.sort(np.asarray(facets.areas), axis=1)
    np.testing.assert_allclose(areas[:, -6:], 1 / m**2, rtol=1e-10)
    np.testing.assert_allclose(areas[:, :-6], 0.0, atol=1e-10 / m**2)


def test_large_builds_hand_the_triangulators_freed_memory_back(rng, monkeypatch):
    """From `TRIM_WALKERS` walkers `delaunay` calls glibc's `malloc_trim` once the triangulator is
    done (Qhull's freed blocks otherwise stay in the process: 3.5 GiB at N = 1e6 periodic), and
    below it does not; where the C library has no `malloc_trim` the build goes on without it."""
    from jaxgeom.tessellation import _delaunay

    calls = []
    monkeypatch.setattr(_delaunay, "_malloc_trim", lambda: lambda pad: calls.append(pad))
    x = rng.random((200, 3))
    jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    assert calls == []
    monkeypatch.setattr(_delaunay, "TRIM_WALKERS", 200)
    jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
    jaxgeom.delaunay(x)
    assert calls == [0, 0]
    monkeypatch.setattr(_delaunay, "_malloc_trim", lambda: None)
    assert jaxgeom.delaunay(x).simplices.shape[1] == 4


@pytest.mark.parametrize("span", [1, 2, 100])
def test_periodic_rows_sort_by_neighbour_then_image(rng, span):
    """`_pad_periodic_neighbors` packs each slot's (neighbour, image) into one key: rows come
    out sorted by neighbour index, a neighbour seen at several images ordered by its shift (as
    the dual's row keys order them), padding last with no shift; wide shifts (large skins of
    sparse samples) take 64-bit keys."""
    from jaxgeom.tessellation._delaunay import RawGraph, _pad_periodic_neighbors

    n, k, d = (200 if span == 100 else 40), 12, 3  # span 100: 8 bits per axis, 64-bit keys from n = 128
    degree = rng.integers(1, k + 1, n)
    rows = np.repeat(np.arange(n), degree)
    cols = rng.integers(0, 6, rows.size)  # few distinct neighbours: many seen at several images
    shifts = rng.integers(-span, span + 1, (rows.size, d)).astype(np.int8)
    raw = RawGraph(np.zeros((0, d + 1), np.int32), None, rows, cols, shifts, np.zeros(n, bool))
    nbrs, out = _pad_periodic_neighbors(raw, n, k)
    assert nbrs.dtype == np.int32 and out.dtype == np.int8
    for i in range(n):
        mine = sorted((int(c), tuple(s.tolist())) for c, s in zip(cols[rows == i], shifts[rows == i], strict=True))
        got = [(int(c), tuple(s.tolist())) for c, s in zip(nbrs[i], out[i], strict=True)]
        assert got[: len(mine)] == mine
        assert got[len(mine) :] == [(n, (0,) * d)] * (k - len(mine))
