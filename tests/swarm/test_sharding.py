"""Ensembles over devices. The multi-device checks run in a subprocess with 4 forced CPU
devices (tests/swarm/sharded_checks.py), so this process keeps one device; the argument checks
run here."""

import os
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import numpy as np
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin


def swarm(n, seed=0, **kwargs):
    return jaxgeom.init_swarm(rastrigin, np.random.default_rng(seed).uniform(-2.0, 2.0, (n, 2)), key=seed, **kwargs)


# tests/conftest.py's compile settings for the suite (LLVM optimisation off, XLA's loop emitters).
# Under them XLA emits some float ops differently for 2 lanes a device than for 8 on one, and the
# sharded ensemble drifts from the unsharded one by an ulp (velocities at step 3: 4.5e-15
# relative). The bitwise claim is made, and checked, under XLA's own settings: what users run.
_SUITE_ONLY_XLA_FLAGS = (
    "--xla_backend_optimization_level",
    "--xla_llvm_disable_expensive_passes",
    "--xla_cpu_use_fusion_emitters",
)


def _xla_default_env() -> dict[str, str]:
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if not f.startswith(_SUITE_ONLY_XLA_FLAGS)]
    return dict(os.environ, XLA_FLAGS=" ".join(flags))


@pytest.mark.multidevice
def test_sharded_ensembles_and_gradients_equal_one_device():
    script = Path(__file__).with_name("sharded_checks.py")
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=900, env=_xla_default_env()
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-6000:]
    assert "sharded checks passed" in done.stdout


def test_stack_swarms_needs_equal_shapes():
    with pytest.raises(ValueError, match=r"init_swarm\(\.\.\., capacity=jaxgeom.Capacity"):
        jaxgeom.stack_swarms([swarm(30), swarm(40, seed=1)])
    with pytest.raises(TypeError, match="non-empty sequence of single-swarm"):
        jaxgeom.stack_swarms([])


def two_swarms():
    cap = jaxgeom.Capacity(simplices=128, neighbors=16)
    return jaxgeom.stack_swarms([swarm(30, seed=i, capacity=cap) for i in range(2)]), jaxgeom.SwarmParams(cloning=False)


def test_batch_arguments_are_checked():
    batch, params = two_swarms()
    with pytest.raises(ValueError, match="use rebuild='callback' or 'device'"):
        jaxgeom.simulate(rastrigin, batch, params, n_steps=1)
    with pytest.raises(ValueError, match="`spectral_gap_every` .* needs rebuild='host'"):
        jaxgeom.simulate(rastrigin, batch, params, n_steps=2, rebuild="callback", spectral_gap_every=2)
    with pytest.raises(ValueError, match="this state is one swarm"):
        jaxgeom.simulate(rastrigin, swarm(30), params, n_steps=1, mesh=jaxgeom.batch_mesh())
    with pytest.raises(TypeError, match="`mesh` must be a jax.sharding.Mesh"):
        jaxgeom.simulate(rastrigin, batch, params, n_steps=1, rebuild="callback", mesh="gpu")
    with pytest.raises(ValueError, match="`devices` is empty"):
        jaxgeom.batch_mesh([])


def test_one_device_mesh_equals_vmap():
    batch, params = two_swarms()
    run = dict(n_steps=2, rebuild="callback", observe=("mean_fitness",))
    alone = jaxgeom.simulate(rastrigin, batch, params, **run)
    meshed = jaxgeom.simulate(rastrigin, batch, params, mesh=jaxgeom.batch_mesh(), **run)
    np.testing.assert_array_equal(np.asarray(meshed[0].positions), np.asarray(alone[0].positions))
    assert alone[0].positions.shape == (2, 30, 2) and alone[1]["mean_fitness"].shape == (2, 3)


@pytest.mark.multidevice
def test_multihost_recipe_runs_with_two_processes_on_this_machine():
    """bench/multihost.py: jax.distributed.initialize with two CPU processes (gloo collectives)."""
    script = Path(__file__).parents[2] / "bench" / "multihost.py"
    port = str(12000 + os.getpid() % 1000)
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), "--process-id", str(i), "--coordinator", f"127.0.0.1:{port}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for i in range(2)
    ]
    outputs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-3000:] for o in outputs]
    assert "multi-process ensemble equals one process: True" in outputs[0][0], outputs[0]
    assert "process 1 of 2: 1 local of 2 devices" in outputs[1][0], outputs[1]


def test_walker_mesh_arguments_are_checked():
    state, params = swarm(30), jaxgeom.SwarmParams(cloning=False)
    mesh = jaxgeom.walker_mesh()
    with pytest.raises(ValueError, match="needs the device rebuild: use rebuild='device'"):
        jaxgeom.simulate(rastrigin, state, params, n_steps=1, rebuild="host", mesh=mesh)
    with pytest.raises(ValueError, match="split its walkers with mesh=jaxgeom.walker_mesh"):
        jaxgeom.simulate(rastrigin, state, params, n_steps=1, rebuild="device", mesh=jaxgeom.batch_mesh())
    with pytest.raises(TypeError, match=r"`mesh` must be a jax.sharding.Mesh \(jaxgeom.walker_mesh\(\)\)"):
        jaxgeom.rebuild(state.tess, state.positions, mesh="gpu")
    with pytest.raises(ValueError, match="`devices` is empty"):
        jaxgeom.walker_mesh([])


@pytest.mark.multidevice  # with the sharding checks: two compilations of the device rebuild (~25 s)
def test_one_device_walker_mesh_equals_no_mesh():
    """The split code path (shard_map over the cells) on a one-device mesh: the same run."""
    x = np.random.default_rng(2).normal(size=(60, 2))
    state = jaxgeom.init_swarm(rastrigin, x, key=2, capacity=jaxgeom.Capacity(simplices=240, neighbors=24))
    params = jaxgeom.SwarmParams(cloning=False, dt=0.005)
    run = dict(n_steps=2, rebuild="device", observe=("mean_fitness",))
    alone = jaxgeom.simulate(rastrigin, state, params, **run)
    meshed = jaxgeom.simulate(rastrigin, state, params, mesh=jaxgeom.walker_mesh(), **run)
    np.testing.assert_array_equal(np.asarray(meshed[0].tess.simplices), np.asarray(alone[0].tess.simplices))
    np.testing.assert_allclose(np.asarray(meshed[0].positions), np.asarray(alone[0].positions), rtol=0, atol=1e-14)
    assert int(alone[1]["n_fallbacks"]) == 0


def test_walker_split_refuses_traces_and_checkpointing():
    state, params = swarm(30), jaxgeom.SwarmParams(cloning=False)
    run = dict(n_steps=1, rebuild="device", mesh=jaxgeom.walker_mesh())
    with pytest.raises(TypeError, match="cannot run under jax.jit, jax.grad or checkpoint=True"):
        jaxgeom.simulate(rastrigin, state, params, checkpoint=True, **run)
    with pytest.raises(TypeError, match="cannot run under jax.jit"):
        eqx.filter_jit(lambda s: jaxgeom.simulate(rastrigin, s, params, **run))(state)
