"""The multi-host recipe, checked on one machine: N processes (one per host in real use), each
running this same script with its own --process-id, form one JAX runtime
(`jax.distributed.initialize`); an ensemble of swarms is split over every process's devices and
the gathered result is compared with one process running the whole batch.

    python bench/multihost.py --process-id 0 --num-processes 2 &
    python bench/multihost.py --process-id 1 --num-processes 2

On GPUs leave out --cpu-collectives (NCCL is used); on CPUs JAX needs gloo for the collectives.
"""

from __future__ import annotations

import argparse

import jax


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--process-id", type=int, required=True)
    parser.add_argument("--num-processes", type=int, default=2)
    parser.add_argument("--coordinator", default="127.0.0.1:12355", help="host:port of process 0")
    parser.add_argument("--cpu-collectives", default="gloo", help="'' on GPU machines")
    parser.add_argument("--swarms", type=int, default=4)
    args = parser.parse_args()
    if args.cpu_collectives:
        jax.config.update("jax_cpu_collectives_implementation", args.cpu_collectives)
    jax.distributed.initialize(
        coordinator_address=args.coordinator, num_processes=args.num_processes, process_id=args.process_id
    )
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    from jax.experimental import multihost_utils

    import jaxgeom
    from jaxgeom.apps._landscapes import rastrigin

    capacity = jaxgeom.Capacity(simplices=128, neighbors=16)
    batch = jaxgeom.stack_swarms(
        [
            jaxgeom.init_swarm(rastrigin, np.random.default_rng(i).uniform(-2, 2, (40, 2)), key=i, capacity=capacity)
            for i in range(args.swarms)
        ]
    )
    params, run = jaxgeom.SwarmParams(cloning=False), dict(n_steps=3, rebuild="callback", observe=("mean_fitness",))
    mesh = jaxgeom.batch_mesh()  # every process's devices
    _, history = jaxgeom.simulate(rastrigin, jaxgeom.shard_batch(batch, mesh), params, mesh=mesh, **run)
    gathered = np.asarray(multihost_utils.process_allgather(history["mean_fitness"], tiled=True))
    print(
        f"process {jax.process_index()} of {jax.process_count()}: {len(jax.local_devices())} local of "
        f"{jax.device_count()} devices",
        flush=True,
    )
    if jax.process_index() == 0:
        alone = np.asarray(jaxgeom.simulate(rastrigin, batch, params, **run)[1]["mean_fitness"])
        print(f"multi-process ensemble equals one process: {np.array_equal(gathered, alone)}", flush=True)


if __name__ == "__main__":
    main()
