"""Device Voronoi cells by bisector clipping (jaxgeom._cellclip) against Qhull."""

import jax
import numpy as np
import pytest

import jaxgeom
from jaxgeom._cellclip import voronoi_cells_2d

UNIT = np.array([[0.0, 0.0], [1.0, 1.0]])


def neighbor_sets(vertices, labels, count, rtol=1e-9):
    """Each cell's neighbours: the labels of its edges longer than rtol x its perimeter."""
    v, lab, c = np.asarray(vertices), np.asarray(labels), np.asarray(count)
    out = []
    for i in range(len(c)):
        poly = v[i, : c[i]]
        edges = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
        out.append({int(j) for j, e in zip(lab[i, : c[i]], edges) if j >= 0 and e > rtol * edges.sum()})
    return out


@pytest.mark.parametrize("sample", ["uniform", "gaussian"])
def test_certified_cells_match_qhull_exactly(sample):
    rng = np.random.default_rng(0)
    x = rng.random((600, 2)) if sample == "uniform" else np.clip(0.5 + 0.15 * rng.normal(size=(600, 2)), 0.01, 0.99)
    vertices, labels, count, area, certified, overflowed = jax.jit(voronoi_cells_2d)(x, UNIT)
    certified = np.asarray(certified)
    assert not np.any(overflowed) and certified.mean() > 0.9  # gaussian: the sparse rim needs more than k candidates
    if certified.all():
        assert float(np.sum(area)) == pytest.approx(1.0, rel=1e-12)  # box-clipped cells tile the box
    tess = jaxgeom.delaunay(x, box=UNIT)
    checked = (np.asarray(tess.tier) == 2) & certified
    np.testing.assert_allclose(np.asarray(area)[checked], np.asarray(jaxgeom.voronoi_volumes(tess))[checked],
                               rtol=1e-10)
    qhull = [set(row[row < 600].tolist()) for row in np.asarray(tess.neighbors)]
    ours = neighbor_sets(vertices, labels, count)
    assert all(ours[i] == qhull[i] for i in np.flatnonzero(checked))


def test_an_exact_square_lattice_has_square_cells_and_four_neighbours():
    g = (np.arange(10) + 0.5) / 10
    x = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    vertices, labels, count, area, certified, _ = voronoi_cells_2d(x, UNIT)
    np.testing.assert_allclose(np.asarray(area), 0.01, rtol=1e-12)
    degrees = [len(s) for s in neighbor_sets(vertices, labels, count)]
    assert max(degrees) == 4 and min(degrees) == 2 and np.all(certified)


def test_cells_with_too_few_candidates_are_flagged_not_trusted():
    x = np.random.default_rng(1).random((400, 2))
    _, _, _, area, certified, _ = voronoi_cells_2d(x, UNIT, k=6)
    _, _, _, exact, _, _ = voronoi_cells_2d(x, UNIT, k=64)
    wrong = ~np.isclose(np.asarray(area), np.asarray(exact), rtol=1e-9)
    assert wrong.any() and not np.any(wrong & np.asarray(certified))  # every wrong cell is flagged


def test_vmap_over_swarms_equals_separate_calls_and_one_compilation_serves_moving_swarms():
    rng = np.random.default_rng(2)
    batch = rng.random((3, 150, 2))
    traces = []

    def cells(x):
        traces.append(1)
        return voronoi_cells_2d(x, UNIT)[3]

    jitted = jax.jit(cells)
    separate = np.stack([np.asarray(jitted(x)) for x in batch])
    for step in range(5):  # a moving swarm: same shapes, no new trace
        jitted(np.clip(batch[0] + 0.01 * step * rng.normal(size=(150, 2)), 0.0, 1.0))
    assert len(traces) == 1
    np.testing.assert_allclose(np.asarray(jax.vmap(cells)(batch)), separate, rtol=1e-12)
