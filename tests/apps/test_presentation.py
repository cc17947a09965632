"""What a new user sees: --help, the progress bar, the timing line, the figures' content."""

import argparse
import re

import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin, rosenbrock, sample_boltzmann
from jaxgeom.apps._plots import _contour_levels, _frame, _landscape_grid, observable_panels
from jaxgeom.cli import _parser, main


def subcommands():
    sub = next(a for a in _parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


@pytest.mark.parametrize("command", ["simulate", "analyze", "tune"])
def test_help_explains_every_option_and_shows_its_default(command, capsys):
    parser = subcommands()[command]
    for action in parser._actions:
        assert action.help and action.help.strip(), f"{command} {action.option_strings} has no help text"
    with pytest.raises(SystemExit):
        main([command, "--help"])
    text = " ".join(capsys.readouterr().out.split())
    shown = [a for a in parser._actions if a.option_strings and a.default is not argparse.SUPPRESS]
    assert text.count("(default:") == len(shown)
    assert "--precision {float64,float32} floating-point type of the computation (default: float64)" in text
    assert "--seed SEED seed of" in text and "(default: 0)" in text


def test_simulate_help_explains_its_defaults_against_swarmparams(capsys):
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    defaults = jaxgeom.SwarmParams()
    assert f"SwarmParams default: {float(defaults.temperature)}" in text
    assert f"SwarmParams default: {float(defaults.gamma)}" in text
    assert "(default: 1.0)" in text and "(default: 2.0)" in text


def test_progress_bar_one_per_run_silent_unless_asked(capsys):
    x0 = np.random.default_rng(0).uniform(-1.0, 1.0, (60, 2))
    state = jaxgeom.init_swarm(rastrigin, x0, key=0)
    params = jaxgeom.SwarmParams(cloning=False)
    jaxgeom.simulate(rastrigin, state, params, n_steps=3, progress="auto")  # stderr is not a terminal here
    assert capsys.readouterr().err == ""
    jaxgeom.simulate(rastrigin, state, params, n_steps=3, progress=True)
    assert re.search(r"simulate: 100%.*3/3", capsys.readouterr().err)
    with pytest.raises(TypeError, match="`progress` must be False, True, 'auto' or a tqdm bar"):
        jaxgeom.simulate(rastrigin, state, params, n_steps=3, progress="yes")


def test_cli_draws_one_bar_over_its_segments(capsys):
    assert main(["simulate", "--n", "60", "--steps", "9", "--gap-every", "0", "--progress", "--no-cloning"]) == 0
    captured = capsys.readouterr()
    assert "9/9" in captured.err and "3/3" not in captured.err  # segments of 3 steps advance one bar
    assert captured.err.count(" 0/9 ") == 1  # one bar started (its close may redraw 100% once more)
    assert "compile" in captured.out  # the timing line says where compilation went


def test_tune_progress_bar_shows_the_loss(capsys):
    x0 = np.random.default_rng(1).uniform(-1.0, 1.0, (40, 2))
    state = jaxgeom.init_swarm(rastrigin, x0, key=0)
    loss = jaxgeom.simulation_loss(
        rastrigin, state, "mean_fitness", params=jaxgeom.SwarmParams(cloning=False), n_steps=2, tuned=("nu",)
    )
    jaxgeom.tune(loss, max_steps=1, progress=True)
    err = capsys.readouterr().err
    assert "tune (bfgs)" in err and "loss" in err and "nu=" in err


def test_sample_boltzmann_of_a_callable_has_the_gaussian_variance():
    """exp(-beta |x|^2) has variance 1/(2 beta) per coordinate (the box +-3 cuts < 1e-7 of it)."""
    x, box = sample_boltzmann(lambda p: jnp.sum(p**2), 20000, 2, beta=2.0, seed=0, box=(-3.0, 3.0))
    assert x.shape == (20000, 2) and np.all(np.abs(x) <= 3.0)
    np.testing.assert_allclose(x.var(axis=0), 0.25, rtol=0.04)
    np.testing.assert_allclose(box[1], [3.0, 3.0])
    with pytest.raises(ValueError, match="needs `box="):
        sample_boltzmann(lambda p: jnp.sum(p**2), 10, 2)


@pytest.mark.parametrize("name", ["double_well", "quadratic", "rastrigin", "rosenbrock"])
def test_sample_boltzmann_at_zero_and_tiny_beta_is_uniform_on_the_box(name):
    """exp(-0 V) = 1. (Once: beta = 0 hung the double well's sampler, NaN for the quadratic;
    beta = 1e-300 put every quadratic walker at 0.) Uniform on [-h, h]: variance h^2 / 3."""
    for beta in (0.0, 1e-300):
        x, (lower, upper) = sample_boltzmann(name, 20000, 2, beta=beta, seed=0)
        half = upper[0]
        assert np.all(np.isfinite(x)) and np.all(np.abs(x) <= half)
        np.testing.assert_allclose(x.var(axis=0), half**2 / 3, rtol=0.04)


def test_double_well_sample_in_high_dimension_at_low_beta():
    """The x_0 marginal carries Z(x_0)^(d - 1), which overflowed from d ~ 500 (then the
    sampler looped for ever); it is normalised in log space."""
    x, _ = sample_boltzmann("double_well", 200, 1000, beta=1e-3, seed=0)
    assert x.shape == (200, 1000) and np.all(np.isfinite(x))


def test_sample_boltzmann_refuses_a_beta_it_cannot_sample():
    with pytest.raises(ValueError, match="`beta` must be"):
        sample_boltzmann("quadratic", 10, 2, beta=-1.0)
    with pytest.raises(ValueError, match="`beta` must be"):
        sample_boltzmann("double_well", 10, 2, beta=np.nan)
    with pytest.raises(ValueError, match=r"exp\(-1e\+300 V\) by rejection accepted 0 of 10 walkers in 200 rounds"):
        sample_boltzmann("double_well", 10, 2, beta=1e300)  # a capped loop, not a hang


def test_observable_panels_skip_constant_and_undefined_series():
    t = np.arange(5) * 0.1
    series = {
        "time": t,
        "mean_fitness": np.array([3.0, 2.0, 1.5, 1.2, 1.0]),
        "nu": np.full(5, 0.1),
        "mean_expansion": np.array([np.nan, 1.0, 2.0, 1.0, 0.5]),
        "mean_ricci": np.full(5, np.nan),
        "ricci_resolution": np.full(5, 1e-9),
    }
    drawn, constant, undefined = observable_panels(series, gaps=[0.2])
    assert drawn == ["mean_fitness", "mean_expansion", "spectral_gap"]
    assert constant == ["nu"] and undefined == ["mean_ricci"]


def test_rosenbrock_contours_are_log_spaced_rastrigin_linear():
    _, _, valley = _landscape_grid(rosenbrock, np.array([-2.0, -2.0]), np.array([2.0, 2.0]), 2)
    levels = _contour_levels(valley) - valley.min()
    assert np.allclose(np.diff(np.log(levels)), np.log(levels[1] / levels[0]))  # geometric
    _, _, wells = _landscape_grid(rastrigin, np.array([-5.0, -5.0]), np.array([5.0, 5.0]), 2)
    assert np.allclose(np.diff(_contour_levels(wells)), np.diff(_contour_levels(wells))[0])


def test_snapshot_frame_holds_every_walker():
    x = np.random.default_rng(0).standard_normal((1000, 3))
    lo, hi = _frame(x, (-10.0, 10.0))
    assert np.all(x[:, :2] > lo) and np.all(x[:, :2] < hi)


@pytest.mark.slow  # the k-NN run in 4D: test_cli's user landscape test
def test_figures_of_a_3d_run(tmp_path, capsys):
    """Smoke: a 3D Delaunay run writes both figures (the content rules are tested above)."""
    assert (
        main(
            [
                "simulate",
                "--n",
                "150",
                "--steps",
                "3",
                "--gap-every",
                "0",
                "--no-progress",
                "--dim",
                "3",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert (tmp_path / "swarm.png").stat().st_size > 10_000 and (tmp_path / "observables.png").stat().st_size > 10_000
    capsys.readouterr()
