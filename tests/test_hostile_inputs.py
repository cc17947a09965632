"""Issue 47: no legal input exhausts memory, nothing NaN passes without a word.

Diverging swarms under every driver, in a child process with a memory cap; NaN and
indefinite metrics; a non-traceable objective. (Ctrl-C in `jaxgeom tune`: tests/apps/test_cli.py.)
"""

import os
import resource
import subprocess
import sys
import textwrap
import time
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.tessellation._triangulators import triangulate

MEMORY_CAP = 4 * 2**30  # address space; XLA reserves more than it touches (resident: ~0.6-1.4 GB here)


def run_capped(argv, timeout=240, cap=MEMORY_CAP):
    """(exit status, output, seconds) of `argv` in a child process whose address space is capped."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    began = time.perf_counter()
    proc = subprocess.run(
        argv,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (cap, cap)),
    )
    return proc.returncode, proc.stdout + proc.stderr, time.perf_counter() - began


@pytest.mark.parametrize("dim", [2, pytest.param(3, marks=pytest.mark.slow)])
def test_tune_on_rosenbrock_ends_with_the_cause_instead_of_exhausting_memory(dim, tmp_path):
    """Once: 24 GB resident and the kernel's OOM killer (a diverged swarm's coordinates sent CDT
    into an endless allocation); then `target 'velocity_variance' must be a finite number; got nan`."""
    status, out, seconds = run_capped(
        [
            sys.executable,
            "-m",
            "jaxgeom.cli",
            "tune",
            "--tune",
            "nu",
            "eps_sigma",
            "--dim",
            str(dim),
            "--weights",
            "metric_full",
            "--landscape",
            "rosenbrock",
            "--max-steps",
            "3",
            "--no-progress",
        ],
        cap=3 * 2**30,
    )
    assert status == 2 and "Traceback" not in out, out
    assert "the simulation at the true values diverged by step" in out, out
    assert "reduce --dt below" in out and "|grad V| reaches" in out, out


DRIVERS = textwrap.dedent("""
    import sys, jax, numpy as np, jax.numpy as jnp, jaxgeom
    jax.config.update("jax_enable_x64", True)
    def V(x):  # Rosenbrock (and a bowl beyond 2D): dt = 0.05 is far too large for it
        return 100.0 * (x[1] - x[0] ** 2) ** 2 + (1.0 - x[0]) ** 2 + jnp.sum(x[2:] ** 2)
    for case in sys.argv[1:]:
        d, graph = (3 if "3d" in case else 2), ("knn" if "knn" in case else "delaunay")
        state = jaxgeom.init_swarm(V, np.random.default_rng(0).uniform(-2, 2, (80, d)), key=0, graph=graph, k=8)
        params = jaxgeom.SwarmParams(dt=0.05, gamma=0.5, temperature=1.0, nu=0.3, weights="metric_full",
                                     anisotropic=True)
        if case == "host":
            try:
                jaxgeom.simulate(V, state, params, n_steps=30)
                raise SystemExit("host: no divergence")
            except FloatingPointError as err:
                assert "diverged by step" in str(err), err
        elif case.startswith("seeds"):
            loss = jaxgeom.simulation_loss(V, state, "mean_fitness", n_steps=30, params=params, n_seeds=3)
            assert np.isposinf(float(jax.jit(lambda t: loss(t))(loss.to_theta())))
            assert "diverged by step" in loss.divergence(loss.to_theta())
        else:
            mode = "device" if case == "device" else "callback"
            _, h = jax.jit(lambda s: jaxgeom.simulate(V, s, params, n_steps=30, rebuild=mode))(state)
            assert int(h["diverged_step"]) >= 0
        print("ok", case, flush=True)
""")


@pytest.mark.slow
@pytest.mark.parametrize(
    "cases", [("host", "callback", "seeds"), ("callback-knn", "callback-3d", "seeds-knn", "device")], ids=" ".join
)
def test_a_diverging_swarm_never_grows_memory_in_any_driver(cases, tmp_path):
    """Every driver meets the diverged walkers' coordinates (1e6 swarm radii, then inf) in its
    rebuilds; under a capped address space each ends with its divergence report."""
    script = tmp_path / "drivers.py"
    script.write_text(DRIVERS)
    status, out, _ = run_capped([sys.executable, str(script), *cases], timeout=400)
    assert status == 0, out
    assert all(f"ok {case}" in out for case in cases), out


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e200])
@pytest.mark.parametrize("backend", ["cdt", "qhull"])
def test_triangulators_refuse_coordinates_they_cannot_take_at_once(bad, backend):
    """CDT allocated until the machine ran out of memory on an infinite coordinate, and looped for
    minutes on one walker at 1e200."""
    x = np.random.default_rng(0).uniform(-1, 1, (200, 2))
    x[7] = bad
    began = time.perf_counter()
    with pytest.raises(ValueError, match=r"1 walker\(s\) have non-finite coordinates or coordinates beyond"):
        triangulate(x, backend)
    assert time.perf_counter() - began < 1.0


@pytest.fixture
def tess():
    return jaxgeom.delaunay(np.random.default_rng(0).random((200, 2)))


def nan_metric(p):
    return jnp.full((2, 2), jnp.nan)


def saddle(p):
    return jnp.diag(jnp.asarray([1.0, -1.0]))


def test_a_nan_metric_array_is_refused_like_an_asymmetric_one(tess):
    g = np.broadcast_to(np.eye(2), (200, 2, 2)).copy()
    g[[3, 17]] = np.nan
    with pytest.raises(
        ValueError,
        match=r"`metric` must be finite; 2 walker\(s\) have NaN or inf entries, first "
        r"rows \[3, 17\]",
    ):
        jaxgeom.ricci_scalar(tess, metric=g)
    with pytest.raises(ValueError, match="must be finite"):
        jaxgeom.ricci_scalar(tess, metric=np.full((200, 2, 2), np.nan))


def test_metric_defects_flags_nan_rows_of_callables(tess):
    assert np.asarray(jaxgeom.metric_defects(tess, nan_metric)).all()

    def nan_right(p):
        return jnp.where(p[0] > 0.5, jnp.nan, 1.0) * jnp.eye(2)

    np.testing.assert_array_equal(jaxgeom.metric_defects(tess, nan_right), np.asarray(tess.points)[:, 0] > 0.5)


@pytest.mark.parametrize("metric", [nan_metric, saddle], ids=["nan", "indefinite"])
@pytest.mark.parametrize(
    "kernel",
    [
        lambda t, g: jaxgeom.ricci_scalar(t, metric=g),
        lambda t, g: jaxgeom.viscous_force(t, np.ones((200, 2)), nu=0.1, weights="metric_full", metric=g),
        lambda t, g: jaxgeom.edge_lengths(t, metric=g),
    ],
    ids=["ricci_scalar", "viscous_force", "edge_lengths"],
)
def test_a_defective_callable_metric_warns_with_the_count_and_the_remedy(tess, kernel, metric):
    with pytest.warns(RuntimeWarning, match=r"at 200 of 200 walkers.*jaxgeom\.metric_defects"):
        kernel(tess, metric)
    with warnings.catch_warnings():  # checked once per callable and positions
        warnings.simplefilter("error")
        kernel(tess, metric)


def test_a_sound_callable_metric_gives_no_warning(tess):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jaxgeom.ricci_scalar(tess, metric=jaxgeom.hessian_metric(lambda p: jnp.sum(p**2), 0.1))


def test_a_non_traceable_objective_is_named_with_the_fix():
    """Once: JAX's TracerArrayConversionError from inside the user's objective."""

    def V(p):
        return jnp.sum(p**2)

    state = jaxgeom.init_swarm(V, np.random.default_rng(0).random((40, 2)))
    with pytest.raises(TypeError, match=r"the objective must be JAX-traceable.*TracerArrayConversionError"):
        jaxgeom.simulation_loss(
            V, state, lambda h: float(np.asarray(h["mean_fitness"])[-1]), n_steps=2, params=jaxgeom.SwarmParams()
        )
