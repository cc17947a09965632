import argparse
import json
import re

import jax
import numpy as np
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import LANDSCAPES, sample_boltzmann
from jaxgeom.cli import main
from jaxgeom.cli._legend import SIMULATE_ROWS, analyze_definition


def assert_every_analyze_row_defined(printed: str) -> None:
    """Every `key value` row under a `[section]` of analyze's report has a definition (--explain)."""
    section, rows = None, 0
    for line in printed.splitlines():
        if re.fullmatch(r"\[\w+\]", line):
            section = line[1:-1]
        elif section and re.match(r"  \w", line):
            key = line.split()[0]
            assert analyze_definition(section, key), f"[{section}] {key} has no definition"
            rows += 1
    assert rows > 10 and "--explain defines every row" in printed


def assert_every_simulate_row_defined(printed: str) -> None:
    """Every row of simulate's table (the lines after the header with four values) has a definition."""
    lines = printed.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("observable"))
    names = []
    for line in lines[start + 1 :]:
        parts = line.split()
        if len(parts) != 5:
            break
        names.append(parts[0])
    assert len(names) > 8 and "spectral_gap" in names
    assert not [name for name in names if name not in SIMULATE_ROWS]


def test_analyze_default_sample_writes_consistent_summary(tmp_path, capsys):
    assert main(["analyze", "--n", "600", "--seed", "3", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert "[graph]" in printed and "[volumes]" in printed
    assert_every_analyze_row_defined(printed)
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["swarm"]["n_walkers"] == 600 and report["swarm"]["dim"] == 2
    assert report["curvature"]["precision"] == "float64"  # the default of both commands
    graph = report["graph"]
    assert graph["tier0"] + graph["tier1"] + graph["tier2"] == 600
    assert graph["tier0"] >= report["volumes"]["n_unbounded"] > 0  # also cells reaching outside the hull
    assert 5.5 < graph["degree_mean"] < 6.0
    assert report["timings_s"]["delaunay"] > 0
    assert report["metric"]["kind"] == "hessian" and report["metric"]["tier2_min_eigenvalue"] >= 0.1 - 1e-12
    curvature, cells = report["curvature"], report["cells"]
    assert np.isfinite(curvature["tier2_volume_weighted_ricci"]) and curvature["mean_abs_deficit"] > 0
    assert 0 < cells["tier2_shape_distortion_mean"] < 1 and cells["volume_distortion"] > 0
    assert (tmp_path / "proxies.png").stat().st_size > 10_000
    for proxy in ("ricci_scalar", "shape_distortion", "riemannian_volumes", "deficit_angles", "spectral_gap"):
        assert report["timings_s"][proxy] >= 0
    graph_proxies = report["graph_proxies"]
    assert 0 < graph_proxies["spectral_gap_largest_component"] < 1 and graph_proxies["kernel_graph_components"] == 1
    assert graph_proxies["best_walker_geodesic_eccentricity"] > 0 and graph_proxies["unreachable_walkers"] == 0
    assert graph_proxies["geodesic_method"] == "heat"
    estimation = report["estimation"]
    assert estimation["tier2_gradient_norm_median"] > 0 and -1 <= estimation["agreement_eigenvalue_correlation"] <= 1
    assert estimation["agreement_method_preference"] in ("excellent", "good", "poor")
    assert (tmp_path / "estimation.png").stat().st_size > 20_000
    exact = report["metric_curvature"]  # the exact curvature beside the Regge proxy, same walkers and weights
    assert exact["method"] == "hessian" and exact["flagged_nan_walkers"] == 0
    assert np.isfinite(exact["exact_same_walkers"]) and np.isfinite(exact["regge_same_walkers"])
    # the double well's clip floor is active at part of the walkers: a kink the two means see differently
    assert exact["regge_vs_exact"] == "not comparable" and "clip floor is active" in exact["regge_vs_exact_why"]


def test_analyze_accepts_a_landscape_file_like_simulate(tmp_path, capsys):
    """A .py landscape is the same landscape as the built-in it copies: identical metric and
    curvature sections on the same walkers (600, as the test above: one compilation serves the three runs)."""
    (tmp_path / "dw.py").write_text("from jaxgeom.apps._landscapes import double_well as V\nBOX = (-2.5, 2.5)\n")
    points = tmp_path / "x.npy"
    np.save(points, sample_boltzmann("double_well", 600, 2, seed=2)[0])
    reports = []
    for spec in ("double_well", str(tmp_path / "dw.py")):
        out = tmp_path / spec.replace("/", "_")
        assert main(["analyze", "--points", str(points), "--landscape", spec, "--out", str(out)]) == 0
        reports.append(json.loads((out / "summary.json").read_text()))
    capsys.readouterr()
    for section in ("curvature", "cells", "graph_proxies"):
        for key, value in reports[0][section].items():
            if isinstance(value, float) and "seconds" not in key:
                assert reports[1][section][key] == pytest.approx(value, rel=1e-12, nan_ok=True), (section, key)


def test_analyze_flat_metric_has_zero_curvature(tmp_path):
    assert main(["analyze", "--n", "200", "--metric", "none", "--out", str(tmp_path)]) == 0  # as the beta = 0 test
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["curvature"]["tier2_ricci_max"] == report["curvature"]["tier2_ricci_min"] == 0.0
    assert "kind" in report["metric"] and "tier2_condition_mean" not in report["metric"]


def test_analyze_points_without_a_landscape_reports_only_geometry(tmp_path, capsys):
    np.save(tmp_path / "pts.npy", np.random.default_rng(0).random((200, 2)))  # as the flat-metric and beta = 0 tests
    assert main(["analyze", "--points", str(tmp_path / "pts.npy"), "--box", "0", "1", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["swarm"]["landscape"].startswith("none") and report["metric"]["kind"] == "none"
    assert "skipped" in report["estimation"] and "best_fitness" not in report["graph_proxies"]
    assert "total_finite" not in report["volumes"]
    np.testing.assert_allclose(report["volumes"]["total_in_box"], 1.0, rtol=1e-12)
    assert 0 < report["volumes"]["tier2_total"] < 1
    assert (
        main(["analyze", "--points", str(tmp_path / "pts.npy"), "--landscape", "quadratic", "--out", str(tmp_path)])
        == 0
    )
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["swarm"]["landscape"] == "quadratic" and report["metric"]["kind"] == "hessian"
    assert "best_fitness" in report["graph_proxies"] and "walkers_with_hessian" in report["estimation"]
    assert_every_analyze_row_defined(capsys.readouterr().out)


@pytest.mark.slow
def test_both_commands_take_the_same_precision_flag(tmp_path, capsys):
    try:
        assert main(["analyze", "--n", "100", "--metric", "none", "--precision", "float32"]) == 0
        assert re.search(r"precision\s+float32", capsys.readouterr().out)
        assert (
            main(
                [
                    "simulate",
                    "--n",
                    "50",
                    "--steps",
                    "1",
                    "--gap-every",
                    "0",
                    "--no-progress",
                    "--precision",
                    "float32",
                    "--out",
                    str(tmp_path),
                ]
            )
            == 0
        )
        assert json.loads((tmp_path / "history.json").read_text())["dtype"] == "float32"
    finally:
        jax.config.update("jax_enable_x64", True)  # the CLI sets it for the process


@pytest.mark.slow
def test_analyze_emergent_metric_in_3d(tmp_path):
    assert main(["analyze", "--n", "800", "--dim", "3", "--metric", "emergent", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["metric"]["tier2_condition_mean"] >= 1.0
    assert np.isfinite(report["curvature"]["tier2_ricci_median"])


@pytest.mark.slow  # test_reliability runs analyze --periodic on its own sample
def test_analyze_periodic_points_file(tmp_path):
    pts = np.random.default_rng(0).random((300, 2))  # 3D periodic graphs: test_reliability lattices
    np.save(tmp_path / "pts.npy", pts)
    assert (
        main(
            ["analyze", "--points", str(tmp_path / "pts.npy"), "--periodic", "--box", "0", "1", "--out", str(tmp_path)]
        )
        == 0
    )
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["graph"]["tier2"] == 300
    assert abs(report["volumes"]["tier2_total"] - 1.0) < 1e-9 and abs(report["volumes"]["total_in_box"] - 1.0) < 1e-9


@pytest.mark.slow
def test_analyze_knn_in_high_dimension(tmp_path, capsys):
    assert main(["analyze", "--graph", "knn", "--k", "8", "--dim", "6", "--n", "400", "--out", str(tmp_path)]) == 0
    assert_every_analyze_row_defined(capsys.readouterr().out)
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["graph"]["degree_min"] == report["graph"]["degree_max"] == 8
    assert "skipped" in report["volumes"] and "skipped" in report["curvature"]
    exact = report["metric_curvature"]  # the exact curvature of the Hessian metric needs no graph
    assert exact["method"] == "hessian" and np.isfinite(exact["tier2_riemannian_mean_exact_ricci"])
    assert exact["weights"].startswith("r_k^d") and exact["tier2_walkers_used"] > 0


def test_analyze_reports_the_stochastic_exact_curvature_from_d_17():
    """The report section alone (the whole command at d = 20 spends minutes in the estimation
    section's 231-coefficient quadratic fits)."""
    import argparse

    from jaxgeom.apps._landscapes import double_well
    from jaxgeom.cli._analyze import Analysis, section_metric_curvature

    x = np.random.default_rng(0).normal(scale=0.6, size=(300, 20))
    args = argparse.Namespace(metric="hessian", eps_sigma=0.1, seed=0, landscape="double_well")
    analysis = Analysis(args, x, None, "test", fitness=double_well, tess=jaxgeom.knn_graph(x, 8))
    exact = section_metric_curvature(analysis)
    assert exact["method"] == "hessian-stochastic" and exact["probes"] == 64
    # double well: the floor is active near x_0 = 0, and above d = 10 those walkers are flagged
    assert exact["flagged_nan_walkers"] == exact["floor_active_walkers"] > 0
    assert np.isfinite(exact["tier2_riemannian_mean_exact_ricci"]) and exact["standard_error_of_the_mean"] > 0


def test_analyze_rejects_negative_eps_sigma(capsys):
    import pytest

    with pytest.raises(SystemExit):
        main(["analyze", "--eps-sigma", "-1"])
    assert "--eps-sigma must be a finite number >= 0" in capsys.readouterr().err


def test_analyze_reports_bad_input_clearly(tmp_path, capsys):
    pts = np.random.default_rng(0).random((50, 2))
    pts[7, 0] = np.nan
    np.save(tmp_path / "bad.npy", pts)
    assert main(["analyze", "--points", str(tmp_path / "bad.npy")]) == 2
    assert "NaN or inf" in capsys.readouterr().err


@pytest.fixture(scope="module")
def simulate_run(tmp_path_factory):
    """One `jaxgeom simulate` run read by the tests below: its printed table, its history.json,
    the figures it saved and its output folder."""
    import contextlib
    import io

    import matplotlib.figure

    out_dir = tmp_path_factory.mktemp("simulate")
    saved, savefig, printed = [], matplotlib.figure.Figure.savefig, io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(printed):
        patch.setattr(
            matplotlib.figure.Figure, "savefig", lambda fig, *a, **k: (saved.append(fig), savefig(fig, *a, **k))[1]
        )
        status = main(
            [
                "simulate",
                "--n",
                "120",
                "--steps",
                "10",
                "--gap-every",
                "3",
                "--no-progress",
                "--scutoids",
                "--out",
                str(out_dir),
            ]
        )
    history = json.loads((out_dir / "history.json").read_text()) if status == 0 else None
    return {"status": status, "out": printed.getvalue(), "history": history, "saved": saved, "dir": out_dir}


def test_simulate_writes_time_series_and_figures(simulate_run):
    assert simulate_run["status"] == 0
    out, history, saved, out_dir = (simulate_run[k] for k in ("out", "history", "saved", "dir"))
    scutoid_series = ("prism_fraction", "simple_scutoid_fraction", "complex_scutoid_fraction", "mean_neighbor_change")
    assert all(name in out for name in scutoid_series), "--scutoids: the table shows the scutoid observables"
    assert "best_fitness" in out and "total clones" in out
    assert_every_simulate_row_defined(out)
    assert re.search(r"kernel_graph_components(\s+\d+){4}\n", out), "a graph row says which graph"
    assert not re.search(r"^spectral gap at steps", out, flags=re.M), "a row without values"
    assert len(history["series"]["mean_fitness"]) == 11 and len(history["series"]["time"]) == 11
    assert history["dtype"] == "float64"  # the default of both commands
    assert history["series"]["best_fitness"][-1] <= history["series"]["best_fitness"][0]
    assert history["spectral_gap"]["step"] == [0, 3, 6, 9]
    assert (out_dir / "swarm.png").stat().st_size > 10_000 and (out_dir / "observables.png").stat().st_size > 10_000
    fractions = np.array([history["series"][name] for name in scutoid_series[:3]], dtype=float)
    assert np.isnan(fractions[:, 0]).all(), "no scutoid before the first step"
    np.testing.assert_allclose(fractions[:, 1:].sum(axis=0), 1.0, rtol=1e-12)
    titles = {ax.get_title() for fig in saved for ax in fig.axes}
    assert any(title.startswith("prisms") for title in titles) and any(t.startswith("complex") for t in titles)


def test_cli_history_equals_one_call_and_every_gap_is_on_schedule(simulate_run):
    """10 steps run as segments of 4, 4, 2 (the figure's snapshots), gaps every 3 steps: the
    command line's history against one `jaxgeom.simulate` call."""
    assert simulate_run["status"] == 0
    printed, history = simulate_run["out"], simulate_run["history"]
    assert history["spectral_gap"]["step"] == [0, 3, 6, 9] and "measured at steps [0, 3, 6, 9]" in printed
    fitness, _, half = LANDSCAPES["rastrigin"]
    x0 = np.random.default_rng(0).uniform(-half, half, (120, 2))
    params = jaxgeom.SwarmParams(dt=0.01, gamma=2.0, temperature=1.0, nu=0.1, eps_sigma=0.1, clone_rate=0.1)
    state = jaxgeom.init_swarm(fitness, x0, key=0)
    _, whole = jaxgeom.simulate(fitness, state, params, n_steps=10, spectral_gap_every=3)
    for name in ("mean_expansion", "velocity_variance", "mean_ricci", "n_clones"):
        cli = np.array([np.nan if v is None else v for v in history["series"][name]])
        np.testing.assert_allclose(cli, np.asarray(whole[name]), rtol=1e-10, atol=1e-12, equal_nan=True)
    np.testing.assert_allclose(history["spectral_gap"]["value"], np.asarray(whole["spectral_gap"]), rtol=1e-8)


def test_simulate_user_landscape_file_in_3d_knn(tmp_path, capsys):
    (tmp_path / "bowl.py").write_text(
        "import jax.numpy as jnp\nBOX = (-1.0, 1.0)\n\ndef V(x):\n    return jnp.sum(x ** 2)\n"
    )
    assert (
        main(
            [
                "simulate",
                "--landscape",
                str(tmp_path / "bowl.py"),
                "--n",
                "200",
                "--steps",
                "6",
                "--dim",
                "4",
                "--graph",
                "knn",
                "--k",
                "8",
                "--gap-every",
                "0",
                "--no-cloning",
                "--no-progress",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    assert "mean_fitness" in capsys.readouterr().out
    for figure in ("swarm.png", "observables.png"):  # drawn for a k-NN swarm in 4D too
        assert (tmp_path / "out" / figure).stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--dim", "4"], "--dim 4 needs --graph knn"),
        (["--landscape", "nowhere"], "--landscape must be one of"),
        (["--dt", "0"], "`dt` must be a finite number > 0"),
    ],
)
def test_simulate_reports_bad_input(argv, message, capsys):
    assert main(["simulate", "--n", "50", "--steps", "2", "--no-progress"] + argv) == 2
    assert message in capsys.readouterr().err


def test_tune_prints_iterations_and_writes_json_and_figure(tmp_path, capsys):
    assert (
        main(
            [
                "tune",
                "--n",
                "30",
                "--steps",
                "3",
                "--max-steps",
                "2",
                "--seeds",
                "2",
                "--tune",
                "nu",
                "eps_sigma",
                "--grid",
                "2",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )  # as the Ctrl-C tests below
    out = capsys.readouterr().out
    assert re.search(r"iter\s+loss\s+\|grad\|\s+nu\s+eps_sigma", out) and "true values:" in out
    assert re.search(r"found:\s+nu=\S+ \+- \S+\s+eps_sigma=\S+ \+- \S+", out)
    report = json.loads((tmp_path / "tune.json").read_text())
    first = report["iterations"][0]
    assert first["iteration"] == 0 and first["values"] == {"nu": 0.05, "eps_sigma": pytest.approx(0.2)}
    losses = [it["loss"] for it in report["iterations"]]
    assert losses == sorted(losses, reverse=True) and report["truth"] == {"nu": 0.3, "eps_sigma": 0.05}
    grid = np.asarray(report["grid"]["loss"])
    assert grid.shape == (2, 2) and np.isfinite(grid).all() and report["grid"]["names"] == ["nu", "eps_sigma"]
    assert (tmp_path / "tune.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--seeds", "0"], "--seeds must be a finite number >= 1"),
        (["--tune", "mu"], "invalid choice: 'mu'"),
        (["--objective", "fit"], "invalid choice: 'fit'"),
    ],
)
def test_tune_refuses_bad_arguments(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["tune", "--n", "50", "--steps", "2"] + argv)
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_tune_reports_a_bad_start_clearly(capsys):
    assert main(["tune", "--n", "50", "--steps", "2", "--tune", "nu", "--nu", "0", "--no-progress"]) == 2
    assert "--nu must be > 0 to be tuned" in capsys.readouterr().err


def test_analyze_metric_section_without_tier2_walkers():
    """300 walkers in 4D have no tier-2 walker: the metric section reports NaN (once: numpy's
    'zero-size array to reduction operation minimum')."""
    import argparse

    from jaxgeom.apps._landscapes import double_well, sample_boltzmann
    from jaxgeom.cli._analyze import Analysis, section_metric

    points, box = sample_boltzmann("double_well", 300, 4, seed=0)
    args = argparse.Namespace(metric="hessian", landscape="double_well", eps_sigma=0.1)
    a = Analysis(args=args, points=points, box=box, source="test", fitness=double_well)
    a.tess = jaxgeom.delaunay(points)
    assert not np.any(np.asarray(a.tess.interior))
    out = section_metric(a)
    assert np.isnan(out["tier2_min_eigenvalue"]) and out["tier2_condition_count"] == 0


@pytest.mark.slow
def test_analyze_in_4d_with_few_walkers(tmp_path):
    assert main(["analyze", "--n", "300", "--dim", "4", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "summary.json").read_text())
    assert report["graph"]["tier2"] == 0 and report["swarm"]["dim"] == 4


@pytest.mark.parametrize("landscape", ["quadratic", "rastrigin"])
def test_analyze_at_beta_zero_samples_the_box_uniformly(tmp_path, landscape):
    """(Once: a hang for the double well, a misleading error for these two.)"""
    assert (
        main(
            [
                "analyze",
                "--beta",
                "0",
                "--landscape",
                landscape,
                "--n",
                "200",
                "--metric",
                "none",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "summary.json").read_text())
    assert "exp(-0.0 V)" in report["swarm"]["source"]


def _interrupt_when(argv, pattern, tmp_path, timeout=240, cache=True):
    """Run the CLI in its own process, send SIGINT once its stderr matches `pattern` (a regex),
    and return (exit status, stderr). `cache=False`: without the compilation cache (its
    programs are compiled, not read back)."""
    import os
    import signal
    import subprocess
    import sys
    import threading
    import time

    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    if not cache:
        env["JAXGEOM_COMPILE_CACHE"] = "0"
    proc = subprocess.Popen(
        [sys.executable, "-m", "jaxgeom.cli", *argv, "--out", str(tmp_path), "--progress"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        cwd=tmp_path,
    )
    err = []
    reader = threading.Thread(
        target=lambda: err.extend(iter(lambda: proc.stderr.read(1).decode(errors="replace"), "")), daemon=True
    )
    reader.start()
    deadline = time.monotonic() + timeout
    while not re.search(pattern, "".join(err)):
        assert proc.poll() is None, "".join(err)
        assert time.monotonic() < deadline, "".join(err)
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    proc.stdout.read()
    status = proc.wait(timeout=120)
    reader.join(timeout=10)
    return status, "".join(err)


def test_ctrl_c_during_simulate_writes_the_steps_that_ran(tmp_path):
    """Once: a KeyboardInterrupt traceback and an empty --out."""
    status, err = _interrupt_when(
        ["simulate", "--n", "100", "--steps", "100000", "--gap-every", "0", "--precision", "float64"],
        r"\b([1-9]\d*)/100000",
        tmp_path,
    )
    assert status == 130 and "Traceback" not in err, err
    step = int(re.search(r"interrupted at step (\d+) of 100000; the steps that ran are written", err).group(1))
    history = json.loads((tmp_path / "history.json").read_text())
    assert history["interrupted_at_step"] == step > 0
    assert len(history["series"]["mean_fitness"]) == step + 1 and history["series"]["time"][-1] > 0
    assert (tmp_path / "swarm.png").stat().st_size > 0 and (tmp_path / "observables.png").stat().st_size > 0


@pytest.mark.slow  # the default tier: a real SIGINT while tune compiles, and Ctrl-C read between iterations below
def test_ctrl_c_during_tune_writes_the_iterations_that_ran(tmp_path):
    status, err = _interrupt_when(
        ["tune", "--n", "30", "--steps", "5", "--max-steps", "100000", "--seeds", "1", "--tune", "nu"],
        r"\b([1-9]\d*)/100001",
        tmp_path,
        timeout=480,
    )
    assert status == 130 and "Traceback" not in err, err
    done = int(
        re.search(r"interrupted at iteration (\d+) of 100000; the iterations that ran are written", err).group(1)
    )
    report = json.loads((tmp_path / "tune.json").read_text())
    assert len(report["iterations"]) == done + 1 and report["message"] == "interrupted" and not report["converged"]
    assert (tmp_path / "tune.png").stat().st_size > 0


# "while the targets compile": once the empty progress bar is drawn (at a fixed 4 s, a loaded
# machine was still importing jax: a traceback from the import, not the command's message).
@pytest.mark.parametrize(
    "moment, pattern",
    [
        ("while the targets compile", r"tune \(bfgs\):\s+0%"),
        pytest.param("in the second iteration", r"\b(2)/3\b", marks=pytest.mark.slow),
    ],
)
def test_ctrl_c_in_tune_ends_with_the_message_and_130(moment, pattern, tmp_path):
    """A real SIGINT at two moments: the message, the iterations that ran, exit status 130."""
    status, err = _interrupt_when(
        [
            "tune",
            "--n",
            "30",
            "--steps",
            "4",
            "--max-steps",
            "2",
            "--seeds",
            "2",
            "--tune",
            "nu",
            "eps_sigma",
            "--grid",
            "3",
        ],
        pattern,
        tmp_path,
        cache=moment != "while the targets compile",
    )
    assert status == 130 and "Traceback" not in err, (moment, err)
    line = re.search(
        r"jaxgeom tune: interrupted (?:at iteration (\d+) of 2|before it began)(; the iterations that "
        r"ran are written|; nothing written)",
        err,
    )
    assert line, (moment, err)
    if line.group(2).startswith("; the"):
        report = json.loads((tmp_path / "tune.json").read_text())
        assert len(report["iterations"]) == int(line.group(1)) + 1
    if moment == "in the second iteration":
        assert line.group(2).startswith("; the"), (moment, err)


def test_a_ctrl_c_before_the_command_begins_is_one_line_and_130(monkeypatch, capsys):
    """Once: a Ctrl-C while the command line set itself up (a slow machine, 4 s after the start)
    ended in a traceback."""
    import jaxgeom.cli as cli

    def interrupted(choice):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "use_compile_cache", interrupted)
    assert main(["tune", "--n", "30", "--steps", "3", "--tune", "nu"]) == 130
    assert capsys.readouterr().err == "jaxgeom tune: interrupted before it began; nothing written\n"


@pytest.mark.parametrize("moment", ["the last solver step", "the standard errors", "the loss grid"])
def test_a_ctrl_c_no_iteration_reads_still_ends_tune_with_130(moment, monkeypatch, tmp_path, capsys):
    """Once: a Ctrl-C in the last iteration of a solver that then stopped (or later) was never read,
    and the command exited 0 with its full output. The deferred Ctrl-C is set at each moment."""
    import jaxgeom.cli._tune as cli_tune
    import jaxgeom.swarm._tune as lib_tune
    from jaxgeom.base import _progress

    def ctrl_c_after(fn, on_call=1):
        calls = []

        def wrapped(*args, **kwargs):
            out = fn(*args, **kwargs)
            calls.append(1)
            if len(calls) == on_call:
                _progress._INTERRUPT["requested"] = True
            return out

        return wrapped

    if moment == "the last solver step":
        monkeypatch.setattr(lib_tune, "_step", ctrl_c_after(lib_tune._step, on_call=2))
    elif moment == "the standard errors":
        monkeypatch.setattr(lib_tune, "parameter_errors", ctrl_c_after(lib_tune.parameter_errors))
    else:
        monkeypatch.setattr(cli_tune, "loss_grid", ctrl_c_after(cli_tune.loss_grid))
    status = main(
        [
            "tune",
            "--n",
            "30",
            "--steps",
            "3",
            "--max-steps",
            "2",
            "--seeds",
            "2",
            "--tune",
            "nu",
            "eps_sigma",
            "--grid",
            "2",
            "--out",
            str(tmp_path),
            "--no-progress",
        ]
    )
    err = capsys.readouterr().err
    assert status == 130, err
    line = re.search(r"jaxgeom tune: interrupted at iteration (\d+) of 2; the iterations that ran are written", err)
    assert line, err
    report = json.loads((tmp_path / "tune.json").read_text())
    assert len(report["iterations"]) == int(line.group(1)) + 1 >= 2
    assert not _progress._INTERRUPT["requested"]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--box", "1", "0"], "--box LOWER UPPER must be finite with LOWER < UPPER; got 1.0 0.0"),
        (["--box", "nan", "1"], "--box LOWER UPPER must be finite"),
        (["--box", "0", "1"], "--box applies to walkers given with --points"),
        (["--periodic", "--box", "0", "1"], "--box applies to walkers given with --points"),
    ],
)
def test_analyze_box_is_validated_and_not_ignored(argv, message, capsys):
    """Once: a sampled swarm ignored --box without a word."""
    assert main(["analyze", "--n", "100", *argv]) == 2
    assert message in capsys.readouterr().err


def test_analyze_reports_ollivier_ricci_on_knn_graphs():
    from jaxgeom.cli._analyze import Analysis, section_ollivier_ricci

    x = np.random.default_rng(0).random((120, 5))
    args = argparse.Namespace(metric="none", eps_sigma=0.1, seed=0, landscape=None)
    tess = jaxgeom.knn_graph(x, 6)
    out = section_ollivier_ricci(Analysis(args, x, None, "test", tess=tess))
    reference = jaxgeom.ollivier_ricci(tess)
    assert out["edges"] == int(reference.edge_mask.sum()) // 2 > 300
    assert out["tier2_walker_curvature_mean"] == pytest.approx(np.nanmean(np.asarray(reference.walker_curvature)))
    assert out["isolated_walkers"] == 0 and not out["overflow"]
    delaunay = section_ollivier_ricci(Analysis(args, x[:, :2], None, "test", tess=jaxgeom.delaunay(x[:, :2])))
    assert "skipped" in delaunay


@pytest.fixture
def jax_cache_settings():
    """Restore JAX's cache settings that `use_compile_cache` changes for the process."""
    names = (
        "jax_compilation_cache_dir",
        "jax_persistent_cache_min_compile_time_secs",
        "jax_persistent_cache_min_entry_size_bytes",
    )
    saved = {name: getattr(jax.config, name) for name in names}
    yield
    for name, value in saved.items():
        jax.config.update(name, value)


def test_the_command_line_keeps_its_compiled_programs_unless_told_not_to(tmp_path, monkeypatch, jax_cache_settings):
    from jaxgeom.cli import machine_tag, use_compile_cache

    monkeypatch.setenv("JAXGEOM_COMPILE_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("JAXGEOM_COMPILE_CACHE", raising=False)
    path = use_compile_cache(None)
    assert path == tmp_path / machine_tag() and path.is_dir()
    assert jax.config.jax_compilation_cache_dir == str(path)
    assert use_compile_cache(False) is None
    for off in ("0", "false", "off"):
        monkeypatch.setenv("JAXGEOM_COMPILE_CACHE", off)
        assert use_compile_cache(None) is None
    assert use_compile_cache(True) == path, "the flag wins over the environment"


def test_the_cache_has_one_folder_per_cpu_type(monkeypatch):
    import platform

    from jaxgeom.cli import machine_tag

    here = machine_tag()
    monkeypatch.setattr(platform, "machine", lambda: "another-machine")
    assert machine_tag() != here and len(here) == 12


def test_the_cache_is_pruned_to_half_its_cap_oldest_first(tmp_path):
    import os

    from jaxgeom.cli import prune_cache

    for age in range(10):
        entry = tmp_path / f"entry{age}"
        entry.write_bytes(b"x" * 100)
        os.utime(entry, (1000 + age, 1000 + age))
    prune_cache(tmp_path, cap=2000)
    assert len(list(tmp_path.iterdir())) == 10, "under the cap: nothing removed"
    prune_cache(tmp_path, cap=600)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"entry{age}" for age in range(7, 10)]


def test_analyze_of_two_separated_blobs_names_the_components_not_a_rounding_gap(tmp_path, capsys):
    """Issue 63: two Gaussian blobs 100 widths apart printed `spectral_gap 2.5627e-17`. Their
    kernel graph falls apart into the two blobs: the report names the components and gives the
    larger blob's gap (against a dense eigensolve of its normalized Laplacian), and a kernel wide
    enough (`--length-scale`) joins them again."""
    rng = np.random.default_rng(5)
    blobs = np.concatenate([rng.normal(0.0, 1.0, (150, 2)), rng.normal(100.0, 1.0, (120, 2))])
    np.save(tmp_path / "blobs.npy", blobs)
    assert (
        main(
            ["analyze", "--points", str(tmp_path / "blobs.npy"), "--length-scale", "1.0", "--out", str(tmp_path / "a")]
        )
        == 0
    )
    printed = capsys.readouterr().out
    proxies = json.loads((tmp_path / "a" / "summary.json").read_text())["graph_proxies"]
    assert proxies["kernel_graph_components"] == 2 and proxies["walkers_outside_largest_component"] == 120
    assert re.search(r"kernel_graph_components\s+2\n", printed) and not re.search(r"e-1[5-9]", printed)
    tess = jaxgeom.delaunay(blobs)
    nbrs = np.asarray(tess.neighbors)[:150]
    w = np.asarray(jaxgeom.edge_weights(tess, length_scale=1.0))[:150]
    dense = np.zeros((150, 150))
    rows, slots = np.nonzero(nbrs < 150)
    dense[rows, nbrs[rows, slots]] = w[rows, slots]
    scale = 1.0 / np.sqrt(dense.sum(axis=1))
    gap = np.linalg.eigvalsh(np.eye(150) - scale[:, None] * dense * scale[None, :])[1]
    assert proxies["spectral_gap_largest_component"] == pytest.approx(gap, rel=1e-8) and gap > 1e-3
    assert (
        main(
            ["analyze", "--points", str(tmp_path / "blobs.npy"), "--length-scale", "200", "--out", str(tmp_path / "b")]
        )
        == 0
    )
    wide = json.loads((tmp_path / "b" / "summary.json").read_text())["graph_proxies"]
    assert wide["kernel_graph_components"] == 1 and wide["walkers_outside_largest_component"] == 0


def test_simulate_explain_defines_each_row_it_prints(simulate_run, capsys):
    from jaxgeom.cli._simulate import summary_table

    rows = [line.split()[0] for line in simulate_run["out"].splitlines()[1:] if len(line.split()) == 5]
    result = {
        "series": {
            name: np.asarray([np.nan if v is None else v for v in values])
            for name, values in simulate_run["history"]["series"].items()
        },
        "spectral_gap": np.asarray(simulate_run["history"]["spectral_gap"]["value"], float),
        "spectral_components": np.asarray(simulate_run["history"]["spectral_gap"]["components"]),
        "spectral_gap_rounding": np.asarray(simulate_run["history"]["spectral_gap"]["at_rounding_level"]),
        "spectral_gap_step": np.asarray(simulate_run["history"]["spectral_gap"]["step"]),
        "n_reallocations": 0,
        "seconds_total": 1.0,
        "seconds_init": 0.0,
        "seconds_steps": 0.0,
        "seconds_rebuild": 0.0,
        "seconds_snapshots": 0.0,
        "config": {"graph": "delaunay"},
    }
    explained = summary_table(result, explain=True)
    legend = explained.split("Rows:")[1]
    for name in rows:
        assert re.search(rf"^  {name}\s+\S", legend, flags=re.M), name
    assert "[x^2/t^2]" in legend and "Units:" in legend


def test_regge_and_exact_curvature_agree_where_the_criterion_says_comparable(tmp_path, capsys):
    """A landscape whose Hessian is positive definite on its box (the floor never acts) and
    smooth on the cells' scale: the criterion says comparable and the two means agree to 5%
    (measured: -0.0615 against -0.0598 at 2000 walkers)."""
    (tmp_path / "cubic.py").write_text(
        "import jax.numpy as jnp\nBOX = (-1.0, 1.0)\n\n\ndef V(p):\n"
        "    return jnp.sum(p**2) + 0.3 * p[0] ** 3 + 0.2 * p[0] * p[1] ** 2"
        " + jnp.exp(0.5 * p[1])\n"
    )
    assert main(["analyze", "--n", "2000", "--landscape", str(tmp_path / "cubic.py"), "--out", str(tmp_path)]) == 0
    capsys.readouterr()
    exact = json.loads((tmp_path / "summary.json").read_text())["metric_curvature"]
    assert exact["floor_active_walkers"] == 0 and exact["regge_vs_exact"] == "comparable", exact
    assert exact["regge_same_walkers"] == pytest.approx(exact["exact_same_walkers"], rel=0.05)


def test_an_exact_scalar_the_sample_does_not_resolve_is_not_comparable():
    """The double well under the smooth softabs floor (no kink): at 5000 walkers the exact scalar
    jumps between neighbouring cells by several times its mean, and the two means differ by 3x
    (0.17 against 0.51; at 20000 walkers, resolved, 0.052 against 0.059)."""
    from jaxgeom.cli._analyze import regge_comparison
    from jaxgeom.swarm._observables import riemannian_log_weights, weighted_mean_from_logs

    points, _ = sample_boltzmann("double_well", 5000, 2, beta=2.0, seed=0)
    tess = jaxgeom.delaunay(points)
    metric = jaxgeom.hessian_metric(LANDSCAPES["double_well"][0], 0.1, floor="softabs")
    regge = np.asarray(jaxgeom.ricci_scalar(tess, metric=metric))
    exact, info = jaxgeom.metric_curvature(metric, tess.points, with_info=True)
    exact = np.asarray(exact)
    log_w, ok = riemannian_log_weights(tess, jaxgeom.metric_at_walkers(tess, metric))
    used = np.asarray(ok & tess.interior) & np.isfinite(exact) & np.isfinite(regge)
    means = [float(weighted_mean_from_logs(v, log_w, used)) for v in (regge, exact)]
    comparable, why = regge_comparison(
        tess, exact, np.asarray(log_w), used, np.asarray(info.floor_active), "softabs", *means
    )
    assert not comparable and why.startswith("unresolved by the sample"), why
    assert abs(means[0] - means[1]) > 0.5 * abs(means[1])


def test_every_observable_simulate_can_print_has_a_definition():
    assert not [name for name in jaxgeom.ALL_OBSERVABLES if name not in SIMULATE_ROWS]
