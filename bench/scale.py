"""Ensembles over devices: the cost of sharding a batch of swarms against one device.

On this 2-core machine the devices are forced host devices (XLA_FLAGS
--xla_force_host_platform_device_count, set here before jax is imported unless
already set), which share the same 2 cores: the figure is the overhead and the
correctness of the layout, not a speed-up. On a machine with several accelerators the same
script measures the real scaling (pass --forced 0).

Writes bench/results/scale.json: for each (B swarms, N walkers), the seconds per step of
`simulate(batch, rebuild="callback")` under vmap on one device and split over the mesh
(medians of --repeat warm runs, with the spread), their ratio, and whether the results are
bitwise equal (else the largest difference of the final positions: with one swarm per device
XLA compiles the lane without its batch axis, which can round differently; with two or more
per device the program is the same and so are the bits).
"""

from __future__ import annotations

import argparse
import os
import sys

if __name__ == "__main__":
    forced = int(sys.argv[sys.argv.index("--forced") + 1]) if "--forced" in sys.argv else 4
    if forced:
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") +
                                   f" --xla_force_host_platform_device_count={forced}").strip()

import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import jaxgeom  # noqa: E402
from jaxgeom._landscapes import rastrigin  # noqa: E402


def batch_of(b: int, n: int):
    capacity = jaxgeom.Capacity(simplices=max(64, 4 * n), neighbors=32)  # room for clustering
    return jaxgeom.stack_swarms([jaxgeom.init_swarm(rastrigin, np.random.default_rng(i).uniform(-3, 3, (n, 2)),
                                                    key=i, capacity=capacity) for i in range(b)])


def timed(fn, repeat: int) -> tuple[list[float], object]:
    out = jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return times, out


def same(a, b) -> bool:
    pairs = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in pairs)


def row(b: int, n: int, steps: int, repeat: int) -> dict:
    batch, mesh = batch_of(b, n), jaxgeom.batch_mesh()
    params = jaxgeom.SwarmParams(temperature=1.0, gamma=2.0)
    run = dict(n_steps=steps, rebuild="callback", observe=("mean_fitness", "velocity_variance"))
    one, out_one = timed(lambda: jaxgeom.simulate(rastrigin, batch, params, **run), repeat)
    placed = jaxgeom.shard_batch(batch, mesh)
    many, out_many = timed(lambda: jaxgeom.simulate(rastrigin, placed, params, mesh=mesh, **run), repeat)
    per_step = {"one_device": [t / steps for t in one], "sharded": [t / steps for t in many]}
    return {"swarms": b, "walkers": n, "steps": steps, "devices": int(mesh.devices.size),
            "seconds_per_step_one_device_median": float(np.median(per_step["one_device"])),
            "seconds_per_step_sharded_median": float(np.median(per_step["sharded"])),
            "spread": {k: [float(min(v)), float(max(v))] for k, v in per_step.items()},
            "sharded_over_one_device": float(np.median(many) / np.median(one)),
            "bitwise_equal": same(out_one, out_many),
            "max_position_difference": float(np.max(np.abs(np.asarray(out_one[0].positions)
                                                            - np.asarray(out_many[0].positions))))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--forced", type=int, default=4, help="forced host devices (0: the real ones)")
    parser.add_argument("--batches", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--walkers", type=int, nargs="+", default=[300, 3000])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "scale.json")
    args = parser.parse_args()
    device = jax.devices()[0]
    rows = []
    for b, n in tqdm([(b, n) for b in args.batches for n in args.walkers], desc="scale", disable=None):
        rows.append(row(b, n, args.steps, args.repeat))
        tqdm.write(json.dumps(rows[-1]))
    meta = {"machine": platform.machine(), "cores": os.cpu_count(), "jax": jax.__version__,
            "backend": jax.default_backend(), "device": f"{device.device_kind} x{jax.device_count()}",
            "forced_host_devices": args.forced,
            "gpu": "none lent to this task: no GPU figures" if jax.default_backend() == "cpu" else "yes"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "ensembles": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
