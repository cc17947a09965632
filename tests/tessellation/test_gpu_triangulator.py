"""triangulator="cupy": the adapter and the device-side check on the CPU (scipy standing in for
CuPy's Delaunay), and, marked `gpu`, CuPy's gDel2D against CDT with exact in-circle arbitration."""

from fractions import Fraction

import equinox as eqx
import jax
import numpy as np
import pytest
from scipy.spatial import Delaunay

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.swarm._rebuild import update_host, update_in_trace
from jaxgeom.tessellation import _delaunay as delaunay_module
from jaxgeom.tessellation import _triangulators as triangulators
from jaxgeom.tessellation._delaunay import CapacityError, planar_graph_on_device
from jaxgeom.tessellation._device_check import (
    EULER,
    FLAT,
    LEFT_OUT,
    OK,
    OUT_OF_RANGE,
    planar_summary,
    planar_triangulation_status,
)


def point_sets(rng):
    swarm = rng.normal(size=(40, 2))[rng.integers(0, 40, 3000)] + 1e-3 * rng.normal(size=(3000, 2))  # clones
    i, j = np.meshgrid(np.arange(30), np.arange(30))
    return {
        "uniform": rng.random((3000, 2)),
        "gaussian": rng.normal(size=(3000, 2)),
        "clustered": swarm,
        "lattice": np.c_[i.ravel(), j.ravel()].astype(float) + 0.25 * (j.ravel() % 2)[:, None],
    }


def test_the_adapter_reads_simplices_checks_them_and_derives_the_adjacency(rng, stand_in):
    x = rng.random((2000, 2))
    tri = triangulators.gpu_triangulation(x, "cupy")
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
    assert "cupy raised RuntimeError" in built.fallback and built.fallback.endswith("; CDT built this graph instead")
    assert sorted(map(tuple, np.sort(built.tri.simplices, axis=1))) == sorted(
        map(tuple, np.sort(triangulators._cdt(x).simplices, axis=1))
    )


def test_cupy_is_refused_clearly_without_a_gpu_and_auto_passes_it_by(monkeypatch):
    if triangulators.cuda_cupy_available():
        pytest.skip("this machine has a GPU with CuPy")
    x = np.random.default_rng(0).random((50, 2))
    find_spec = triangulators.importlib.util.find_spec
    monkeypatch.setattr(
        triangulators.importlib.util, "find_spec", lambda name: None if name == "cupy" else find_spec(name)
    )
    with pytest.raises(ValueError, match=r"triangulator='cupy' is not installed: pip install \"jaxgeom\[cuda12\]\""):
        jaxgeom.delaunay(x, triangulator="cupy")
    monkeypatch.setattr(
        triangulators.importlib.util, "find_spec", lambda name: object() if name == "cupy" else find_spec(name)
    )
    with pytest.raises(ValueError, match=r"CuPy is installed, but JAX's backend is 'cpu'"):  # the extra on a CPU
        jaxgeom.delaunay(x, triangulator="cupy")
    assert triangulators.resolve_triangulator("auto", 2) != "cupy"


# --- the graph built on the device (scipy standing in for CuPy, the CPU for the GPU) ----------


@pytest.fixture
def stand_in(monkeypatch):
    """triangulator="cupy" served by scipy's Qhull and numpy in place of CuPy's gDel2D and CuPy;
    per call of `device_triangles`, whether it was handed a JAX array (the positions where they
    live) or a host array."""
    calls = []
    real = triangulators.device_triangles

    def spied(points, *args):
        calls.append("jax" if isinstance(points, jax.Array) else "host")
        return real(points, *args)

    monkeypatch.setitem(triangulators.DEVICE_BACKENDS, "cupy", lambda: (Delaunay, np))
    monkeypatch.setattr(triangulators, "device_triangles", spied)
    monkeypatch.setattr(delaunay_module, "device_triangles", spied)
    monkeypatch.setattr(triangulators, "installed", lambda name: True)
    return calls


def same_graph(ours, ref):
    assert ours.capacity == ref.capacity
    for field in ("neighbors", "tier", "hull", "overflow"):
        np.testing.assert_array_equal(np.asarray(getattr(ours, field)), np.asarray(getattr(ref, field)), err_msg=field)
    assert sorted(map(tuple, np.sort(np.asarray(ours.simplices), axis=1))) == sorted(
        map(tuple, np.sort(np.asarray(ref.simplices), axis=1))
    )


@pytest.mark.parametrize("name", ["uniform", "gaussian", "clustered"])
def test_the_device_build_gives_cdts_graph_field_for_field(rng, stand_in, name):
    x = point_sets(rng)[name][:2900]  # 2900 walkers: padded to a bucket of 3072
    ours, reason = planar_graph_on_device(jax.numpy.asarray(x), None, None, "cupy")
    assert reason is None and stand_in == ["jax"]
    same_graph(ours, jaxgeom.delaunay(x, triangulator="cdt"))
    box = (x.min(axis=0) - 0.1, x.max(axis=0) + 0.1)
    same_graph(jaxgeom.delaunay(x, triangulator="cupy", box=box), jaxgeom.delaunay(x, triangulator="cdt", box=box))


def test_the_device_build_keeps_pinned_capacities_and_refuses_too_small_ones(rng, stand_in):
    x = rng.random((500, 2))
    ref = jaxgeom.delaunay(x, triangulator="cdt", capacity=(1200, 24))
    same_graph(jaxgeom.delaunay(x, triangulator="cupy", capacity=(1200, 24)), ref)
    need = int(np.max(np.sum(np.asarray(ref.neighbors) < 500, axis=1)))
    with pytest.raises(CapacityError, match="too small for this graph"):
        jaxgeom.delaunay(x, triangulator="cupy", capacity=(1200, need - 1))


def test_a_failed_device_check_falls_back_to_cdt_and_says_why(rng, stand_in, monkeypatch):
    x = rng.random((400, 2))
    clockwise = lambda q: type("T", (), {"simplices": Delaunay(q).simplices[:, [0, 2, 1]]})  # noqa: E731
    monkeypatch.setitem(triangulators.DEVICE_BACKENDS, "cupy", lambda: (clockwise, np))
    with pytest.warns(
        RuntimeWarning,
        match="cupy's triangulation failed its check: triangles flat or negatively.*; CDT built this graph instead",
    ):
        tess = jaxgeom.delaunay(x, triangulator="cupy")
    same_graph(tess, jaxgeom.delaunay(x, triangulator="cdt"))
    monkeypatch.setitem(triangulators.DEVICE_BACKENDS, "cupy", lambda: (lambda q: 1 / 0, np))
    assert planar_graph_on_device(jax.numpy.asarray(x), None, None, "cupy") == (
        None,
        "cupy raised ZeroDivisionError: division by zero",
    )


def test_positions_the_device_build_refuses_get_the_host_paths_error(rng, stand_in):
    x = rng.random((300, 2))
    bad = x.copy()
    bad[7] = np.nan
    assert planar_graph_on_device(jax.numpy.asarray(bad), None, None, "cupy") == (None, None)
    far = 1e11 + x * 1e-2  # float64 rounds these to 4% of their spacing: triangulated, then refused
    with pytest.raises(ValueError, match="cannot be resolved in float64") as ours:
        planar_graph_on_device(jax.numpy.asarray(far), None, None, "cupy")
    with pytest.raises(ValueError) as theirs:
        jaxgeom.delaunay(far, triangulator="cdt")
    assert str(ours.value) == str(theirs.value)


def test_the_device_check_skips_padding_rows_and_walkers(rng):
    x = rng.random((300, 2))
    s = Delaunay(x).simplices.astype(np.int32)
    padded = np.vstack([s, np.full((40, 3), 300, np.int32)])
    assert int(planar_triangulation_status(x, padded)[0]) == OK
    walkers = np.vstack([x, np.repeat(x[:1], 20, axis=0)])  # 320 walkers, the last 20 padding
    triangles = np.where(padded == 300, 320, padded)
    (counts, box), adjacency = planar_summary(walkers, triangles, 0, 300)
    ref = Delaunay(x)
    assert counts.tolist()[:2] == [OK, len(s)]
    assert int(counts[2]) == max(
        len(r) for r in np.split(ref.vertex_neighbor_vertices[1], ref.vertex_neighbor_vertices[0][1:-1])
    )
    np.testing.assert_array_equal(np.asarray(adjacency)[: len(s)], ref.neighbors)
    assert (np.asarray(adjacency)[len(s) :] == -1).all()
    np.testing.assert_array_equal(np.asarray(box), np.r_[x.min(axis=0), x.max(axis=0), np.abs(x).max()])
    assert int(planar_summary(walkers, triangles[1:], 0, 300)[0][0][0]) == EULER
    assert int(planar_summary(walkers, triangles, 0, 301)[0][0][0]) == LEFT_OUT  # walker 300 in no triangle
    assert int(planar_summary(walkers, triangles, 1, 300)[0][0][0]) == FLAT


def test_both_edge_sorts_order_the_keys_alike(rng):
    from jaxgeom.tessellation._device_check import sort_by_two_keys, sort_in_two_radix_passes

    lo, hi = (jax.numpy.asarray(rng.integers(0, 50, 3000), jax.numpy.int32) for _ in range(2))
    one, two = sort_by_two_keys(lo, hi), sort_in_two_radix_passes(lo, hi)
    order = np.lexsort((np.asarray(hi), np.asarray(lo)))  # numpy: the last key is the primary one
    for ours in (one, two):
        np.testing.assert_array_equal(np.asarray(ours[0]), np.asarray(lo)[order])
        np.testing.assert_array_equal(np.asarray(ours[1]), np.asarray(hi)[order])
        np.testing.assert_array_equal(np.asarray(lo)[np.asarray(ours[2])], np.asarray(ours[0]))
        np.testing.assert_array_equal(np.asarray(hi)[np.asarray(ours[2])], np.asarray(ours[1]))
    np.testing.assert_array_equal(np.asarray(two[2]), order)  # stable: ties keep their order


@pytest.mark.parametrize("rebuild_every, tight", [(1, False), (3, False), (1, True)])
def test_simulate_rebuilds_on_the_device_as_cdt_would(rng, stand_in, rebuild_every, tight):
    x = rng.uniform(-3, 3, (300, 2))
    degree = int(np.max(np.sum(np.asarray(jaxgeom.delaunay(x).neighbors) < 300, axis=1)))
    capacity = (600, degree) if tight else None  # tight: the rebuilds must grow it
    params = jaxgeom.SwarmParams(dt=0.05, nu=0.3)
    run = lambda t: jaxgeom.simulate(  # noqa: E731
        rastrigin,
        jaxgeom.init_swarm(rastrigin, x, key=1, triangulator=t, capacity=capacity),
        params,
        n_steps=6,
        rebuild_every=rebuild_every,
        observe=("mean_ricci", "n_clones"),
    )
    ref_state, ref = run("cdt")
    stand_in.clear()
    state, history = run("cupy")
    builds = 6 // rebuild_every + int(history["n_reallocations"])  # a graph that did not fit is built again
    assert stand_in == ["host"] + ["jax"] * builds  # the first graph, then every rebuild
    assert int(history["n_reallocations"]) == int(ref["n_reallocations"]) == int(tight)
    assert int(history["n_triangulator_fallbacks"]) == 0 and history["n_clones"].sum() > 0
    np.testing.assert_allclose(state.positions, ref_state.positions, rtol=1e-10)
    np.testing.assert_allclose(history["mean_ricci"], ref["mean_ricci"], rtol=1e-10)
    same_graph(state.tess, ref_state.tess)


def callback_run(x, triangulator, nu=0.3, capacity=None):
    state = jaxgeom.init_swarm(rastrigin, x, key=1, triangulator=triangulator, capacity=capacity)
    return simulate_callback(state, nu)


def simulate_callback(state, nu):
    return jaxgeom.simulate(
        rastrigin,
        state,
        jaxgeom.SwarmParams(dt=0.05, nu=nu),
        n_steps=4,
        rebuild="callback",
        observe=("mean_fitness", "mean_ricci"),
    )[1]


def test_the_callback_rebuild_triangulates_in_a_buffer_callback_under_jit_vmap_and_grad(rng, stand_in, monkeypatch):
    x = rng.uniform(-3, 3, (200, 2))
    calls = []
    real = triangulators.padded_triangles
    monkeypatch.setattr(triangulators, "padded_triangles", lambda *a: calls.append(1) or real(*a))
    swarm = jaxgeom.init_swarm(rastrigin, x, key=1, triangulator="cupy")
    run = jax.jit(lambda nu: simulate_callback(swarm, nu))
    ours, ref = run(0.3), callback_run(x, "cdt")
    assert len(calls) == 5 and int(ours["n_triangulator_fallbacks"]) == 0  # the first graph and 4 rebuilds
    for name in ("mean_fitness", "mean_ricci"):
        np.testing.assert_allclose(ours[name], ref[name], rtol=1e-10)
    rebuilt = lambda p: update_in_trace(eqx.tree_at(lambda s: s.positions, swarm, p), 8)  # noqa: E731
    moved = swarm.positions + 0.05 * jax.numpy.sin(3 * swarm.positions)
    both = jax.vmap(rebuilt)(jax.numpy.stack([moved, swarm.positions]))  # one swarm after the other
    for k, p in enumerate((moved, swarm.positions)):
        np.testing.assert_array_equal(
            np.asarray(both.tess.neighbors[k]), np.asarray(jax.jit(rebuilt)(p).tess.neighbors)
        )
    np.testing.assert_array_equal(np.asarray(both.tess.neighbors[1]), np.asarray(swarm.tess.neighbors))
    np.testing.assert_array_equal(np.asarray(both.n_triangulator_fallbacks), [0, 0])
    gradient = jax.grad(lambda p: jax.numpy.sum(rebuilt(p).positions ** 2))(moved)  # positions pass through
    np.testing.assert_allclose(np.asarray(gradient), 2 * np.asarray(moved), rtol=1e-14)


@pytest.mark.slow
def test_the_callback_rebuild_falls_back_to_cdt_counted_and_grows_as_cdt_does(rng, stand_in, monkeypatch):
    x = rng.uniform(-3, 3, (200, 2))
    ref = callback_run(x, "cdt")
    monkeypatch.setitem(triangulators.DEVICE_BACKENDS, "cupy", lambda: (lambda q: 1 / 0, np))
    failing = callback_run(x, "cupy")
    assert int(failing["n_triangulator_fallbacks"]) == 5  # the first graph and 4 rebuilds, all by CDT
    np.testing.assert_allclose(failing["mean_fitness"], ref["mean_fitness"], rtol=1e-10)
    monkeypatch.setitem(triangulators.DEVICE_BACKENDS, "cupy", lambda: (Delaunay, np))
    degree = int(np.max(np.sum(np.asarray(jaxgeom.delaunay(x).neighbors) < 200, axis=1)))
    tight = callback_run(x, "cupy", capacity=(400, degree))  # the rebuilds outgrow it: overflow, grow, rerun
    assert int(tight["n_reallocations"]) == int(callback_run(x, "cdt", capacity=(400, degree))["n_reallocations"]) > 0
    np.testing.assert_allclose(tight["mean_fitness"], ref["mean_fitness"], rtol=1e-10)


def incircle(a, b, c, d) -> Fraction:
    """> 0 when d lies inside the circle through the counter-clockwise a, b, c; exact."""
    rows = [[Fraction(p[0]) - Fraction(d[0]), Fraction(p[1]) - Fraction(d[1])] for p in (a, b, c)]
    m = [[u, v, u * u + v * v] for u, v in rows]
    return (
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    )


def locally_delaunay_everywhere(x, simplices, adjacency) -> bool:
    for t, (tri, across) in enumerate(zip(simplices, adjacency, strict=True)):
        for other in across:
            if other > t:
                opposite = next(v for v in simplices[other] if v not in tri)
                if incircle(*x[tri], x[opposite]) > 0:
                    return False
    return True


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["uniform", "gaussian", "clustered", "lattice"])
def test_cupy_gives_cdts_graph_or_an_equally_delaunay_one(rng, name):
    if not triangulators.cuda_cupy_available():
        pytest.skip('needs a CUDA GPU with CuPy (pip install "jaxgeom[cuda12]")')
    x = point_sets(rng)[name]
    gpu, cdt = triangulators._cupy(jax.numpy.asarray(x)), triangulators._cdt(x)
    ours, theirs = (set(map(tuple, np.sort(t.simplices, axis=1))) for t in (gpu, cdt))
    if ours != theirs:  # only co-circular quadruples may differ: both must be Delaunay, exactly
        assert locally_delaunay_everywhere(x, gpu.simplices, gpu.neighbors)
        assert locally_delaunay_everywhere(x, cdt.simplices, cdt.neighbors)
    a, b = jaxgeom.delaunay(x, triangulator="cupy"), jaxgeom.delaunay(x, triangulator="cdt")
    np.testing.assert_allclose(
        np.asarray(jaxgeom.voronoi_volumes(a)), np.asarray(jaxgeom.voronoi_volumes(b)), rtol=1e-9, equal_nan=True
    )


@pytest.mark.gpu
def test_a_cupy_rebuild_keeps_the_positions_on_the_device(rng):
    if not triangulators.cuda_cupy_available():
        pytest.skip('needs a CUDA GPU with CuPy (pip install "jaxgeom[cuda12]")')
    state = jaxgeom.init_swarm(rastrigin, rng.uniform(-3, 3, (20_000, 2)), triangulator="cupy")
    moved = eqx.tree_at(lambda s: s.positions, state, state.positions + 0.01 * jax.numpy.sin(state.positions * 7))
    with jax.transfer_guard_device_to_host("disallow"):  # an implicit copy of the positions raises
        rebuilt, grew, separated = update_host(moved, 8)
    assert int(rebuilt.n_triangulator_fallbacks) == 0 and separated == 0
    same_graph(
        rebuilt.tess, jaxgeom.delaunay(np.asarray(moved.positions), triangulator="cdt", capacity=rebuilt.tess.capacity)
    )


@pytest.mark.gpu
def test_cupy_rebuilds_in_a_trace_on_xlas_stream_as_cdt_does(rng):
    if not triangulators.cuda_cupy_available():
        pytest.skip('needs a CUDA GPU with CuPy (pip install "jaxgeom[cuda12]")')
    x = rng.uniform(-3, 3, (5000, 2))
    ours, ref = callback_run(x, "cupy"), callback_run(x, "cdt")
    assert int(ours["n_triangulator_fallbacks"]) == 0
    np.testing.assert_allclose(ours["mean_fitness"], ref["mean_fitness"], rtol=1e-9)
    swarm = jaxgeom.init_swarm(rastrigin, x, key=1, triangulator="cupy")
    batched = jax.jit(jax.vmap(lambda nu: simulate_callback(swarm, nu)["mean_fitness"][-1]))(
        jax.numpy.array([0.3, 0.1])
    )
    np.testing.assert_allclose(float(batched[0]), float(ref["mean_fitness"][-1]), rtol=1e-9)
