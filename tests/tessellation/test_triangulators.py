"""Host triangulators (jaxgeom.tessellation._triangulators): every backend against Qhull, and
against exact arithmetic where they disagree; the cheap check; the fallback to Qhull, counted."""

import itertools
import warnings
from fractions import Fraction

import numpy as np
import pytest

import jaxgeom
import jaxgeom.tessellation._triangulators as backends
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.tessellation._triangulators import (
    CoincidentPointsError,
    check_triangulation,
    installed,
    resolve_triangulator,
    triangulate,
)

OTHERS = [(name, d) for name in ("cdt", "shull") for d in backends.DIMENSIONS[name]]
CASES = [
    pytest.param(
        name,
        d,
        id=f"{name}-{d}d",
        marks=() if installed(name) else pytest.mark.skip(reason=f"{name} is not installed ({backends.INSTALL[name]})"),
    )
    for name, d in OTHERS
]


def simplex_set(tess) -> set:
    s = np.asarray(tess.simplices)[np.asarray(tess.simplex_mask)]
    if tess.simplex_shifts is None:
        return {tuple(sorted(r)) for r in s.tolist()}
    shifts = np.asarray(tess.simplex_shifts)[np.asarray(tess.simplex_mask)]
    return {
        tuple(sorted(zip(r.tolist(), map(tuple, sh.tolist()), strict=True))) for r, sh in zip(s, shifts, strict=True)
    }


def neighbor_sets(tess) -> list:
    n = tess.n_points
    nbrs = np.asarray(tess.neighbors)
    if tess.neighbor_shifts is None:
        return [set(r[r < n].tolist()) for r in nbrs]
    shifts = np.asarray(tess.neighbor_shifts)
    return [
        {(int(j), tuple(s.tolist())) for j, s in zip(r, sh, strict=True) if j < n}
        for r, sh in zip(nbrs, shifts, strict=True)
    ]


def clustered(rng, n: int, d: int) -> np.ndarray:
    """Five clusters whose walker spacings span 1e-4 .. 1 (1e4 x)."""
    scales = np.array([1e-4, 1e-3, 1e-2, 1e-1, 1.0]) * (n / 5) ** (1 / d)
    centers = rng.uniform(-50, 50, (5, d))
    return np.concatenate([c + s * rng.random((n // 5, d)) for c, s in zip(centers, scales, strict=True)])


def swarm_after_cloning(d: int) -> np.ndarray:
    """Positions of a simulated swarm with cloning (clones sit next to their companions)."""
    x = np.random.default_rng(5).uniform(-3, 3, (300, d))
    state = jaxgeom.init_swarm(rastrigin, x, triangulator="qhull")
    final, history = jaxgeom.simulate(
        rastrigin, state, jaxgeom.SwarmParams(dt=0.05, nu=0.3), n_steps=8, observe=("n_clones",)
    )
    assert history["n_clones"].sum() > 0
    return np.asarray(final.positions)


def lifted_det(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """det of the rows (p_i - q, |p_i - q|^2), i = 0..d: zero where q lies on the circumsphere
    of the simplex p, with one sign inside and the other outside (float)."""
    rows = p - q[:, None, :]
    return np.linalg.det(np.concatenate([rows, (rows**2).sum(-1, keepdims=True)], axis=-1))


def exact_det(m: list) -> Fraction:
    if len(m) == 1:
        return m[0][0]
    return sum((-1) ** j * m[0][j] * exact_det([row[:j] + row[j + 1 :] for row in m[1:]]) for j in range(len(m)))


def exact_lifted_det(p: np.ndarray, q: np.ndarray) -> Fraction:
    rows = [[Fraction(float(a)) - Fraction(float(b)) for a, b in zip(v, q, strict=True)] for v in p]
    return exact_det([r + [sum(c * c for c in r)] for r in rows])


def exact_delaunay_violations(x: np.ndarray, simplices: np.ndarray) -> int:
    """Interior faces of a triangulation whose opposite vertex lies strictly inside the other
    simplex's circumsphere, decided exactly (fractions) wherever float is not sure. None:
    the triangulation is Delaunay (locally Delaunay everywhere suffices)."""
    d1 = simplices.shape[1]
    owners = {}
    for t, simplex in enumerate(simplices.tolist()):
        for k in range(d1):
            owners.setdefault(frozenset(simplex[:k] + simplex[k + 1 :]), []).append((t, simplex[k]))
    pairs = np.array([(t, w) for pair in owners.values() if len(pair) == 2 for (t, _), (_, w) in (pair, pair[::-1])])
    t_idx, w_idx = pairs.T
    p = x[simplices[t_idx]]
    inside_sign = np.sign(lifted_det(p, p.mean(axis=1)))  # the centroid is inside the circumsphere
    value = lifted_det(p, x[w_idx]) * inside_sign
    unsure = np.abs(value) < 1e-6 * (np.abs(p).max() + 1.0) ** (2 * d1)
    sure = int((value[~unsure] > 0).sum())
    return sure + sum(
        exact_lifted_det(x[simplices[t]], x[w]) * sign > 0
        for t, w, sign in zip(t_idx[unsure], w_idx[unsure], inside_sign[unsure], strict=True)
    )


# --- the same graph as Qhull ----------------------------------------------------------------


@pytest.mark.parametrize("name, d", CASES)
@pytest.mark.parametrize("layout", ["plain", "boxed", "periodic"])
@pytest.mark.parametrize("sample", ["uniform", "gaussian"])
def test_same_graph_as_qhull_in_general_position(rng, name, d, layout, sample):
    n = 700 if d == 2 else 400
    x = rng.random((n, d)) if sample == "uniform" else np.clip(0.5 + 0.15 * rng.normal(size=(n, d)), 0.01, 0.99)
    kw = {} if layout == "plain" else dict(box=(0.0, 1.0), periodic=layout == "periodic")
    ref, ours = (jaxgeom.delaunay(x, triangulator=t, **kw) for t in ("qhull", name))
    assert simplex_set(ours) == simplex_set(ref)
    assert neighbor_sets(ours) == neighbor_sets(ref)
    np.testing.assert_array_equal(np.asarray(ours.tier), np.asarray(ref.tier))
    np.testing.assert_allclose(jaxgeom.voronoi_volumes(ours), jaxgeom.voronoi_volumes(ref), rtol=1e-10)


@pytest.mark.parametrize("name, d", CASES)
def test_clustered_swarms_are_exactly_delaunay(rng, name, d):
    """Spacings spanning 1e4x, and a simulated swarm with clones: where the backend and Qhull
    disagree, exact in-sphere tests decide, and the backend must be the one that is right."""
    for x in (clustered(rng, 1000, d), swarm_after_cloning(d)):
        box = (x.min(axis=0) - 1.0, x.max(axis=0) + 1.0)
        ours, ref = (jaxgeom.delaunay(x, triangulator=t, box=box) for t in (name, "qhull"))
        # the cells clipped to the box tile it, whoever is right (3D slivers of the 1e-4 cluster
        # cost float64 digits in their circumcentres: Qhull's graph misses by 4e-7 there)
        volume = np.prod(box[1] - box[0])
        assert abs(float(jaxgeom.voronoi_volumes(ours).sum()) / volume - 1) < (1e-9 if d == 2 else 1e-6)
        assert exact_delaunay_violations(x, np.asarray(ours.simplices)[np.asarray(ours.simplex_mask)]) == 0
        if simplex_set(ours) != simplex_set(ref):
            assert exact_delaunay_violations(x, np.asarray(ref.simplices)[np.asarray(ref.simplex_mask)]) > 0
        else:
            np.testing.assert_allclose(jaxgeom.voronoi_volumes(ours), jaxgeom.voronoi_volumes(ref), rtol=1e-8)


def test_the_exact_check_finds_a_non_delaunay_flip(rng):
    x = rng.random((200, 2))
    s = np.asarray(jaxgeom.delaunay(x, triangulator="qhull").simplices)[:-1]
    s = s[s[:, 0] < 200]
    assert exact_delaunay_violations(x, s) == 0
    tri = backends.qhull(x)[0]
    t, k = np.argwhere(tri.neighbors >= 0)[0]
    o = tri.neighbors[t, k]
    a, b = (v for v in tri.simplices[t] if v != tri.simplices[t, k])
    w = next(v for v in tri.simplices[o] if v not in (a, b))
    flipped = np.delete(tri.simplices, [t, o], axis=0)
    flipped = np.vstack([flipped, [tri.simplices[t, k], a, w], [tri.simplices[t, k], w, b]])
    assert exact_delaunay_violations(x, flipped) > 0


@pytest.mark.parametrize("name, d", CASES)
@pytest.mark.parametrize("periodic", [False, True])
def test_lattices_keep_exact_volumes_and_positive_measure_neighbours(name, d, periodic):
    side = 9 if d == 2 else 5
    x = (np.array(list(itertools.product(range(side), repeat=d)), float) + 0.5) / side
    kw = dict(box=(0.0, 1.0), periodic=periodic)
    ours, ref = (jaxgeom.delaunay(x, triangulator=t, **kw) for t in (name, "qhull"))
    # Co-spherical cells split either way: contacts between two hull walkers are all kept (the
    # rule of Tessellation.neighbors), so only the other walkers' neighbours are unique.
    inside = ~np.asarray(ref.hull)
    assert [s for s, keep in zip(neighbor_sets(ours), inside, strict=True) if keep] == [
        s for s, keep in zip(neighbor_sets(ref), inside, strict=True) if keep
    ]
    volumes = np.asarray(jaxgeom.voronoi_volumes(ours))
    # Every cell is a cube of side 1/side, the boxed hull cells included (their clipping once
    # gave 0.009-0.01 for 0.008 in 3D with every backend: tests/geometry/test_volumes.py)
    np.testing.assert_allclose(volumes, side**-d, rtol=1e-9)
    if periodic:
        assert all(len(s) == 2 * d for s in neighbor_sets(ours))


def test_cdt_drops_its_zero_area_triangles_along_a_collinear_hull_side():
    """A sheared hexagonal lattice: its bottom row is an exactly collinear hull side, and CDT
    keeps zero-area triangles along it. (Once: they failed the check and Qhull built the graph,
    warned.) The adapter drops them; the graph passes the check, and its neighbours and volumes
    are Qhull's, but for contacts between two hull walkers (co-circular ties, kept by the rule
    of Tessellation.neighbors)."""
    i, j = np.meshgrid(np.arange(14), np.arange(14))
    z = np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2], -1).reshape(-1, 2) @ np.array([[1.0, 0.0], [0.15, 1.0]])
    tri = backends._cdt(z)
    assert check_triangulation(tri, z) is None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback warning
        ours = jaxgeom.delaunay(z, triangulator="cdt")
    ref = jaxgeom.delaunay(z, triangulator="qhull")
    hull = np.asarray(ours.hull) | np.asarray(ref.hull)
    for k, (a, b) in enumerate(zip(neighbor_sets(ours), neighbor_sets(ref), strict=True)):
        assert all(hull[m] and hull[k] for m in a ^ b), k
    np.testing.assert_allclose(
        np.asarray(jaxgeom.voronoi_volumes(ours)), np.asarray(jaxgeom.voronoi_volumes(ref)), rtol=1e-9, equal_nan=True
    )


@pytest.mark.parametrize("name, d", CASES)
def test_far_from_the_origin(rng, name, d):
    """A 1e15 offset: the walkers stay resolved (spacing 1e4 >> the ulp 0.125)."""
    x = 1e15 + 1e4 * (200 ** (1 / d)) * rng.random((200, d))
    ours, ref = (jaxgeom.delaunay(x, triangulator=t) for t in (name, "qhull"))
    assert neighbor_sets(ours) == neighbor_sets(ref)


@pytest.mark.parametrize("name, d", CASES)
def test_duplicates_take_the_coincident_points_path(rng, name, d):
    x = rng.random((100, d))
    x[17] = x[40]
    with pytest.raises(CoincidentPointsError, match="left out of the triangulation.*duplicates") as err:
        jaxgeom.delaunay(x, triangulator=name)
    assert {int(err.value.rows[0]), int(err.value.partners[0])} == {17, 40}


@pytest.mark.parametrize("d", [2, 3, 4])
def test_qhull_without_its_outer_plane_check_keeps_every_simplex_and_left_out_walker(rng, d):
    """`QHULL_OPTIONS`' Q5 skips Qhull's final outer-plane check (a periodic 3D build 7-9%
    faster) and nothing else: on uniform walkers, duplicates, near-duplicates, lattices (exact
    and jittered) and co-spherical walkers, the simplices and the left-out (coplanar) walkers
    equal Qhull's with the check."""
    from scipy.spatial import Delaunay

    assert "Q5" in backends.QHULL_OPTIONS.split()
    checked = " ".join(o for o in backends.QHULL_OPTIONS.split() if o != "Q5")
    x = rng.random((400, d))
    lattice = np.stack(np.meshgrid(*[np.arange(5)] * d, indexing="ij"), -1).reshape(-1, d) / 4.0
    sphere = rng.standard_normal((300, d))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    cases = [x, np.concatenate([x, x[:5]]), np.concatenate([x, x[:5] + 1e-13]), lattice]
    cases += [lattice + 1e-12 * rng.standard_normal(lattice.shape), np.concatenate([sphere, sphere[:3]])]
    rows = lambda a: a[np.lexsort(a.T[::-1])]  # noqa: E731  (in one order, row by row)
    left_out = 0
    for points in cases:
        fast, slow = (Delaunay(points, qhull_options=o) for o in (backends.QHULL_OPTIONS, checked))
        np.testing.assert_array_equal(rows(np.sort(fast.simplices, axis=1)), rows(np.sort(slow.simplices, axis=1)))
        np.testing.assert_array_equal(rows(fast.coplanar), rows(slow.coplanar))
        left_out += len(fast.coplanar)
    assert left_out >= 10  # the duplicates (5) and the sphere's (3) at least


def test_cdt_on_morton_sorted_points_returns_the_callers_order(rng, monkeypatch):
    """Above MORTON_MIN_POINTS CDT sees its points sorted along a Z curve; here the threshold
    is lowered so small inputs take that path: the same triangles and adjacency as unsorted,
    in the caller's numbering, oriented, and duplicates still named by the caller's rows."""
    i, j = np.meshgrid(np.arange(12.0), np.arange(9.0))
    lattice = np.column_stack([i.ravel() + 0.5 * j.ravel(), j.ravel()])
    cases = [rng.random((600, 2)), clustered(rng, 600, 2), lattice, 1e15 + 1e4 * rng.random((300, 2))]
    for x in cases:
        plain = backends._cdt(x)
        monkeypatch.setattr(backends, "MORTON_MIN_POINTS", 1)
        tri = backends._cdt(x)
        monkeypatch.undo()
        assert not np.array_equal(backends.morton_order(x), np.arange(len(x)))
        assert check_triangulation(tri, x) is None and not backends._flat(x, tri.simplices).any()
        key = {tuple(sorted(t)): k for k, t in enumerate(tri.simplices.tolist())}
        match = [key[tuple(sorted(t))] for t in plain.simplices.tolist()]
        assert sorted(match) == list(range(len(tri.simplices)))  # the same triangles
        assert (tri.neighbors < 0).sum() == (plain.neighbors < 0).sum()  # the same hull edges
        for k in range(3):  # neighbour k lies across the edge opposite vertex k
            m = tri.neighbors[:, k] >= 0
            edge, other = np.delete(tri.simplices[m], k, axis=1), tri.simplices[tri.neighbors[m, k]]
            assert (edge[:, :, None] == other[:, None, :]).any(-1).all()
    x = rng.random((100, 2))
    x[17] = x[40]
    monkeypatch.setattr(backends, "MORTON_MIN_POINTS", 1)
    with pytest.raises(CoincidentPointsError, match="duplicates") as err:
        jaxgeom.delaunay(x, triangulator="cdt")
    assert {int(err.value.rows[0]), int(err.value.partners[0])} == {17, 40}


def test_morton_codes_interleave_the_quantised_coordinates_bit_by_bit(rng):
    """Bit b * d + k of a code is bit b of coordinate k quantised to `bits` bits on the
    bounding box: the d = 2, 3 bit-spreading masks and the loop for d > 3 against a
    Python-integer reference."""
    for d in (1, 2, 3, 4, 6):
        x = rng.random((200, d)) * np.arange(1, d + 1) * 1e3 - 7.0
        code, n_bits = backends.morton_codes(x)
        bits = n_bits // d
        lo, hi = x.min(axis=0), x.max(axis=0)
        q = ((x - lo) / (hi - lo) * (2**bits - 1)).astype(np.uint64).tolist()
        ref = [sum(((row[k] >> b) & 1) << (b * d + k) for b in range(bits) for k in range(d)) for row in q]
        assert bits == min(16, 60 // d) and code.tolist() == ref, d


# --- the check and the fallback -------------------------------------------------------------


def test_the_check_accepts_delaunay_and_names_each_defect(rng):
    x = rng.random((300, 2))
    tri = backends._cdt(x)
    assert check_triangulation(tri, x) is None
    bad = backends._Triangulation(tri.simplices[:, [0, 2, 1]], tri.neighbors[:, [0, 2, 1]])
    assert "flat or negatively oriented" in check_triangulation(bad, x)
    assert "left out" in check_triangulation(tri, np.vstack([x, [[5.0, 5.0]]]))
    dropped = backends._Triangulation(tri.simplices[1:], tri.neighbors[1:])
    assert check_triangulation(dropped, x) is not None
    asym = backends._Triangulation(tri.simplices, np.where(tri.neighbors == 5, 6, tri.neighbors))
    assert "symmetric" in check_triangulation(asym, x)
    out = backends._Triangulation(np.where(tri.simplices == 0, 300, tri.simplices), tri.neighbors)
    assert "out of range" in check_triangulation(out, x)
    x3 = rng.random((200, 3))
    tri3 = backends.qhull(x3)[0]
    assert "flat or negatively oriented" in check_triangulation(tri3, x3)  # Qhull's 3D simplices are not oriented
    flip = backends._volumes(x3, tri3.simplices)[0] < 0
    oriented = backends._Triangulation(
        np.where(flip[:, None], tri3.simplices[:, [1, 0, 2, 3]], tri3.simplices),
        np.where(flip[:, None], tri3.neighbors[:, [1, 0, 2, 3]], tri3.neighbors),
    )
    assert check_triangulation(oriented, x3) is None
    hollow = backends._Triangulation(oriented.simplices[1:], oriented.neighbors[1:])
    assert check_triangulation(hollow, x3) is not None


def test_the_check_finds_a_defect_in_any_chunk(rng, monkeypatch):
    """The orientation and adjacency tests run in chunks of `CHECK_CHUNK` simplices: one
    flipped triangle, or one neighbour entry its partner does not return, is found in the
    first, a boundary or the last chunk."""
    monkeypatch.setattr(backends, "CHECK_CHUNK", 64)
    x = rng.random((300, 2))
    tri = backends._cdt(x)
    simplices, neighbors = np.asarray(tri.simplices), np.asarray(tri.neighbors)
    assert check_triangulation(backends._Triangulation(simplices, neighbors), x) is None
    for row in (0, 63, 64, len(simplices) - 1):
        flipped_s, flipped_n = simplices.copy(), neighbors.copy()
        flipped_s[row], flipped_n[row] = simplices[row, [0, 2, 1]], neighbors[row, [0, 2, 1]]
        assert "flat or negatively oriented" in check_triangulation(backends._Triangulation(flipped_s, flipped_n), x)
        other = next(
            m for m in range(len(simplices)) if m != row and row not in neighbors[m] and m not in neighbors[row]
        )
        one_sided = neighbors.copy()
        one_sided[row, 0] = other
        assert "symmetric" in check_triangulation(backends._Triangulation(simplices, one_sided), x)


def test_cdt_marks_its_triangles_oriented_only_where_the_check_would_pass(rng):
    """The check skips its orientation test for CDT's output (`oriented`): that holds only if
    `_cdt` kept exactly the triangles the test passes, here also on a sheared lattice whose
    collinear hull side gives CDT zero-area triangles."""
    i, j = np.meshgrid(np.arange(12.0), np.arange(9.0))
    lattice = np.column_stack([i.ravel() + 0.5 * j.ravel(), j.ravel()])
    for x in (rng.random((500, 2)), lattice):
        tri = backends._cdt(x)
        assert tri.oriented and not backends._flat(x, tri.simplices).any()
        assert check_triangulation(backends._Triangulation(tri.simplices, tri.neighbors), x) is None
    assert "flat or negatively oriented" in check_triangulation(
        backends._Triangulation(tri.simplices[:, [0, 2, 1]], tri.neighbors[:, [0, 2, 1]], oriented=False), x
    )


def test_a_backend_that_fails_is_replaced_by_qhull_with_a_warning(rng, monkeypatch):
    x = rng.random((300, 2))
    monkeypatch.setitem(backends.BUILDERS, "cdt", lambda pts: (_ for _ in ()).throw(RuntimeError("boom")))
    with pytest.warns(RuntimeWarning, match=r"cdt raised RuntimeError: boom; Qhull built this graph"):
        tess = jaxgeom.delaunay(x, triangulator="cdt")
    assert simplex_set(tess) == simplex_set(jaxgeom.delaunay(x, triangulator="qhull"))
    real = backends._cdt
    monkeypatch.setitem(
        backends.BUILDERS,
        "cdt",
        lambda pts: (t := real(pts)) and backends._Triangulation(t.simplices[1:], t.neighbors[1:]),
    )
    with pytest.warns(RuntimeWarning, match="failed its check"):
        jaxgeom.delaunay(x, triangulator="cdt")


@pytest.mark.parametrize("rebuild", ["host", "callback"])
def test_simulate_counts_each_fallback_and_runs_as_qhull_would(rng, monkeypatch, rebuild):
    x = rng.uniform(-3, 3, (200, 2))
    params = jaxgeom.SwarmParams(dt=0.05, nu=0.3)
    run = lambda t: jaxgeom.simulate(
        rastrigin,
        jaxgeom.init_swarm(rastrigin, x, key=1, triangulator=t),
        params,
        n_steps=4,
        rebuild=rebuild,
        observe=("mean_ricci",),
    )
    ref_state, ref = run("qhull")
    calls = []
    real = backends._cdt
    monkeypatch.setitem(backends.BUILDERS, "cdt", lambda pts: calls.append(1) or 1 / 0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # counted, not warned
        state, history = run("cdt")
    assert int(history["n_triangulator_fallbacks"]) == len(calls) == 5  # the first graph and 4 rebuilds
    assert int(ref["n_triangulator_fallbacks"]) == 0
    np.testing.assert_allclose(state.positions, ref_state.positions, rtol=1e-12)
    monkeypatch.setitem(backends.BUILDERS, "cdt", real)
    assert int(run("cdt")[1]["n_triangulator_fallbacks"]) == 0


# --- choosing a backend ---------------------------------------------------------------------


def test_auto_takes_the_fastest_installed(monkeypatch):
    assert resolve_triangulator("auto", 4) == "qhull"
    assert resolve_triangulator("auto", 2) == ("shull" if installed("shull") else "cdt")
    assert resolve_triangulator("auto", 3) == ("shull" if installed("shull") else "qhull")
    monkeypatch.setattr(backends, "installed", lambda name: name not in ("shull", "cupy"))
    assert resolve_triangulator("auto", 2) == "cdt" and resolve_triangulator("auto", 3) == "qhull"
    monkeypatch.setattr(backends, "installed", lambda name: True)  # a GPU with CuPy: cupy first in 2D
    assert resolve_triangulator("auto", 2) == "cupy" and resolve_triangulator("auto", 3) == "shull"


def test_bad_triangulators_are_refused(rng, monkeypatch, own_messages):
    x = rng.random((50, 3))
    with pytest.raises(ValueError, match="unknown triangulator 'triangle'; valid values are 'auto', 'qhull'"):
        jaxgeom.delaunay(x, triangulator="triangle")
    with pytest.raises(ValueError, match=r"triangulator='cdt' builds d = 2 only.*d = 3"):
        jaxgeom.delaunay(x, triangulator="cdt")
    with pytest.raises(TypeError, match="`triangulator` must be a string"):
        jaxgeom.init_swarm(rastrigin, x, triangulator=None)
    monkeypatch.setattr(backends, "installed", lambda name: name != "shull")
    with pytest.raises(
        ValueError, match=r"'shull' is not installed: pip install \"jaxgeom\[gpl\]\" \(shull, GPL-3.0\)"
    ):
        jaxgeom.delaunay(x, triangulator="shull")


def test_the_swarm_keeps_its_triangulator(rng):
    x = rng.uniform(-3, 3, (100, 2))
    state = jaxgeom.init_swarm(rastrigin, x, triangulator="cdt")
    assert state.triangulator == "cdt"
    final, _ = jaxgeom.simulate(rastrigin, state, jaxgeom.SwarmParams(dt=0.05), n_steps=2, observe=())
    assert final.triangulator == "cdt"
    assert jaxgeom.init_swarm(rastrigin, x).triangulator == resolve_triangulator("auto", 2)


def test_triangulate_reports_no_fallback_for_qhull(rng):
    assert triangulate(rng.random((50, 2)), "qhull").fallback is None
