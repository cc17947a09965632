"""Legal input that used to exhaust memory, hang, or return wrong answers silently (issue 12)."""

import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import padded_sets, scipy_neighbor_sets

import jaxgeom
from jaxgeom.cli import main
from jaxgeom.swarm._divergence import SimulationDiverged
from jaxgeom.tessellation._delaunay import CapacityError
from jaxgeom.tessellation._planar import sort_rows


def ring_with_hub(n):
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.vstack([np.c_[np.cos(t), np.sin(t)], [[0.0, 0.0]]])


def test_a_walker_ringed_by_200_others(rng):
    x = ring_with_hub(200)
    tess = jaxgeom.delaunay(x)
    assert padded_sets(tess.neighbors, 201) == scipy_neighbor_sets(x)
    assert int(tess.degree[200]) == 200 and not bool(tess.overflow)
    area = np.asarray(jaxgeom.voronoi_volumes(tess))[200]
    # the hub's cell: a regular 200-gon whose apothem is half the distance to the ring
    np.testing.assert_allclose(area, 200 * 0.5**2 * np.tan(np.pi / 200), rtol=1e-12)


@pytest.mark.parametrize("network", [True, None])
@pytest.mark.parametrize("width", [5, 32, 33, 100])
def test_rows_are_sorted_at_any_width(rng, width, network):
    columns = jnp.asarray(rng.integers(0, 50, (width, 40)), jnp.int32)
    expected = np.sort(np.asarray(columns).T, axis=1)
    np.testing.assert_array_equal(np.asarray(sort_rows(columns, network=network)), expected)


def test_a_fine_grid_far_from_the_origin_triangulates_like_at_the_origin():
    grid = np.stack(np.meshgrid(np.arange(12.0), np.arange(12.0)), -1).reshape(-1, 2) * 1e-6
    grid += np.random.default_rng(1).uniform(-1e-8, 1e-8, grid.shape)
    box = (-0.5e-6, 11.5e-6)
    here, far = jaxgeom.delaunay(grid, box=box), jaxgeom.delaunay(grid + 1e6, box=(box[0] + 1e6, box[1] + 1e6))
    assert padded_sets(here.neighbors, len(grid)) == padded_sets(far.neighbors, len(grid))
    interior = np.asarray(far.interior)
    assert interior.sum() > 50
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(far))[interior], 1e-12, rtol=0.05)


def test_a_thin_strip_is_not_collinear(rng):
    x = rng.random((400, 2)) * [1.0, 1e-7]
    tess = jaxgeom.delaunay(x)
    assert padded_sets(tess.neighbors, 400) == scipy_neighbor_sets(x)
    with pytest.raises(ValueError, match="collinear"):
        jaxgeom.delaunay(np.c_[np.linspace(0.0, 1.0, 50), 0.3 * np.linspace(0.0, 1.0, 50) + 1e6])


def bowl(x):
    return jnp.sum(x**2 - 2.0 * jnp.cos(3.0 * x))


@pytest.fixture
def bowl_swarm(rng):
    return jaxgeom.init_swarm(bowl, rng.uniform(-3.0, 3.0, (200, 2)), key=0)


@pytest.mark.parametrize("rebuild", ["host", "callback"])
def test_a_diverging_swarm_stops_with_the_step_and_the_cause(bowl_swarm, rebuild):
    with pytest.raises(SimulationDiverged, match=r"diverged by step \d+ .*reduce dt below"):
        jaxgeom.simulate(
            bowl, bowl_swarm, jaxgeom.SwarmParams(dt=10.0), n_steps=30, rebuild=rebuild, observe=("mean_fitness",)
        )


def test_a_diverging_swarm_is_flagged_under_jit(bowl_swarm):
    def last_fitness(dt):
        params = jaxgeom.SwarmParams(dt=dt, cloning=False)
        return jaxgeom.simulate(bowl, bowl_swarm, params, n_steps=8, rebuild="callback", observe=("mean_fitness",))[1][
            "diverged_step"
        ]

    assert int(jax.jit(last_fitness)(10.0)) > 0 and int(jax.jit(last_fitness)(0.01)) == -1


def test_huge_forces_are_a_divergence_not_a_degenerate_swarm(rng):
    steep = lambda x: 1e30 * jnp.sum(x**2)  # noqa: E731
    state = jaxgeom.init_swarm(steep, rng.uniform(-1.0, 1.0, (100, 2)))
    with pytest.raises(SimulationDiverged, match="reduce dt"):
        jaxgeom.simulate(steep, state, jaxgeom.SwarmParams(), n_steps=5, observe=("mean_fitness",))


def test_the_cli_exits_non_zero_on_divergence(capsys):
    assert (
        main(
            [
                "simulate",
                "--n",
                "100",
                "--steps",
                "20",
                "--dt",
                "5",
                "--gap-every",
                "0",
                "--no-progress",
                "--precision",
                "float64",
            ]
        )
        == 2
    )  # the CLI sets jax_enable_x64 for the process
    assert "diverged by step" in capsys.readouterr().err


def test_anisotropic_noise_needs_a_positive_floor():
    with pytest.raises(ValueError, match="eps_sigma.*anisotropic"):
        jaxgeom.SwarmParams(anisotropic=True, eps_sigma=0.0)


def test_a_zero_metric_is_named_not_run_on(rng):
    """eps_sigma = 0 on a linear landscape: the Hessian metric is 0. Once: NaN curvature
    without a word, infinite metric weights, and simulate blamed dt."""
    linear = lambda x: jnp.sum(x)  # noqa: E731
    x = rng.random((200, 2))
    tess = jaxgeom.delaunay(x)
    with pytest.warns(UserWarning, match=r"eps_sigma = 0 leaves g = floor\(H\) singular.*Give eps_sigma > 0"):
        zero = jaxgeom.hessian_metric(linear, 0.0)
    assert np.all(np.isnan(np.asarray(jaxgeom.ricci_scalar(tess, metric=zero))))
    w = np.asarray(jaxgeom.edge_weights(tess, weights="metric_full", metric=zero))
    mask = np.asarray(tess.neighbor_mask)
    assert np.all(np.isnan(w[mask])) and np.all(w[~mask] == 0)
    force = jaxgeom.viscous_force(tess, rng.random((200, 2)), nu=0.1, weights="metric_full", metric=zero)
    assert np.all(np.isnan(np.asarray(force)))  # not 0: row normalisation keeps the NaN
    state = jaxgeom.init_swarm(linear, x)
    params = jaxgeom.SwarmParams(eps_sigma=0.0, weights="metric_full")
    with pytest.raises(
        SimulationDiverged, match=r"eps_sigma = 0\) is singular.*the zero metric at 200.*raise eps_sigma"
    ):
        jaxgeom.simulate(linear, state, params, n_steps=3, observe=("mean_fitness",))


@pytest.mark.parametrize("rebuild", ["host", "callback"])
@pytest.mark.parametrize("triangulator", ["qhull", "cdt"])
def test_cloning_onto_one_point_separates_the_walkers(rng, rebuild, triangulator):
    """Clones 1e-12 from their companions: Qhull merges such walkers (they are moved apart and
    counted); CDT's exact predicates triangulate them as they are (nothing to separate)."""
    swarm = jaxgeom.init_swarm(bowl, rng.uniform(-3.0, 3.0, (200, 2)), key=0, triangulator=triangulator)
    params = jaxgeom.SwarmParams(dt=0.01, clone_rate=1.0, clone_jitter=1e-12, temperature=0.0)
    final, history = jaxgeom.simulate(bowl, swarm, params, n_steps=10, rebuild=rebuild, observe=("n_clones",))
    assert history["n_clones"].sum() > 0
    assert (int(history["n_separated"]) > 0) == (triangulator == "qhull")
    x = np.asarray(final.positions)
    assert len(np.unique(x, axis=0)) == len(x)
    rebuilt = jaxgeom.delaunay(x, triangulator=triangulator)  # the state's graph is the graph of its positions
    assert padded_sets(final.tess.neighbors, len(x)) == padded_sets(rebuilt.neighbors, len(x))


def test_simulate_jits_vmaps_and_differentiates_with_the_callback_rebuild(bowl_swarm):
    def loss(nu):
        params = jaxgeom.SwarmParams(nu=nu, cloning=False)
        return jaxgeom.simulate(bowl, bowl_swarm, params, n_steps=4, rebuild="callback", observe=("mean_fitness",))[1][
            "mean_fitness"
        ][-1]

    eager = [float(loss(nu)) for nu in (0.1, 0.3)]
    np.testing.assert_allclose(float(jax.jit(loss)(0.1)), eager[0], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.vmap(loss)(jnp.array([0.1, 0.3]))), eager, rtol=1e-12)
    assert np.isfinite(float(jax.jit(jax.grad(loss))(0.1)))


def test_host_rebuild_under_a_trace_points_to_the_callback(bowl_swarm):
    def loss(nu):
        return jaxgeom.simulate(bowl, bowl_swarm, jaxgeom.SwarmParams(nu=nu), n_steps=2)[1]["mean_fitness"][-1]

    with pytest.raises(TypeError, match="rebuild='callback'"):
        jax.grad(loss)(0.1)


def test_init_swarm_keeps_a_pinned_capacity_or_raises(rng):
    x = rng.uniform(-1.0, 1.0, (300, 2))
    with pytest.raises(CapacityError, match="too small"):
        jaxgeom.init_swarm(bowl, x, capacity=(10, 4))
    assert jaxgeom.init_swarm(bowl, x, capacity=(640, 24)).tess.capacity == (640, 24)


@pytest.mark.parametrize("d", [2, 3, 4])
def test_small_eigh_and_cholesky_match_lapack(rng, d):
    from jaxgeom.base._simplex import small_cholesky, small_eigh

    a = rng.normal(size=(500, d, d))
    a = a + np.swapaxes(a, 1, 2)
    a[:3] = np.eye(d)  # repeated eigenvalues
    a[3] = 0.0
    values, vectors = small_eigh(jnp.asarray(a))
    np.testing.assert_allclose(np.asarray(values), np.linalg.eigvalsh(a), atol=1e-13)
    np.testing.assert_allclose(np.einsum("nij,nj,nkj->nik", vectors, values, vectors), a, atol=1e-13)
    spd = np.einsum("nij,nkj->nik", a, a) + np.eye(d)
    np.testing.assert_allclose(np.asarray(small_cholesky(jnp.asarray(spd))), np.linalg.cholesky(spd), atol=1e-13)


def run_with_watchdog(argv, seconds: float):
    import threading

    result = []
    worker = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    worker.start()
    worker.join(timeout=seconds)
    assert not worker.is_alive(), f"{' '.join(argv)} hung"
    assert result == [0]


@pytest.mark.slow
def test_analyze_in_3d_never_hangs():
    """The normal suite's `analyze --dim 3`: the same code path as the default size (the
    deadlock needed two batched LAPACK eigh calls at once; the divergence diagnosis and the
    metric use Jacobi now), at 800 walkers."""
    run_with_watchdog(["analyze", "--dim", "3", "--n", "800"], 150)


@pytest.mark.slow
def test_analyze_in_3d_at_its_default_size_never_hangs(tmp_path):
    """`analyze --dim 3` deadlocked in 4 of 6 runs: two batched LAPACK eigh calls at once on
    XLA's CPU thread pool. Three runs in one process, each within 150 s (about 30 s for the
    first, with compilation, and 5 s for the others on 2 cores)."""
    for _ in range(3):
        run_with_watchdog(["analyze", "--dim", "3"], 150)


def lattice(m, d, offset):
    return np.stack(np.meshgrid(*[np.arange(float(m))] * d, indexing="ij"), -1).reshape(-1, d) + offset


def face_neighbors(points, m):
    """{(j, shift)} of the 2d axis neighbours of each lattice walker on the m-periodic torus."""
    index = {tuple(np.floor(p).astype(int) % m): i for i, p in enumerate(points)}
    d = points.shape[1]
    out = []
    for p in points:
        cell, row = np.floor(p).astype(int), set()
        for axis, step in itertools.product(range(d), (-1, 1)):
            q = cell.copy()
            q[axis] += step
            row.add((index[tuple(q % m)], tuple((q // m).tolist())))
        out.append(row)
    return out


@pytest.mark.parametrize("d, m, offset", [(2, 30, 0.0), (2, 30, 0.5), (2, 16, 0.25), (3, 6, 0.0), (3, 6, 0.5)])
def test_periodic_lattices_are_exact(d, m, offset):
    x = lattice(m, d, offset)
    tess = jaxgeom.delaunay(x, box=(0.0, float(m)), periodic=True)
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(tess)), 1.0, rtol=1e-12)
    nbrs, shifts = np.asarray(tess.neighbors), np.asarray(tess.neighbor_shifts)
    rows = [
        {(int(j), tuple(s.tolist())) for j, s in zip(nb, sh, strict=True) if j < len(x)}
        for nb, sh in zip(nbrs, shifts, strict=True)
    ]
    assert rows == face_neighbors(x, m)


def test_a_boxed_lattice_has_face_neighbours_and_unit_cells():
    x = lattice(12, 2, 0.5)
    tess = jaxgeom.delaunay(x, box=(0.0, 12.0))
    interior = np.asarray(tess.interior)
    assert interior.sum() > 50
    np.testing.assert_allclose(np.asarray(jaxgeom.voronoi_volumes(tess))[interior], 1.0, rtol=1e-12)
    assert set(np.asarray(tess.degree)[interior].tolist()) == {4}


@pytest.mark.parametrize("h", [1e-3, 1e-6])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_constant_metric_is_flat_at_any_spacing(rng, h, dtype):
    """float32 gave mean |R| = 1.2e3 at h ~ 2e-5 on a constant metric (eps / h^2 cancellation)."""
    x = (rng.random((1500, 2)) * h * np.sqrt(1500)).astype(dtype)
    tess = jaxgeom.delaunay(x, box=(0.0, h * np.sqrt(1500)))
    g = jnp.tile(2.1 * jnp.eye(2, dtype=tess.points.dtype), (1500, 1, 1))
    interior = np.asarray(tess.interior)
    ricci = np.asarray(jaxgeom.ricci_scalar(tess, metric=g))[interior]
    resolution = np.asarray(jaxgeom.ricci_resolution(tess, metric=g))[interior]
    assert np.all(np.abs(ricci) <= resolution) and np.all(ricci == 0.0)
    quadratic = jaxgeom.hessian_metric(lambda p: jnp.sum(p**2), 0.1)  # constant Hessian metric
    assert np.all(np.asarray(jaxgeom.ricci_scalar(tess, metric=quadratic))[interior] == 0.0)


@pytest.mark.parametrize("d", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_float32_curvature_error_stays_below_the_stated_resolution(rng, d):
    from jaxgeom.apps._landscapes import double_well

    x = (0.3 + 0.01 * rng.random((800, d))).astype(np.float32)  # the same points in both precisions
    metric = jaxgeom.hessian_metric(double_well, 0.1)
    r = {}
    for dtype in (np.float32, np.float64):
        tess = jaxgeom.delaunay(x.astype(dtype), box=(0.3, 0.31))
        r[dtype] = (
            np.asarray(jaxgeom.ricci_scalar(tess, metric=metric)),
            np.asarray(jaxgeom.ricci_resolution(tess, metric=metric)),
        )
    interior = np.asarray(tess.interior)
    ratio = np.abs(r[np.float32][0] - r[np.float64][0])[interior] / r[np.float32][1][interior]
    assert np.percentile(ratio, 99) < 1.0 and np.all(np.isfinite(ratio))


@pytest.mark.parametrize("scale", [1e-20, 1e20])
def test_float32_swarms_outside_the_representable_range_are_refused(rng, scale):
    with pytest.raises(ValueError, match=r"spacing of .* outside what float32 .* spacings in \["):
        jaxgeom.delaunay(rng.random((300, 2)).astype(np.float32) * scale)


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_float32_curvature_and_volumes_work_at_extreme_but_representable_scales(rng, scale):
    x = rng.random((400, 3))
    metric = np.tile(np.eye(3), (400, 1, 1)) * (1.0 + 1e-3 * np.arange(400))[:, None, None]
    ref = jaxgeom.delaunay(x)
    tess = jaxgeom.delaunay((x * scale).astype(np.float32))
    interior = np.asarray(ref.interior)
    np.testing.assert_allclose(
        np.asarray(jaxgeom.voronoi_volumes(tess))[interior] / scale**3,
        np.asarray(jaxgeom.voronoi_volumes(ref))[interior],
        rtol=1e-3,
    )
    ricci = np.asarray(jaxgeom.ricci_scalar(tess, metric=metric.astype(np.float32) / scale**2))[
        interior
    ]  # R is invariant
    assert np.all(np.isfinite(ricci))
    np.testing.assert_allclose(
        ricci, np.asarray(jaxgeom.ricci_scalar(ref, metric=metric))[interior], rtol=2e-2, atol=2e-2
    )


@pytest.mark.slow  # meaningful at XLA's default optimisation level: CI runs this module's slow tests that way
@pytest.mark.parametrize("n", [5000, 16384, 30720])
def test_float32_hessians_are_symmetric_at_every_batch_size(n):
    """jaxlib 0.10.2 miscompiled this on CPU (asymmetric, entries off by 15% at n = 16384 and
    30720): pyproject.toml excludes it (jax-ml/jax#39103)."""
    from jaxgeom.apps._landscapes import double_well

    x = jnp.asarray((0.3 + np.random.default_rng(0).random((n, 3))).astype(np.float32))
    h = np.asarray(jax.jit(jax.vmap(jax.hessian(double_well)))(x))
    np.testing.assert_allclose(h, np.swapaxes(h, 1, 2), atol=0)
    np.testing.assert_allclose(h, np.asarray(jax.vmap(jax.hessian(double_well))(x)), atol=1e-5)


def test_the_bulk_gap_ignores_detached_stragglers(rng):
    from jaxgeom.geometry._spectral import bulk_spectral_gap

    cluster = rng.normal(size=(300, 2)) * 0.1
    stragglers = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [0.0, -3.0], [2.5, 2.5]])
    tess = jaxgeom.delaunay(np.vstack([cluster, stragglers]))
    assert float(jaxgeom.spectral_gap(tess, k=2)[1]) < 1e-5  # the whole graph: weights exp(-160), i.e. 0
    gap, n_comp, outside = bulk_spectral_gap(tess)
    assert n_comp == 6 and outside == 5
    lap = jaxgeom.graph_laplacian(tess)
    w = np.asarray(lap.weights)
    dense = np.zeros((305, 305))
    for i, row in enumerate(np.asarray(tess.neighbors)):
        for k, j in enumerate(row):
            if j < 305 and j < 300 and i < 300:
                dense[i, j] = w[i, k]
    sub = dense[:300, :300]
    s = 1.0 / np.sqrt(sub.sum(1))
    reference = np.linalg.eigvalsh(np.eye(300) - s[:, None] * sub * s[None, :])[1]
    np.testing.assert_allclose(gap, reference, rtol=1e-8)


def test_a_failing_spectral_gap_never_ends_a_run(monkeypatch, bowl_swarm):
    import scipy.sparse.linalg

    import jaxgeom.swarm._history as sim

    def broken(tess):
        raise scipy.sparse.linalg.ArpackNoConvergence("no convergence", np.zeros(0), np.zeros((0, 0)))

    monkeypatch.setattr(sim, "bulk_spectral_gap", broken)
    with pytest.warns(RuntimeWarning, match="spectral gap failed"):
        _, history = jaxgeom.simulate(
            bowl, bowl_swarm, jaxgeom.SwarmParams(), n_steps=2, spectral_gap_every=1, observe=("mean_fitness",)
        )
    assert np.isnan(history["spectral_gap"]).all() and len(history["mean_fitness"]) == 3


def test_float32_lobpcg_is_accurate_or_nan(rng):
    x = rng.random((2000, 2)).astype(np.float32)
    x64 = jax.enable_x64 if hasattr(jax, "enable_x64") else jax.experimental.enable_x64  # jax >= 0.8 / older
    with x64(False):
        tess = jaxgeom.delaunay(x)
        lam = np.asarray(jaxgeom.spectral_gap(tess, k=3, method="lobpcg", seed=1))
    reference = np.asarray(jaxgeom.spectral_gap(jaxgeom.delaunay(x.astype(np.float64)), k=3))
    ok = np.isfinite(lam)
    np.testing.assert_allclose(lam[ok], reference[ok], rtol=2e-2, atol=1e-6)


@pytest.mark.slow
def test_analyze_periodic_on_its_own_sample_and_notes_the_geometric_reference(tmp_path):
    assert main(["analyze", "--periodic", "--n", "2000", "--out", str(tmp_path)]) == 0
    import json

    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["graph"]["tier2"] == 2000
    np.testing.assert_allclose(report["volumes"]["tier2_total"], 25.0, rtol=1e-9)
    np.testing.assert_allclose(report["volumes"]["total_in_box"], 25.0, rtol=1e-9)
    assert "spacing" in report["estimation"]["geometric_reference"]
    assert report["curvature"]["tier2_volume_weighted_ricci_resolution"] > 0


def test_high_dimensional_default_samples_are_fast_and_exact():
    import time

    from jaxgeom.apps._landscapes import double_well, sample_boltzmann

    start = time.perf_counter()
    x, box = sample_boltzmann("double_well", 5000, 10)
    assert time.perf_counter() - start < 5.0 and x.shape == (5000, 10) and np.all(np.abs(x) <= 2.5)
    ours, _ = sample_boltzmann("double_well", 20000, 3, seed=1)
    rng = np.random.default_rng(2)
    trial = rng.uniform(-2.5, 2.5, (400_000, 3))
    accepted = trial[rng.random(len(trial)) < np.exp(-2.0 * np.asarray(double_well(trial)))]
    np.testing.assert_allclose(ours.var(axis=0), accepted.var(axis=0), rtol=0.05)


@pytest.mark.parametrize("d", [2, 3])
def test_without_a_box_cells_reaching_outside_the_hull_are_tier_0(rng, d):
    from helpers import brute_force_tiers

    x = rng.random((500, d))
    assert np.array_equal(np.asarray(jaxgeom.delaunay(x).tier), brute_force_tiers(x))


def test_volume_distortion_without_a_box_matches_the_boxed_value(rng):
    """It was 123 without a box and 0.301 with one: second-layer cells at the sample's edge
    reached 424x the mean volume and counted as interior."""
    x = rng.uniform(-5.0, 5.0, (5000, 2))
    free, boxed = jaxgeom.delaunay(x), jaxgeom.delaunay(x, box=(-5.0, 5.0))
    np.testing.assert_allclose(
        float(jaxgeom.volume_distortion(free)), float(jaxgeom.volume_distortion(boxed)), rtol=0.05
    )
