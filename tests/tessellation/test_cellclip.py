"""The Delaunay rebuild on the device (jaxgeom.rebuild, jaxgeom.tessellation._cellclip) against Qhull."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.tessellation._cellclip import _cycles, check_cycles, rebuild_unchecked, triangulate, voronoi_cycles

N = 400  # one size for every test below: the rebuild compiles once per graph structure
UNIT = (0.0, 1.0)


def simplex_set(tess):
    s = np.asarray(tess.simplices)
    return {tuple(sorted(row)) for row in s[s[:, 0] < tess.n_points].tolist()}


def assert_same_graph(new, ref):
    """Neighbours, tiers, hull flags and simplices equal; volumes to 1e-10 relative."""
    assert not bool(new.overflow)
    np.testing.assert_array_equal(np.asarray(new.neighbors), np.asarray(ref.neighbors))
    np.testing.assert_array_equal(np.asarray(new.tier), np.asarray(ref.tier))
    np.testing.assert_array_equal(np.asarray(new.hull), np.asarray(ref.hull))
    assert simplex_set(new) == simplex_set(ref)
    np.testing.assert_allclose(
        np.asarray(jaxgeom.voronoi_volumes(new)), np.asarray(jaxgeom.voronoi_volumes(ref)), rtol=1e-10
    )


def moved(x, scale, seed, box=None):
    y = x + scale * np.random.default_rng(seed).normal(size=x.shape)
    return y if box is None else np.clip(y, box[0] + 1e-9, box[1] - 1e-9)


@pytest.mark.parametrize("sample", [pytest.param("uniform-boxed", marks=pytest.mark.slow), "gaussian-plain"])
def test_rebuild_equals_qhull_on_random_walkers(sample):
    rng = np.random.default_rng(3)
    box = UNIT if sample == "uniform-boxed" else None
    x0 = rng.random((N, 2)) if box else rng.normal(size=(N, 2))
    tess = jaxgeom.delaunay(x0, box=box)
    for seed in range(3):  # a moving swarm: each rebuild from the previous graph
        x = moved(x0, 0.02, seed, box)
        new = jaxgeom.rebuild(tess, x)
        assert_same_graph(new, jaxgeom.delaunay(x, box=box, capacity=tess))
        tess = new


@pytest.mark.slow
def test_rebuild_compiles_once_for_a_moving_swarm():
    x = np.random.default_rng(4).random((N, 2))
    tess = jaxgeom.delaunay(x, box=UNIT)
    before = rebuild_unchecked._cache_size()
    for step in range(50):
        x = moved(x, 0.002, step, UNIT)
        tess = jaxgeom.rebuild(tess, x)
    assert rebuild_unchecked._cache_size() - before <= 1  # 0 if an earlier test compiled this structure
    assert_same_graph(tess, jaxgeom.delaunay(x, box=UNIT, capacity=tess))


@pytest.mark.slow
def test_rebuild_vmaps_over_swarms():
    x0 = np.random.default_rng(5).random((N, 2))
    tess = jaxgeom.delaunay(x0, box=UNIT)
    batch = np.stack([moved(x0, 0.01, seed, UNIT) for seed in range(4)])
    together = jax.vmap(rebuild_unchecked, in_axes=(None, 0))(tess, jnp.asarray(batch))
    for b in range(4):
        alone = jaxgeom.rebuild(tess, batch[b])
        for field in ("neighbors", "simplices", "tier", "hull", "overflow"):
            np.testing.assert_array_equal(np.asarray(getattr(together, field)[b]), np.asarray(getattr(alone, field)))


@pytest.mark.parametrize("jitter", [1e-3, 0.0])
def test_square_lattices_are_rebuilt_right_or_flagged(jitter):
    """Lattices (co-circular ties; rows of nearly collinear walkers on the hull, whose far
    Voronoi vertices the repair rounds do not yet resolve) are certified with Qhull's graph,
    exact volumes and flat curvature, or flagged for the host: never wrong."""
    g = (np.arange(20) + 0.5) / 20
    x = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    x = x + jitter * np.random.default_rng(6).uniform(-0.5, 0.5, x.shape) / 20
    tess = jaxgeom.delaunay(np.random.default_rng(7).random((N, 2)), box=UNIT)
    new = jaxgeom.rebuild(tess, x)
    if jitter and not bool(new.overflow):
        assert_same_graph(new, jaxgeom.delaunay(x, box=UNIT, capacity=tess))
    elif not bool(new.overflow):
        interior = np.asarray(new.tier) == 2
        np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(new))[interior], 1 / 400, rtol=1e-12)
        ricci = np.asarray(jaxgeom.ricci_scalar(new))[interior]
        assert np.all(np.isfinite(ricci)) and np.max(np.abs(ricci)) < 1e-6


@functools.partial(jax.jit, static_argnames="first_pass")
def starved(x, first_pass):
    """The triangulation with a first pass of `first_pass` candidates and one repair round."""
    return triangulate(x, s_cap=2 * N, first_pass=first_pass, local_rounds=1, exact_rounds=0)


@pytest.mark.slow
def test_a_starved_triangulation_is_flagged_never_wrong():
    """Too few candidates: some rebuilds fail their certificate; every certified one is Qhull's."""
    outcomes = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        x = rng.random((N, 2)) if seed % 2 else rng.normal(size=(N, 2))
        result = starved(jnp.asarray(x), 4)
        if bool(result.certified):
            ref = jaxgeom.delaunay(x)
            ours = {tuple(sorted(r)) for r in np.asarray(result.simplices).tolist() if r[0] < N}
            assert ours == simplex_set(ref)
        outcomes.append(bool(result.certified))
    assert not all(outcomes)


def test_the_certificate_catches_a_corrupted_cell():
    x = jnp.asarray(np.random.default_rng(8).random((60, 2)))
    labels, count, _, _ = voronoi_cycles(x, jnp.broadcast_to(jnp.arange(60, dtype=jnp.int32), (60, 60)))
    assert not bool(check_cycles(x, _cycles(labels, count, 60)).certificate.failed)
    i = int(np.argmax(np.asarray(count)))  # swap two neighbours in one cell's cycle
    corrupted = labels.at[i, 0].set(labels[i, 1]).at[i, 1].set(labels[i, 0])
    checks = check_cycles(x, _cycles(corrupted, count, 60))
    assert bool(checks.certificate.failed) and bool(checks.suspect[i])


def test_rebuild_rejects_graphs_it_cannot_build():
    x = np.random.default_rng(9).random((50, 3))
    with pytest.raises(ValueError, match="2D, non-periodic"):
        jaxgeom.rebuild(jaxgeom.delaunay(x), x)
    with pytest.raises(TypeError, match="Delaunay"):
        jaxgeom.rebuild(jaxgeom.knn_graph(x[:, :2], 6), x[:, :2])
    tess = jaxgeom.delaunay(x[:, :2])
    with pytest.raises(ValueError, match="shape and dtype"):
        jaxgeom.rebuild(tess, x[:40, :2])
