"""scutoids: neighbour changes against set arithmetic on scipy's graphs, known moves (a
translation, one Delaunay flip, a clone), and the spacetime volume against exact integrals."""

import itertools

import numpy as np
import pytest
from helpers import scipy_neighbor_sets
from scipy.spatial import Delaunay

import jaxgeom
from jaxgeom.geometry._scutoids import COMPLEX, PRISM, SIMPLE


def reference_changes(x0, x1, parents):
    """(shared, lost, gained) of every walker by Python sets on scipy's Delaunay graphs."""
    before, after = scipy_neighbor_sets(x0), scipy_neighbor_sets(x1)
    rows = [
        (len(before[p] & after[i]), len(before[p] - after[i]), len(after[i] - before[p])) for i, p in enumerate(parents)
    ]
    return np.array(rows).T


@pytest.mark.parametrize("d", [2, 3])
def test_counts_equal_set_arithmetic_for_random_moves_and_clones(rng, d):
    n = 300 if d == 2 else 200
    x0 = rng.random((n, d))
    parents = np.arange(n)
    cloned = rng.choice(n, 15, replace=False)
    parents[cloned] = rng.integers(0, n, 15)
    x1 = x0 + 0.02 * rng.standard_normal((n, d))
    x1[cloned] = x0[parents[cloned]] + 1e-3 * rng.standard_normal((15, d))
    s = jaxgeom.scutoids(jaxgeom.delaunay(x0), jaxgeom.delaunay(x1), parents)
    shared, lost, gained = reference_changes(x0, x1, parents)
    np.testing.assert_array_equal(s.shared, shared)
    np.testing.assert_array_equal(s.lost, lost)
    np.testing.assert_array_equal(s.gained, gained)
    kind = np.where((lost == 0) & (gained == 0), PRISM, np.where((lost <= 1) & (gained <= 1), SIMPLE, COMPLEX))
    np.testing.assert_array_equal(s.kind, kind)
    np.testing.assert_array_equal(s.parent, parents)
    assert set(np.unique(kind)) == {PRISM, SIMPLE, COMPLEX} or d == 3  # 3D moves change most cells


def test_a_translation_makes_every_walker_a_prism_of_volume_v_dt(rng):
    x0 = rng.random((400, 2))
    before, after = jaxgeom.delaunay(x0), jaxgeom.delaunay(x0 + np.array([0.3, -0.7]))
    s = jaxgeom.scutoids(before, after, dt=0.05)
    assert (np.asarray(s.kind) == PRISM).all() and (np.asarray(s.lost) == 0).all()
    bounded = np.isfinite(np.asarray(s.bottom_volume))
    assert bounded.sum() > 350 and np.array_equal(~bounded, np.asarray(s.hull))
    np.testing.assert_allclose(
        np.asarray(s.spacetime_volume)[bounded], 0.05 * np.asarray(s.bottom_volume)[bounded], rtol=1e-12
    )
    assert np.isnan(np.asarray(s.spacetime_volume)[~bounded]).all()


@pytest.mark.parametrize("d", [2, 3])
def test_a_uniform_scaling_gives_the_exact_spacetime_integral(rng, d):
    """Walkers moving linearly from x to s x: every cell's volume is (1 + tau (s - 1))^d V,
    whose integral over the step is V dt (s^(d+1) - 1) / ((d + 1)(s - 1))."""
    x0 = rng.random((300, d)) - 0.5
    scale, dt = 1.3, 0.1
    s = jaxgeom.scutoids(jaxgeom.delaunay(x0), jaxgeom.delaunay(scale * x0), dt=dt)
    bottom = np.asarray(s.bottom_volume)
    ok = np.isfinite(bottom)
    np.testing.assert_allclose(np.asarray(s.top_volume)[ok], scale**d * bottom[ok], rtol=1e-11)
    exact = bottom * dt * (scale ** (d + 1) - 1) / ((d + 1) * (scale - 1))
    np.testing.assert_allclose(np.asarray(s.spacetime_volume)[ok], exact[ok], rtol=1e-11)
    assert (np.asarray(s.kind) == PRISM).all()


def one_flip(rng):
    """Positions before and after moving one walker so that exactly one Delaunay edge flips:
    (x0, x1, the removed edge, the added edge)."""
    x0 = rng.random((200, 2))
    tri = Delaunay(x0)
    edges = lambda t: {tuple(sorted(e)) for s in t.simplices for e in itertools.combinations(s, 2)}  # noqa: E731
    base = edges(tri)
    for s, nbrs in zip(tri.simplices, tri.neighbors, strict=True):
        for m in range(3):
            if nbrs[m] < 0:
                continue
            k, (i, j) = s[m], (s[(m + 1) % 3], s[(m + 2) % 3])
            other = tri.simplices[nbrs[m]]
            l = next(v for v in other if v not in (i, j))
            middle = 0.5 * (x0[i] + x0[j])
            for t in np.linspace(0.05, 0.95, 19):  # move k towards edge ij until the edge flips
                x1 = x0.copy()
                x1[k] = (1 - t) * x0[k] + t * middle
                after = edges(Delaunay(x1))
                if after != base:
                    if base - after == {tuple(sorted((i, j)))} and after - base == {tuple(sorted((k, l)))}:
                        return x0, x1, (i, j), (k, l)
                    break
    raise AssertionError("no single flip found")


def test_one_flip_changes_exactly_four_walkers_into_simple_scutoids(rng):
    x0, x1, (i, j), (k, l) = one_flip(rng)
    s = jaxgeom.scutoids(jaxgeom.delaunay(x0), jaxgeom.delaunay(x1))
    lost, gained, kind = np.asarray(s.lost), np.asarray(s.gained), np.asarray(s.kind)
    changed = np.flatnonzero((lost > 0) | (gained > 0))
    assert sorted(changed) == sorted([i, j, k, l])
    assert lost[i] == lost[j] == 1 and gained[i] == gained[j] == 0
    assert gained[k] == gained[l] == 1 and lost[k] == lost[l] == 0
    assert (kind[changed] == SIMPLE).all() and (np.delete(kind, changed) == PRISM).all()


def test_a_clone_is_joined_to_its_parents_cell(rng):
    """Walker c jumps next to parent p: its bottom is p's cell at t, so its shared and lost
    neighbours are p's, and it gains p (and nothing else, for a clone this close)."""
    x0 = rng.random((300, 2))
    hull = np.asarray(jaxgeom.delaunay(x0).hull)
    p = 10
    c = int(np.argmax(np.where(hull, 0.0, np.linalg.norm(x0 - x0[p], axis=1))))  # inside, far from p
    x1 = x0.copy()
    x1[c] = x0[p] + 1e-7 * np.array([0.6, 0.8])
    parents = np.arange(300)
    parents[c] = p
    before, after = jaxgeom.delaunay(x0), jaxgeom.delaunay(x1)
    s = jaxgeom.scutoids(before, after, parents)
    old = scipy_neighbor_sets(x0)[p]
    new = scipy_neighbor_sets(x1)[c]
    assert int(s.parent[c]) == p and p in new
    assert int(s.shared[c]) == len(old & new) and int(s.lost[c]) == len(old - new) and int(s.gained[c]) == 1
    np.testing.assert_allclose(float(s.bottom_volume[c]), float(np.asarray(jaxgeom.voronoi_volumes(before))[p]))
    # the walkers around c's old place lose it; unrelated walkers far from both places are prisms
    far = np.linalg.norm(x0 - x0[p], axis=1) > 0.3
    far &= np.linalg.norm(x0 - x0[c], axis=1) > 0.3
    assert (np.asarray(s.kind)[far] == PRISM).all()


def test_fractions_and_bad_arguments(rng):
    x0 = rng.random((100, 2))
    t = jaxgeom.delaunay(x0)
    s = jaxgeom.scutoids(t, jaxgeom.delaunay(x0 + 0.01 * rng.standard_normal((100, 2))))
    fractions = np.asarray(s.fractions())
    assert fractions.sum() == pytest.approx(1.0)
    named = s.fractions()  # named fields, counted from `kind` independently
    kind, interior = np.asarray(s.kind), np.asarray(s.interior)
    for field, k in (("prism", PRISM), ("simple", SIMPLE), ("complex", COMPLEX)):
        assert float(getattr(named, field)) == pytest.approx(np.mean(kind[interior] == k))
    assert all(np.isnan(np.asarray(s.fractions(np.zeros(100, bool)))))
    with pytest.raises(ValueError, match="`parents` must hold walker ids"):
        jaxgeom.scutoids(t, t, np.full(100, 100))
    with pytest.raises(ValueError, match="`parents` must be an"):
        jaxgeom.scutoids(t, t, np.zeros(5, int))
    with pytest.raises(TypeError, match="Delaunay"):
        jaxgeom.scutoids(t, jaxgeom.knn_graph(x0, 6))
    with pytest.raises(ValueError, match="same walkers"):
        jaxgeom.scutoids(t, jaxgeom.delaunay(x0[:50]))
    with pytest.raises(ValueError, match="dt"):
        jaxgeom.scutoids(t, t, dt=0.0)
