"""Outputs that are what their labels say: observables against independent computations from
the states, continued runs against one run, the spectral gap's components, cells clipped to
the box against scipy's half-space intersection, the CLI's reports and figures."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import scipy_voronoi_volumes
from scipy.spatial import ConvexHull, HalfspaceIntersection

import jaxgeom
from jaxgeom.apps._landscapes import LANDSCAPES
from jaxgeom.cli import main
from jaxgeom.geometry._spectral import bulk_spectral_gap, gap_rounding_level


def bowl(x):
    return 0.5 * jnp.sum(x**2)


def flat(x):
    return 0.0 * jnp.sum(x)


@pytest.mark.parametrize("d", [2, 3])
def test_velocity_variance_is_per_component(rng, d):
    state = jaxgeom.init_swarm(bowl, rng.normal(size=(60, d)), rng.normal(size=(60, d)) * np.arange(1, d + 1), key=1)
    final, history = jaxgeom.simulate(
        bowl, state, jaxgeom.SwarmParams(nu=0.0, cloning=False), n_steps=2, observe=("velocity_variance",)
    )
    v = np.asarray(final.velocities)
    np.testing.assert_allclose(history["velocity_variance"][-1], np.var(v, axis=0).mean(), rtol=1e-12)
    np.testing.assert_allclose(
        history["velocity_variance"][0], np.var(np.asarray(state.velocities), axis=0).mean(), rtol=1e-12
    )


def test_a_continued_simulation_equals_one_uninterrupted_call(rng):
    state = jaxgeom.init_swarm(bowl, rng.normal(size=(150, 2)), key=3)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=0.5, clone_rate=0.5)
    observe = ("mean_expansion", "velocity_variance", "volume_distortion", "n_clones")
    _, whole = jaxgeom.simulate(bowl, state, params, n_steps=6, observe=observe)
    half, first = jaxgeom.simulate(bowl, state, params, n_steps=3, observe=observe)
    _, second = jaxgeom.simulate(bowl, half, params, n_steps=3, observe=observe)
    assert np.isfinite(second["mean_expansion"][0]) and second["mean_expansion"][0] != 0.0  # was exactly 0.0
    for name in observe:
        joined = np.r_[np.asarray(first[name]), np.asarray(second[name])[1:]]
        np.testing.assert_allclose(joined, np.asarray(whole[name]), rtol=1e-12, atol=1e-12, equal_nan=True)
        assert second[name][0] == first[name][-1] or np.isnan(first[name][-1])


def test_expansion_is_the_volume_weighted_rate_of_the_states(rng):
    """mean_expansion of one noisy step with cloning, recomputed from the two states with scipy's
    Voronoi cells: the walkers tier 2 at both steps, clones included."""
    state = jaxgeom.init_swarm(bowl, rng.normal(size=(200, 2)), key=5)
    params = jaxgeom.SwarmParams(dt=0.05, temperature=1.0, clone_rate=1.0)
    observe = ("mean_expansion",)
    one, _ = jaxgeom.simulate(bowl, state, params, n_steps=1, observe=observe)
    two, history = jaxgeom.simulate(bowl, one, params, n_steps=1, observe=observe)
    before, after = scipy_voronoi_volumes(np.asarray(one.positions)), scipy_voronoi_volumes(np.asarray(two.positions))
    valid = np.asarray(one.tess.tier == 2) & np.asarray(two.tess.tier == 2)
    expected = np.log(after[valid].sum() / before[valid].sum()) / 0.05
    assert np.asarray(two.cloned).sum() > 5
    np.testing.assert_allclose(history["mean_expansion"][-1], expected, rtol=1e-10)
    # the per-cell mean that the label used to show is dominated by the jitter (Jensen)
    per_cell = np.nanmean((after[valid] - before[valid]) / before[valid]) / 0.05
    assert per_cell > expected


def test_expansion_under_a_known_uniform_expansion(rng):
    """v = a x with no force, noise or viscosity: x_n = (1 + n a dt) x_0, so the tier-2 volume
    grows by ((1 + n a dt) / (1 + (n - 1) a dt))^d per step."""
    x0 = rng.normal(size=(200, 2))
    rate, dt = 0.5, 0.01
    state = jaxgeom.init_swarm(flat, x0, rate * x0, key=0)
    params = jaxgeom.SwarmParams(dt=dt, gamma=0.0, temperature=0.0, nu=0.0, cloning=False)
    _, history = jaxgeom.simulate(flat, state, params, n_steps=5, observe=("mean_expansion",))
    n = np.arange(1, 6)
    expected = 2 * np.log((1 + n * rate * dt) / (1 + (n - 1) * rate * dt)) / dt
    assert np.isnan(history["mean_expansion"][0])
    np.testing.assert_allclose(history["mean_expansion"][1:], expected, rtol=1e-10)


def test_the_largest_component_has_a_resolved_gap(rng):
    """Two clusters joined only by edges of relative weight ~1e-10: one 'component' under the old
    1e-12 threshold, with a gap at float64 rounding; now two, and the gap is the cluster's own."""
    blob = rng.uniform(-1, 1, (400, 2))
    blob = blob[np.sum(blob**2, axis=1) < 1][:150]
    x = np.vstack([blob, blob[:140] + [3.3, 0.0]])
    tess = jaxgeom.delaunay(x)
    gap, n_comp, outside = bulk_spectral_gap(tess, length_scale=0.2)
    assert n_comp == 2 and outside == 140
    lap = jaxgeom.graph_laplacian(tess, length_scale=0.2)
    w = np.asarray(lap.weights)
    assert w[w > 0].min() < 1e-9 * w.max()  # the bridges exist, lighter than COMPONENT_RTOL
    dense = np.zeros((290, 290))
    for i, row in enumerate(np.asarray(tess.neighbors)):
        for k, j in enumerate(row):
            if j < 290 and w[i, k] > 1e-8 * w.max():
                dense[i, j] = w[i, k]
    sub = dense[:150, :150]
    s = 1 / np.sqrt(sub.sum(1))
    reference = np.linalg.eigvalsh(np.eye(150) - s[:, None] * sub * s[None, :])[1]
    np.testing.assert_allclose(gap, reference, rtol=1e-8)
    assert gap > 1e3 * gap_rounding_level(150)


def test_a_gap_at_rounding_level_is_flagged_in_the_history(monkeypatch, rng):
    import jaxgeom.swarm._history as sim

    monkeypatch.setattr(sim, "bulk_spectral_gap", lambda tess: (2.5e-15, 64, 10))
    state = jaxgeom.init_swarm(bowl, rng.normal(size=(60, 2)), key=0)
    _, history = jaxgeom.simulate(
        bowl, state, jaxgeom.SwarmParams(), n_steps=2, spectral_gap_every=1, observe=("mean_fitness",)
    )
    assert history["spectral_gap_rounding"].tolist() == [True, True, True]


def _clipped_cell_scipy(x, i, box):
    """Volume of box ∩ cell i from every other walker's half-space (scipy, tests only)."""
    d = x.shape[1]
    dx = np.delete(x, i, axis=0) - x[i]
    normals = np.vstack([dx, np.eye(d), -np.eye(d)])
    offsets = np.r_[0.5 * np.sum(dx * dx, axis=1), box[1] - x[i], x[i] - box[0]]
    corners = HalfspaceIntersection(np.c_[normals, -offsets], np.zeros(d)).intersections
    return ConvexHull(corners).volume


@pytest.mark.parametrize("d, n", [(2, 300), (3, 150)])
def test_cells_clipped_to_the_box(rng, d, n):
    lower, upper = np.zeros(d), np.array([1.0, 2.0, 0.5][:d])
    x = lower + rng.random((n, d)) * upper
    tess = jaxgeom.delaunay(x, box=(lower, upper))
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    raw = np.asarray(jaxgeom.voronoi_volumes(tess, clip=False))
    hull = np.asarray(tess.hull)
    assert hull.any() and np.isfinite(vol).all() and np.isnan(raw[hull]).all()
    np.testing.assert_allclose(vol.sum(), np.prod(upper), rtol=1e-12)
    reference = np.array([_clipped_cell_scipy(x, i, (lower, upper)) for i in range(n)])
    np.testing.assert_allclose(vol, reference, rtol=1e-10)
    inside = np.asarray(tess.tier) > 0  # tiers keep their meaning: these cells lie inside the box
    # unclipped, to rounding: two programs, whose code generation may round differently (ulps)
    np.testing.assert_allclose(vol[inside], raw[inside], rtol=1e-13)
    ricci = np.asarray(jaxgeom.ricci_scalar(tess))
    assert np.isnan(ricci[np.asarray(tess.tier) == 0]).all()


def test_clipped_volumes_are_differentiable(rng):
    x = rng.random((60, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0))
    volumes = lambda p: jaxgeom.voronoi_volumes(eqx.tree_at(lambda t: t.points, tess, p))  # noqa: E731
    total = jax.grad(lambda p: jnp.sum(volumes(p)))(jnp.asarray(x))
    np.testing.assert_allclose(total, 0.0, atol=1e-12)  # the cells tile the box whatever the walkers
    i = int(np.flatnonzero(np.asarray(tess.hull))[0])
    grad = np.asarray(jax.grad(lambda p: volumes(p)[i])(jnp.asarray(x)))
    step = np.zeros_like(x)
    step[i, 1] = 1e-6
    central = (volumes(jnp.asarray(x + step))[i] - volumes(jnp.asarray(x - step))[i]) / 2e-6
    np.testing.assert_allclose(grad[i, 1], central, rtol=1e-6)


def test_clipped_volumes_in_float32(rng):
    x = rng.random((200, 3)).astype(np.float32)
    with jax.enable_x64(False):
        vol = jaxgeom.voronoi_volumes(jaxgeom.delaunay(x, box=(0.0, 1.0)))
        assert vol.dtype == jnp.float32
        np.testing.assert_allclose(float(jnp.sum(vol)), 1.0, rtol=1e-5)


def test_an_undetermined_hessian_fit_warns_and_analyze_picks_k_from_d(rng):
    from jaxgeom.cli._analyze import default_k

    x = rng.normal(size=(300, 6))
    values = np.sum(x**2, axis=1)
    with pytest.warns(RuntimeWarning, match=r"undetermined \(NaN\) at \d+ of 300 walkers.*k >= 56"):
        jaxgeom.compare_estimation_methods(jaxgeom.knn_graph(x, 12), values, eps_sigma=0.1)
    assert default_k(10) == 76 and default_k(2) == 12 and all(default_k(d) > (d + 1) * (d + 2) // 2 for d in range(9))
    h = np.asarray(jaxgeom.estimate_hessian(jaxgeom.knn_graph(x, default_k(6)), values))
    assert np.isfinite(h).all(axis=(1, 2)).mean() > 0.9
    np.testing.assert_allclose(np.nanmedian(h, axis=0), 2 * np.eye(6), atol=1e-8)  # exact for a quadratic


def test_analyze_dim_5_names_the_flag(capsys):
    assert main(["analyze", "--dim", "5"]) == 2
    err = capsys.readouterr().err
    assert "--graph knn" in err and "knn_graph(" not in err


def test_knn_table_leaves_out_the_voronoi_observables(capsys):
    assert main(["simulate", "--graph", "knn", "--n", "80", "--steps", "2", "--gap-every", "0", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "nan" not in out.lower().replace("nan at step", "")
    assert "Not reported on a k-NN graph" in out and "mean_ricci" in out and "NaN at step 0" not in out


def test_help_states_the_landscape_boxes(capsys):
    halves = [half for _, _, half in LANDSCAPES.values()]
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert f"half width {min(halves):g} to {max(halves):g}" in " ".join(capsys.readouterr().out.split())


def test_readme_quick_tour_enables_float64():
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    start = readme.index("## Quick tour")
    tour = readme[start : readme.index("\n## ", start + 1)]
    assert 'jax.config.update("jax_enable_x64", True)' in tour
    assert "estimation.png" in readme


@pytest.fixture
def saved_figures(monkeypatch):
    """The matplotlib figures that the code under test saves (not written)."""
    import matplotlib.figure

    figures = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: figures.append(fig))
    return figures


def _overlapping_tick_labels(ax) -> list:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(ax.figure)  # the figure was closed after saving
    canvas.draw()
    renderer = canvas.get_renderer()
    pairs = []
    for axis in (ax.xaxis, ax.yaxis):
        labels = [t for t in axis.get_ticklabels(which="both") if t.get_visible() and t.get_text()]
        boxes = [t.get_window_extent(renderer) for t in labels]
        pairs += [
            (labels[i].get_text(), labels[j].get_text())
            for i in range(len(boxes))
            for j in range(i + 1, len(boxes))
            if boxes[i].overlaps(boxes[j])
        ]
    return pairs


def _tune_result(values_path):
    from types import SimpleNamespace

    iterations = [{"iteration": i, "loss": 10.0**-i, "values": v} for i, v in enumerate(values_path)]
    return SimpleNamespace(
        iterations=iterations,
        values=values_path[-1],
        solver="bfgs",
        message="converged",
        standard_errors={name: 0.02 for name in values_path[-1]},
    )


def test_tune_figure_ticks_do_not_overlap_and_one_parameter_shows_the_truth(saved_figures, tmp_path):
    from jaxgeom.cli._tune import plot_tuning

    path = [{"nu": 0.05, "eps_sigma": 0.2}, {"nu": 0.12, "eps_sigma": 0.11}, {"nu": 0.29, "eps_sigma": 0.06}]
    axes = [np.geomspace(0.033, 0.45, 4), np.geomspace(0.033, 0.3, 4)]
    grid = {"names": ["nu", "eps_sigma"], "axes": [a.tolist() for a in axes], "loss": np.ones((4, 4)).tolist()}
    plot_tuning(_tune_result(path), {"nu": 0.3, "eps_sigma": 0.05}, grid, tmp_path / "tune.png")
    assert _overlapping_tick_labels(saved_figures[-1].axes[1]) == []
    plot_tuning(_tune_result([{"nu": v["nu"]} for v in path]), {"nu": 0.3}, None, tmp_path / "tune.png")
    panel = saved_figures[-1].axes[1]
    assert any(line.get_label().startswith("truth") and np.allclose(line.get_ydata(), 0.3) for line in panel.lines)
    band = [patch for patch in panel.patches if patch.get_label() == "found +- 1 s.e."]
    assert len(band) == 1 and np.allclose([band[0].get_y(), band[0].get_height()], [0.29 - 0.02, 0.04])


@pytest.mark.parametrize("layout", ["one cluster", "three wells"])
def test_swarm_panels_show_every_walker_then_the_largest_cluster_then_the_distribution(saved_figures, tmp_path, layout):
    """Top row: one frame holding every walker (comparable panels). Middle row: each snapshot
    zoomed on its most populated cluster (once: a few dots in the whole box), holding 95% of
    it and at most 10x its spread wide; a uniform swarm gets a window a quarter of the frame
    wide. Bottom row: the distribution of the colour (shares summing to 1)."""
    from jaxgeom.apps._plots import plot_swarm_snapshots

    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0]]) if layout == "one cluster" else np.array([[-3.0, 2.0], [1.0, 1.0], [2.5, -3.0]])
    weights = np.array([1.0]) if layout == "one cluster" else np.array([0.2, 0.5, 0.3])
    later = [centres[rng.choice(len(centres), 300, p=weights)] + 0.05 * rng.normal(size=(300, 2)) for _ in range(2)]
    snaps = [{"step": 0, "positions": rng.uniform(-5, 5, (300, 2)), "ricci": None}]
    snaps += [{"step": 9 * (k + 1), "positions": x, "ricci": None} for k, x in enumerate(later)]
    plot_swarm_snapshots(bowl, snaps, (-5.0, 5.0), tmp_path / "swarm.png")
    figure = saved_figures[-1]
    top = [ax for ax in figure.axes if ax.get_title().startswith("step")]
    zoomed = [ax for ax in figure.axes if ax.get_title().startswith("zoom:")]
    histograms = [ax for ax in figure.axes if ax.get_title().startswith("median")]
    assert len(top) == len(zoomed) == len(histograms) == 3
    assert len({ax.get_xlim() for ax in top}) == 1 and len({ax.get_ylim() for ax in top}) == 1
    frame = max(np.ptp(top[0].get_xlim()), np.ptp(top[0].get_ylim()))
    (x0, x1), (y0, y1) = zoomed[0].get_xlim(), zoomed[0].get_ylim()
    assert max(x1 - x0, y1 - y0) <= 0.25 * frame + 1e-9, "a uniform swarm: a window, not the whole frame"
    biggest = centres[np.argmax(weights)]
    for ax, walkers in zip(zoomed[1:], later, strict=True):
        cluster = walkers[np.all(np.abs(walkers - biggest) < 0.5, axis=1)]
        (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
        inside = (cluster[:, 0] >= x0) & (cluster[:, 0] <= x1) & (cluster[:, 1] >= y0) & (cluster[:, 1] <= y1)
        assert inside.mean() >= 0.95
        assert max(x1 - x0, y1 - y0) <= 10 * np.max(np.std(cluster, axis=0))
    for ax in histograms:
        assert sum(patch.get_height() for patch in ax.patches) == pytest.approx(1.0)


def test_analyze_figures_are_labelled(saved_figures, tmp_path, capsys):
    assert main(["analyze", "--n", "400", "--dim", "3", "--out", str(tmp_path)]) == 0
    proxies, estimation = saved_figures[-2], saved_figures[-1]
    maps = [ax for ax in proxies.axes if ax.get_title()]
    assert all(ax.get_xlabel() == "x_1" and ax.get_ylabel() == "x_2" for ax in maps[:2])
    assert all(ax.get_ylabel() for ax in proxies.axes if ax not in maps)  # the colour bars
    assert "double_well" in proxies.get_suptitle() and "projected on (x_1, x_2)" in proxies.get_suptitle()
    low, high = estimation.axes[2].get_ylim()  # the convergence panel: whole decades, a flat line drawn flat
    assert high / low >= 10 - 1e-9
    assert "exact Hessian" in estimation.get_suptitle(), "a known landscape: errors against its exact Hessian"
    convergence = estimation.axes[2]
    assert convergence.get_title().startswith("convergence with walkers")
    errors = convergence.lines[0].get_ydata()
    assert len(errors) >= 2 and errors[-1] < errors[0], "the fit converges as the walkers get denser"
    eigen = estimation.axes[0]  # robust axes: the central 98% of the eigenvalues, outliers counted
    assert "beyond the axes" in eigen.get_title() and eigen.get_xlim() == eigen.get_ylim()
    capsys.readouterr()


def test_proxies_figure_has_no_all_zero_panel(saved_figures, tmp_path, capsys):
    """Without a metric the Ricci scalar is 0 at every walker: its panel gives way to the cells'
    volumes and the title says why."""
    np.save(tmp_path / "pts.npy", np.random.default_rng(0).random((200, 2)))
    assert main(["analyze", "--points", str(tmp_path / "pts.npy"), "--box", "0", "1", "--out", str(tmp_path)]) == 0
    proxies = next(fig for fig in saved_figures if fig.get_suptitle().startswith(str(tmp_path / "pts.npy")))
    titles = [ax.get_title() for ax in proxies.axes if ax.get_title()]
    assert not any("Ricci" in title for title in titles) and "Voronoi cell volume (log10)" in titles
    assert "no Ricci panel: R = 0 at every walker" in proxies.get_suptitle()
    for ax in proxies.axes:
        for collection in ax.collections:
            values = collection.get_array()
            if values is not None and len(values) > 1:
                assert np.ptp(np.asarray(values)) > 0, f"a constant panel: {ax.get_title()}"
    capsys.readouterr()


def test_observables_figure_labels_the_estimators(saved_figures, tmp_path):
    from jaxgeom.apps._plots import plot_observables

    t = np.arange(4) * 0.1
    series = {
        "time": t,
        "velocity_variance": np.array([1.0, 0.9, 0.8, 0.7]),
        "mean_expansion": np.array([np.nan, -1.0, -2.0, -1.5]),
    }
    plot_observables(series, [0, 2], [0.1, 2e-16], tmp_path / "o.png", gap_rounding=[False, True])
    labels = {ax.get_title(): ax.get_ylabel() for ax in saved_figures[-1].axes}
    assert labels["velocity variance per component"] == "tr Cov(v) / d"
    assert any("d ln(sum V_i)/dt" in label for label in labels.values())
    gap = next(ax for ax in saved_figures[-1].axes if ax.get_title().startswith("spectral gap"))
    assert any(line.get_label() == "below float64 resolution" for line in gap.lines)
