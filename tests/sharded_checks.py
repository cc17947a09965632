"""Run by tests/test_sharding.py in a subprocess with 4 forced CPU devices (XLA_FLAGS set
before jax is imported): sharded ensembles and seed-sharded losses against one device."""

import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxgeom  # noqa: E402
from jaxgeom._landscapes import rastrigin  # noqa: E402

N, B = 40, 8
CAPACITY = jaxgeom.Capacity(simplices=128, neighbors=16)


def swarm(seed):
    x = np.random.default_rng(seed).uniform(-2.0, 2.0, (N, 2))
    return jaxgeom.init_swarm(rastrigin, x, key=seed, capacity=CAPACITY)


def same(a, b) -> bool:
    """Bitwise equal pytrees (NaN equal to NaN: the callback mode records NaN timings)."""
    pairs = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in pairs)


def check_ensemble():
    batch = jaxgeom.stack_swarms([swarm(i) for i in range(B)])
    params = jaxgeom.SwarmParams(cloning=True, clone_rate=0.5, weights="metric_full", anisotropic=True)
    run = dict(n_steps=4, rebuild="callback", observe=("mean_fitness", "velocity_variance", "n_clones"))
    mesh = jaxgeom.batch_mesh()
    assert mesh.devices.size == 4
    alone = jaxgeom.simulate(rastrigin, batch, params, **run)
    sharded = jaxgeom.simulate(rastrigin, jaxgeom.shard_batch(batch, mesh), params, mesh=mesh, **run)
    assert len(sharded[0].positions.sharding.device_set) == 4
    assert same(alone, sharded), "the sharded ensemble differs from the unsharded one"
    lane = jaxgeom.simulate(rastrigin, swarm(5), params, **run)
    assert same(lane[0].positions, alone[0].positions[5]), "lane 5 differs from its swarm run alone"
    assert float(jnp.sum(alone[1]["n_clones"])) > 0  # cloning took part
    try:
        jaxgeom.simulate(rastrigin, jaxgeom.stack_swarms([swarm(i) for i in range(6)]), params, mesh=mesh, **run)
    except ValueError as err:
        assert "must be a multiple of the mesh's 4 devices" in str(err) and "use 8" in str(err)
    else:
        raise AssertionError("6 swarms on 4 devices were accepted")


def check_device_rebuild_ensemble():
    """The 2D device rebuild (no Qhull unless uncertified) splits the same way."""
    batch = jaxgeom.stack_swarms([swarm(i) for i in range(B)])
    run = dict(n_steps=3, rebuild="device", observe=("mean_fitness",))
    mesh = jaxgeom.batch_mesh()
    params = jaxgeom.SwarmParams(cloning=False)
    alone = jaxgeom.simulate(rastrigin, batch, params, **run)
    assert same(alone, jaxgeom.simulate(rastrigin, jaxgeom.shard_batch(batch, mesh), params, mesh=mesh, **run))


def check_loss_and_gradient():
    params = jaxgeom.SwarmParams(cloning=False, weights="metric_full", anisotropic=True, temperature=0.5)
    results = []
    for mesh in (None, jaxgeom.batch_mesh()):
        loss = jaxgeom.simulation_loss(rastrigin, swarm(0), "mean_fitness", params=params, n_steps=5, n_seeds=8,
                                       mesh=mesh)
        value, grad = eqx.filter_jit(lambda f, t: jax.value_and_grad(f)(t))(loss, loss.to_theta())
        results.append((float(value), np.asarray(grad)))
    (v1, g1), (v4, g4) = results
    assert np.all(g1 != 0.0), g1  # both nu and eps_sigma move the run
    # every lane is bitwise the same; the seed mean's summation order may differ by an ulp
    np.testing.assert_allclose(v4, v1, rtol=1e-14, atol=0)
    np.testing.assert_allclose(g4, g1, rtol=1e-12, atol=0)


if __name__ == "__main__":
    check_ensemble()
    check_device_rebuild_ensemble()
    check_loss_and_gradient()
    print("sharded checks passed")
