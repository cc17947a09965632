"""Run by tests/swarm/test_sharding.py in a subprocess with 4 forced CPU devices (XLA_FLAGS set
before jax is imported): sharded ensembles, seed-sharded losses and one swarm with its walkers
split, against one device."""

import os

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4").strip()

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jaxgeom  # noqa: E402
from jaxgeom.apps._landscapes import rastrigin  # noqa: E402

N, B = 40, 8
CAPACITY = jaxgeom.Capacity(simplices=128, neighbors=16)


def swarm(seed):
    x = np.random.default_rng(seed).uniform(-2.0, 2.0, (N, 2))
    return jaxgeom.init_swarm(rastrigin, x, key=seed, capacity=CAPACITY)


def same(a, b) -> bool:
    """Bitwise equal pytrees (NaN equal to NaN: the callback mode records NaN timings)."""
    pairs = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True)
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
        loss = jaxgeom.simulation_loss(
            rastrigin,
            swarm(0),
            "mean_fitness",
            params=params,
            n_steps=5,
            n_seeds=8,
            tuned=("nu", "eps_sigma"),
            mesh=mesh,
        )
        value, grad = eqx.filter_jit(lambda f, t: jax.value_and_grad(f)(t))(loss, loss.to_theta())
        results.append((float(value), np.asarray(grad)))
    (v1, g1), (v4, g4) = results
    assert np.all(g1 != 0.0), g1  # both nu and eps_sigma move the run
    # every lane is bitwise the same; the seed mean's summation order may differ by an ulp
    np.testing.assert_allclose(v4, v1, rtol=1e-14, atol=0)
    np.testing.assert_allclose(g4, g1, rtol=1e-12, atol=0)


def gaussian_swarm(n, seed, **kwargs):
    x = np.random.default_rng(seed).normal(size=(n, 2))
    return jaxgeom.init_swarm(
        rastrigin, x, key=seed, capacity=jaxgeom.Capacity(simplices=4 * n, neighbors=24), **kwargs
    )


def check_split_rebuild():
    """The device rebuild with its cells split over 4 devices: the graph of one device (and of
    Qhull), and each device clips only its quarter of the cells: the per-cell vertex arrays of
    the compiled program have N / 4 rows in the first pass (never N) and N / 16 in the repairs
    (whose capacity is N / 4 cells)."""
    n = 400
    tess = jaxgeom.delaunay(np.random.default_rng(0).normal(size=(n, 2)))
    moved = np.asarray(tess.points) + 0.05 * np.random.default_rng(1).normal(size=(n, 2))
    mesh = jaxgeom.walker_mesh()
    one, split = jaxgeom.rebuild(tess, moved), jaxgeom.rebuild(tess, moved, mesh=mesh)
    assert not bool(one.overflow)
    assert same(one, split), "the split rebuild differs from the one-device rebuild"
    np.testing.assert_array_equal(np.asarray(split.neighbors), np.asarray(jaxgeom.delaunay(moved).neighbors))
    from jaxgeom.tessellation._cellclip import rebuild_unchecked

    hlo = {m: rebuild_unchecked.lower(tess, moved, m).compile().as_text() for m in (None, mesh)}
    assert "f64[400,24,3]" in hlo[None] and "f64[25,24,3]" not in hlo[None]
    assert "f64[400,24,3]" not in hlo[mesh] and "f64[25,24,3]" in hlo[mesh], "the cells were not split"


def check_split_walkers():
    """One swarm, walkers split over 4 devices, rebuilt on the device every step: the same run
    as on one device to rounding (the same graph at every step). Without cloning every rebuild
    is certified (the split device rebuild builds each graph); with cloning the clustered swarm
    falls back to Qhull on some steps, the same steps in both runs."""
    state = gaussian_swarm(400, 3)
    observe = ("mean_fitness", "mean_ricci", "n_clones", "volume_distortion", "mean_expansion")
    mesh = jaxgeom.walker_mesh()
    for params, fallbacks in (
        (jaxgeom.SwarmParams(cloning=False, weights="metric_full", anisotropic=True, dt=0.005), "none"),
        (jaxgeom.SwarmParams(cloning=True, clone_rate=0.5, dt=0.02), "some"),
    ):
        run = dict(n_steps=5, rebuild="device", observe=observe)
        one = jaxgeom.simulate(rastrigin, state, params, **run)
        split = jaxgeom.simulate(rastrigin, state, params, mesh=mesh, **run)
        assert len(split[0].positions.sharding.device_set) == 4
        assert split[0].positions.sharding.spec == jax.sharding.PartitionSpec("walkers")
        np.testing.assert_array_equal(np.asarray(split[0].tess.simplices), np.asarray(one[0].tess.simplices))
        np.testing.assert_array_equal(np.asarray(split[0].cloned), np.asarray(one[0].cloned))
        np.testing.assert_allclose(np.asarray(split[0].positions), np.asarray(one[0].positions), rtol=0, atol=1e-13)
        for name in observe:
            np.testing.assert_allclose(np.asarray(split[1][name]), np.asarray(one[1][name]), rtol=1e-12, atol=1e-13)
        assert int(one[1]["n_fallbacks"]) == int(split[1]["n_fallbacks"])
        assert (int(one[1]["n_fallbacks"]) == 0) == (fallbacks == "none"), one[1]["n_fallbacks"]
    assert float(jnp.sum(one[1]["n_clones"])) > 0
    for bad, match in (
        (dict(rebuild="callback"), "needs the device rebuild"),
        (dict(mesh=jaxgeom.batch_mesh()), "split its walkers with mesh=jaxgeom.walker_mesh"),
    ):
        try:
            jaxgeom.simulate(rastrigin, state, params, **{**run, "mesh": jaxgeom.walker_mesh(), **bad})
        except ValueError as err:
            assert match in str(err), err
        else:
            raise AssertionError(f"{bad} was accepted")
    try:
        jaxgeom.simulate(rastrigin, gaussian_swarm(402, 0), params, mesh=jaxgeom.walker_mesh(), **run)
    except ValueError as err:
        assert "the number of walkers N = 402 must be a multiple of the mesh's 4 devices" in str(err), err
    else:
        raise AssertionError("402 walkers on 4 devices were accepted")


if __name__ == "__main__":
    check_split_rebuild()
    check_split_walkers()
    check_ensemble()
    check_device_rebuild_ensemble()
    check_loss_and_gradient()
    print("sharded checks passed")
