import itertools
import re
from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_rotation, scipy_voronoi_volumes, tile

import jaxgeom


@pytest.mark.parametrize("d, n", [(2, 600), (3, 400)])
def test_volumes_equal_scipy_voronoi(rng, d, n):
    x = rng.random((n, d))
    vol = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x)))
    ref = scipy_voronoi_volumes(x)
    np.testing.assert_array_equal(np.isnan(vol), np.isnan(ref))
    bounded = ~np.isnan(ref)
    assert bounded.sum() > 0.7 * n
    np.testing.assert_allclose(vol[bounded], ref[bounded], rtol=1e-10, atol=0)


def test_obtuse_simplices_give_negative_pieces_and_exact_cells():
    """A jittered hexagonal patch has many obtuse triangles; cells must still be exact."""
    rng = np.random.default_rng(3)
    i, j = np.meshgrid(np.arange(12), np.arange(12))
    x = np.stack([i + 0.5 * (j % 2), j * np.sqrt(3) / 2], -1).reshape(-1, 2).astype(float)
    x += 0.3 * rng.normal(size=x.shape)
    tess = jaxgeom.delaunay(x)
    from jaxgeom.base._simplex import dual_pieces
    from jaxgeom.tessellation._graph import simplex_coords

    pieces = np.asarray(jax.vmap(dual_pieces)(simplex_coords(tess)))[np.asarray(tess.simplex_mask)]
    assert (pieces < 0).any(), "the test set contains obtuse triangles"
    ref = scipy_voronoi_volumes(x)
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    bounded = ~np.isnan(ref)
    np.testing.assert_allclose(vol[bounded], ref[bounded], rtol=1e-10)


@pytest.mark.parametrize("d, n", [(2, 300), (3, 200)])
def test_periodic_volumes_sum_to_box_and_match_tiled_copy(rng, d, n):
    lower, upper = np.full(d, -0.5), np.linspace(1.0, 1.5, d)
    x = lower + rng.random((n, d)) * (upper - lower)
    vol = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x, box=(lower, upper), periodic=True)))
    assert abs(vol.sum() - np.prod(upper - lower)) < 1e-9
    tiled, _, _ = tile(x, lower, upper, layers=1)
    tiled_vol = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(tiled)))
    np.testing.assert_allclose(vol, tiled_vol[:n], rtol=1e-10)


@pytest.mark.slow
def test_periodic_4d_volumes_sum_to_box(rng):
    x = rng.random((150, 4))
    vol = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)))
    assert np.all(vol > 0)
    assert abs(vol.sum() - 1.0) < 1e-9


@pytest.mark.parametrize("d", [2, 3])
def test_translation_rotation_permutation_invariance(rng, d):
    x = rng.random((250, d))
    base = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x)))
    moved = (x - 0.5) @ random_rotation(d, rng).T + rng.normal(size=d) * 10
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(moved))), base, rtol=1e-9)
    perm = rng.permutation(250)
    permuted = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x[perm])))
    np.testing.assert_allclose(permuted, base[perm], rtol=1e-12)


@pytest.mark.parametrize("d", [2, 3])
def test_uniform_scaling_scales_volumes_by_s_to_the_d(rng, d):
    x = rng.random((200, d))
    base = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x)))
    scaled = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(2.5 * x)))
    np.testing.assert_allclose(scaled, 2.5**d * base, rtol=1e-11)


def test_rebuilt_jittered_swarm_does_not_recompile(rng):
    x = rng.random((800, 2))
    spacing = 1 / np.sqrt(800)
    tess = jaxgeom.delaunay(x, box=(-1.0, 2.0))
    jaxgeom.voronoi_volumes(tess).block_until_ready()
    compiled = jaxgeom.voronoi_volumes.__wrapped__._cache_size()
    capacities = set()
    for _ in range(20):
        x = x + 0.2 * spacing * rng.normal(size=x.shape)
        tess = jaxgeom.delaunay(x, box=(-1.0, 2.0))
        capacities.add(tess.capacity)
        assert np.isfinite(np.asarray(jaxgeom.voronoi_volumes(tess))[np.asarray(tess.tier) == 2]).all()
    assert jaxgeom.voronoi_volumes.__wrapped__._cache_size() == compiled
    assert len(capacities) == 1


def test_rebuilt_3d_swarm_reuses_buckets(rng):
    x = rng.random((600, 3))
    caps = set()
    for _ in range(20):
        x = x + 0.02 * rng.normal(size=x.shape)
        caps.add(jaxgeom.delaunay(x).capacity)
    assert len(caps) <= 2, caps


def test_volumes_differentiable_and_finite(rng):
    x = rng.random((120, 2))
    tess = jaxgeom.delaunay(x)
    interior = np.asarray(tess.tier) == 2

    def total_interior(points):
        vol = jaxgeom.voronoi_volumes(jaxgeom.Tessellation(**{**tess.__dict__, "points": points}))
        return np.float64(0.0) + jax.numpy.sum(jax.numpy.where(interior, vol, 0.0))

    grad = np.asarray(jax.grad(total_interior)(tess.points))
    assert np.isfinite(grad).all()
    eps = 1e-6
    bump = np.zeros_like(x)
    k = int(np.flatnonzero(interior)[0])
    bump[k, 0] = eps
    fd = (total_interior(tess.points + bump) - total_interior(tess.points - bump)) / (2 * eps)
    np.testing.assert_allclose(grad[k, 0], fd, rtol=1e-5, atol=1e-9)


def test_k_nn_graph_has_no_volumes(rng):
    with pytest.raises(ValueError, match="no simplices"):
        jaxgeom.voronoi_volumes(jaxgeom.knn_graph(rng.random((50, 2)), 5))


@pytest.mark.parametrize("d", [2, 3])
def test_float32_volumes_are_accurate(rng, d):
    x = 5.0 + rng.random((400, d))  # offset from the origin: relative coordinates matter in float32
    ref = np.asarray(jaxgeom.voronoi_volumes(jaxgeom.delaunay(x)))
    with jax.enable_x64(False):
        tess = jaxgeom.delaunay(x.astype(np.float32))
        vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    interior = np.asarray(tess.tier) == 2
    assert vol.dtype == np.float32
    np.testing.assert_allclose(vol[interior], ref[interior], rtol=2e-3)
    assert abs(vol[interior].sum() / ref[interior].sum() - 1) < 1e-4


@pytest.mark.parametrize("d", [2, 3])
def test_closed_form_pieces_equal_flag_decomposition(rng, d):
    from jaxgeom.base._simplex import dual_pieces, dual_pieces_flags
    from jaxgeom.tessellation._graph import simplex_coords

    tess = jaxgeom.delaunay(rng.random((150, d)) * 3 - 1)
    coords = simplex_coords(tess)
    closed, flags = np.asarray(jax.vmap(dual_pieces)(coords)), np.asarray(jax.vmap(dual_pieces_flags)(coords))
    mask = np.asarray(tess.simplex_mask)
    np.testing.assert_allclose(closed[mask], flags[mask], rtol=1e-9, atol=1e-12 * np.abs(flags[mask]).max())


def exact_voronoi_area(x: np.ndarray, i: int, big: Fraction = Fraction(10**15)) -> Fraction:
    """Area of walker i's Voronoi cell in exact rationals: a square of half-width `big` clipped
    by every bisector half-plane (independent of any triangulation)."""
    p = [Fraction(float(c)) for c in x[i]]
    poly = [(-big, -big), (big, -big), (big, big), (-big, big)]
    for j in np.delete(np.arange(len(x)), i):
        q = [Fraction(float(c)) for c in x[j]]
        a = [2 * (q[k] - p[k]) for k in range(2)]
        b = sum(c * c for c in q) - sum(c * c for c in p)
        side = [a[0] * u[0] + a[1] * u[1] - b for u in poly]
        out = []
        for k, u in enumerate(poly):
            v, fu, fv = poly[(k + 1) % len(poly)], side[k], side[(k + 1) % len(poly)]
            if fu <= 0:
                out.append(u)
            if fu * fv < 0:
                t = fu / (fu - fv)
                out.append((u[0] + t * (v[0] - u[0]), u[1] + t * (v[1] - u[1])))
        poly = out
    assert all(abs(c) < big for u in poly for c in u), "the cell reaches the start square"
    return sum(u[0] * v[1] - v[0] * u[1] for u, v in zip(poly, poly[1:] + poly[:1], strict=True)) / 2


def near_line(noise: float, seed: int = 0) -> np.ndarray:
    s = np.linspace(0, 1, 40)
    return np.c_[s, 2 * s + noise * np.random.default_rng(seed).standard_normal(40)]


@pytest.mark.parametrize("triangulator", ["qhull", "cdt"])
def test_nearly_collinear_walkers_never_get_a_volume_of_the_wrong_sign(triangulator):
    """Walkers on a line with 1e-13 noise: once a cell of -2.38e12 where exact arithmetic gives
    +2.13e13. Now each such swarm is refused as nearly degenerate (a walker left out, or too
    thin for Qhull's inexact predicates), or each bounded cell's volume has the sign of the
    exact rational area and is close to it, or it is NaN where its pieces cannot decide (a
    triangle within rounding of collinear, a real Voronoi vertex ~1e13 away)."""
    refused, checked, undecided = 0, 0, 0
    for noise, seed in itertools.product([1e-13, 1e-12], range(4)):
        x = near_line(noise, seed)
        try:
            tess = jaxgeom.delaunay(x, triangulator=triangulator)
        except ValueError as err:
            assert re.search(r"nearly (degenerate|collinear)", str(err)), err
            refused += 1
            continue
        vol = np.asarray(jaxgeom.voronoi_volumes(tess))
        for i in np.flatnonzero(~np.asarray(tess.hull)):
            exact = float(exact_voronoi_area(x, i))
            if np.isnan(vol[i]):
                undecided += 1
                continue
            checked += 1
            assert vol[i] * exact > 0 and abs(vol[i] / exact - 1) < (1e-2 if triangulator == "cdt" else 5e-2)
    assert (refused >= 1) == (triangulator == "qhull") and checked > 100 and undecided < 0.05 * checked
    tess = jaxgeom.delaunay(near_line(1e-12), triangulator=triangulator)
    inner = np.flatnonzero(np.asarray(tess.tier) == 2)
    exact = np.array([float(exact_voronoi_area(near_line(1e-12), i)) for i in inner])
    np.testing.assert_allclose(
        np.asarray(jaxgeom.voronoi_volumes(tess))[inner], exact, rtol=1e-4 if triangulator == "cdt" else 0.05
    )


@pytest.mark.parametrize("d, m", [(2, 8), (3, 5)])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_boxed_lattice_cells_are_exact_at_the_wall(d, m, dtype):
    """A cubic lattice in its box: every cell is a cube of side 1/m. Once the cells at the
    walls came out 0.008-0.0113 for 0.008 (3D): planes through a cell's edges (zero-area
    faces) have slope and room ~eps, and room / slope bounded the edges arbitrarily, or an
    edge was counted once per plane through it."""
    g = (np.arange(m) + 0.5) / m
    x = np.stack(np.meshgrid(*[g] * d, indexing="ij"), -1).reshape(-1, d).astype(dtype)
    tess = jaxgeom.delaunay(x, box=(np.zeros(d), np.ones(d)))
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    assert vol.dtype == dtype
    np.testing.assert_allclose(vol, m**-d, rtol=1e-12 if dtype == np.float64 else 1e-5)


@pytest.mark.parametrize("flagged", [0, 1, 37, 300, 999, 1000])
def test_flagged_rows_run_in_groups_of_chunks_as_in_one_loop(rng, flagged):
    """`map_flagged_rows` and `scan_live_chunks` walk their chunks in groups and skip groups of
    padding whole: the outputs equal a plain loop over the chunks, flagged rows anywhere (the
    live chunks ending inside a group, at its end, in the last one, or none), and a gradient
    flows through the groups' `cond`s."""
    from jaxgeom.geometry._boxclip import map_flagged_rows, scan_live_chunks

    n, size = 1000, 8  # 125 chunks: 16 groups of 8, the last padded
    flags = np.zeros(n, bool)
    flags[rng.choice(n, flagged, replace=False)] = True
    values = jnp.asarray(rng.normal(size=n))
    rows, out = map_flagged_rows(
        jnp.asarray(flags), size, lambda ids: values[ids] * 2.0, lambda ids: jnp.full(ids.shape, -1.0)
    )
    live = np.flatnonzero(flags)
    np.testing.assert_array_equal(np.asarray(rows)[: len(live)], live)
    got = np.asarray(out)
    np.testing.assert_array_equal(got[: len(live)], 2.0 * np.asarray(values)[live])
    np.testing.assert_array_equal(got[-(-len(live) // size) * size :], -1.0)  # chunks of padding: `empty`

    def total(v):
        chunks = jnp.asarray(rows).reshape(-1, size)
        return scan_live_chunks(
            lambda c, ids: c + jnp.sum(jnp.where(ids < n, v[jnp.minimum(ids, n - 1)] ** 2, 0.0)), 0.0, chunks, n
        )

    np.testing.assert_allclose(total(values), np.sum(np.asarray(values)[live] ** 2), rtol=1e-12)
    np.testing.assert_allclose(jax.grad(total)(values), 2 * np.asarray(values) * flags, rtol=1e-12)


def test_boxed_3d_tier0_volumes_from_the_boundary_simplices_equal_those_from_all(rng, monkeypatch):
    """`tier0_volumes_3d` measures the tier-0 cells from the simplices with a tier-0 walker alone,
    cut to half the capacity when they fit (48% of them here), in blocks of 512, those of
    padding skipped: bit for bit its own fallback over every simplex (`dual_faces_3d`'s
    volumes, taken when every walker is marked tier 0: all simplices then count), in one
    compiled program."""
    import equinox as eqx

    from jaxgeom.geometry import _dual

    monkeypatch.setattr(_dual, "SIMPLEX_BLOCK", 512)
    tess = jaxgeom.delaunay(rng.random((3000, 3)), box=(0.0, 1.0))
    tier0 = np.asarray(tess.tier == 0)
    on_boundary = np.concatenate([tier0, [False]])[np.asarray(tess.simplices)].any(axis=1)
    assert on_boundary.sum() <= tess.simplices.shape[0] // _dual.BOUNDARY_SHARE < on_boundary.size
    measure = jax.jit(_dual.tier0_volumes_3d)
    cut = np.asarray(measure(tess))
    every = np.asarray(measure(eqx.tree_at(lambda t: t.tier, tess, jnp.zeros_like(tess.tier))))
    np.testing.assert_array_equal(cut[tier0], every[tier0])
    assert measure._cache_size() == 1
