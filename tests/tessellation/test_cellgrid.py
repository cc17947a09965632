"""The device cell list (jaxgeom.tessellation._cellgrid): every walker within the radius it reports is found."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from jaxgeom.tessellation._cellgrid import block_walkers, build_grid, grid_side, walker_reach, within

N = 2000


def sample(kind: str) -> np.ndarray:
    rng = np.random.default_rng(0)
    if kind == "uniform":
        return rng.random((N, 2))
    if kind == "gaussian":
        return rng.normal(size=(N, 2))
    centres = rng.uniform(-5, 5, (20, 2))  # clusters 100x denser than the space between them
    return centres[rng.integers(0, 20, N)] + 0.02 * rng.normal(size=(N, 2))


@jax.jit
def blocks(x):
    grid = build_grid(x, grid_side(N))
    rows = jnp.arange(N, dtype=jnp.int32)
    return block_walkers(x, grid, rows, walker_reach(grid, rows))


@pytest.mark.parametrize("kind", ["uniform", "gaussian", "clustered"])
def test_block_walkers_hold_every_walker_within_their_radius(kind):
    x = sample(kind)
    ids, d2, r2, complete = (np.asarray(a) for a in blocks(jnp.asarray(x)))
    tree = cKDTree(x)
    for i in range(0, N, 5):
        wanted = set(tree.query_ball_point(x[i], np.sqrt(r2[i]) * (1 - 1e-9))) - {i}
        assert wanted <= set(ids[i].tolist()), i
        listed = ids[i] < N
        np.testing.assert_allclose(d2[i][listed], np.sum((x[ids[i][listed]] - x[i]) ** 2, axis=1), rtol=1e-12)
    assert np.median(r2) > 0
    if kind == "uniform":
        assert complete.mean() > 0.9


def test_within_packs_the_entries_in_range_and_reports_overflow():
    ids = jnp.asarray([[5, 6, 7, 8], [1, 2, 3, 4]])
    d2 = jnp.asarray([[0.5, 2.0, 0.1, 0.7], [0.1, 0.2, 0.3, 0.4]])
    packed, fitted = within(ids, d2, jnp.zeros(2), jnp.asarray([1.0, 1.0]), 3, 9)
    np.testing.assert_array_equal(np.asarray(packed), [[5, 7, 8], [1, 2, 3]])
    np.testing.assert_array_equal(np.asarray(fitted), [True, False])
