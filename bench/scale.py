"""Sharding over devices: a batch of swarms, and one swarm's walkers, against one device.

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

For one swarm of N walkers split over the mesh ("walkers" rows): the seconds per step of
`simulate(state, rebuild="device")` (the graph rebuilt on the device every step; no cloning, so
the rebuilds are certified) on one device and with `mesh=walker_mesh()`, the largest difference
of the final positions, whether the graphs are equal, and XLA's buffer plan of the compiled run
per device (temporaries + arguments + outputs), from which the bytes per walker that every
device holds whole (the gathered positions and the global certificate arrays) and the bytes per
walker that are split are solved: per device = whole x N + split x N / D.
"""

from __future__ import annotations

import argparse
import os
import sys

if __name__ == "__main__":
    forced = int(sys.argv[sys.argv.index("--forced") + 1]) if "--forced" in sys.argv else 4
    if forced:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={forced}"
        ).strip()

import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import jaxgeom  # noqa: E402
from jaxgeom.apps._landscapes import rastrigin  # noqa: E402


def batch_of(b: int, n: int):
    capacity = jaxgeom.Capacity(simplices=max(64, 4 * n), neighbors=32)  # room for clustering
    return jaxgeom.stack_swarms(
        [
            jaxgeom.init_swarm(rastrigin, np.random.default_rng(i).uniform(-3, 3, (n, 2)), key=i, capacity=capacity)
            for i in range(b)
        ]
    )


def timed(fn, repeat: int) -> tuple[list[float], object]:
    out = jax.block_until_ready(fn())  # compile
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return times, out


def same(a, b) -> bool:
    pairs = zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True)
    return all(np.array_equal(np.asarray(x), np.asarray(y), equal_nan=True) for x, y in pairs)


def row(b: int, n: int, steps: int, repeat: int) -> dict:
    batch, mesh = batch_of(b, n), jaxgeom.batch_mesh()
    params = jaxgeom.SwarmParams(temperature=1.0, gamma=2.0)
    run = dict(n_steps=steps, rebuild="callback", observe=("mean_fitness", "velocity_variance"))
    one, out_one = timed(lambda: jaxgeom.simulate(rastrigin, batch, params, **run), repeat)
    placed = jaxgeom.shard_batch(batch, mesh)
    many, out_many = timed(lambda: jaxgeom.simulate(rastrigin, placed, params, mesh=mesh, **run), repeat)
    per_step = {"one_device": [t / steps for t in one], "sharded": [t / steps for t in many]}
    return {
        "swarms": b,
        "walkers": n,
        "steps": steps,
        "devices": int(mesh.devices.size),
        "seconds_per_step_one_device_median": float(np.median(per_step["one_device"])),
        "seconds_per_step_sharded_median": float(np.median(per_step["sharded"])),
        "spread": {k: [float(min(v)), float(max(v))] for k, v in per_step.items()},
        "sharded_over_one_device": float(np.median(many) / np.median(one)),
        "bitwise_equal": same(out_one, out_many),
        "max_position_difference": float(
            np.max(np.abs(np.asarray(out_one[0].positions) - np.asarray(out_many[0].positions)))
        ),
    }


def gaussian_swarm(n: int):
    x = np.random.default_rng(0).normal(size=(n, 2))
    return jaxgeom.init_swarm(rastrigin, x, key=0, capacity=jaxgeom.Capacity(simplices=4 * n, neighbors=24))


def planned_bytes(state, params, steps: int, mesh) -> int:
    """Per-device bytes of XLA's buffer plan for the whole run (temporaries, arguments, outputs):
    the split run's program, with the cells split over `mesh` or (None) on one device."""
    from jaxgeom.base._sharding import shard_walkers
    from jaxgeom.swarm._steps import _run_split

    placed = state if mesh is None else shard_walkers(state, mesh, state.positions.shape[0])
    count = jax.numpy.asarray(steps, jax.numpy.int32)
    memory = (
        _run_split.lower(
            rastrigin,
            params,
            placed,
            count,
            count * 0,
            steps,
            ("mean_fitness",),
            1,
            state.tess.neighbors.shape[1],
            mesh,
        )
        .compile()
        .memory_analysis()
    )
    return int(memory.temp_size_in_bytes + memory.argument_size_in_bytes + memory.output_size_in_bytes)


def walker_row(n: int, steps: int, repeat: int) -> dict:
    state, mesh = gaussian_swarm(n), jaxgeom.walker_mesh()
    params = jaxgeom.SwarmParams(cloning=False, dt=0.005)
    run = dict(n_steps=steps, rebuild="device", observe=("mean_fitness", "velocity_variance"))
    one, out_one = timed(lambda: jaxgeom.simulate(rastrigin, state, params, **run), repeat)
    many, out_many = timed(lambda: jaxgeom.simulate(rastrigin, state, params, mesh=mesh, **run), repeat)
    per_step = {"one_device": [t / steps for t in one], "sharded": [t / steps for t in many]}
    devices = int(mesh.devices.size)
    bytes_one, bytes_split = planned_bytes(state, params, steps, None), planned_bytes(state, params, steps, mesh)
    split = (bytes_one - bytes_split) / (1 - 1 / devices) / n  # whole + split = one; whole + split / D = sharded
    return {
        "walkers": n,
        "dimension": 2,
        "steps": steps,
        "devices": devices,
        "seconds_per_step_one_device_median": float(np.median(per_step["one_device"])),
        "seconds_per_step_sharded_median": float(np.median(per_step["sharded"])),
        "spread": {k: [float(min(v)), float(max(v))] for k, v in per_step.items()},
        "sharded_over_one_device": float(np.median(many) / np.median(one)),
        "fallbacks_to_qhull": [int(out_one[1]["n_fallbacks"]), int(out_many[1]["n_fallbacks"])],
        "same_graph": bool(
            np.array_equal(np.asarray(out_one[0].tess.simplices), np.asarray(out_many[0].tess.simplices))
        ),
        "max_position_difference": float(
            np.max(np.abs(np.asarray(out_one[0].positions) - np.asarray(out_many[0].positions)))
        ),
        "planned_bytes_per_device": {"one_device": bytes_one, "sharded": bytes_split},
        "bytes_per_walker": {"whole_on_every_device": bytes_one / n - split, "split": split},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--forced", type=int, default=4, help="forced host devices (0: the real ones)")
    parser.add_argument("--batches", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--walkers", type=int, nargs="+", default=[300, 3000])
    parser.add_argument(
        "--swarm-walkers",
        type=int,
        nargs="+",
        default=[2000, 8000],
        help="N of the one-swarm runs with the walkers split",
    )
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "scale.json")
    args = parser.parse_args()
    device = jax.devices()[0]
    rows = []
    for b, n in tqdm([(b, n) for b in args.batches for n in args.walkers], desc="scale", disable=None):
        rows.append(row(b, n, args.steps, args.repeat))
        tqdm.write(json.dumps(rows[-1]))
    walker_rows = []
    for n in tqdm(args.swarm_walkers, desc="walkers", disable=None):
        walker_rows.append(walker_row(n, max(2, args.steps // 2), args.repeat))
        tqdm.write(json.dumps(walker_rows[-1]))
    meta = {
        "machine": platform.machine(),
        "cores": os.cpu_count(),
        "jax": jax.__version__,
        "backend": jax.default_backend(),
        "device": f"{device.device_kind} x{jax.device_count()}",
        "forced_host_devices": args.forced,
        "gpu": "none lent to this task: no GPU figures" if jax.default_backend() == "cpu" else "yes",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "ensembles": rows, "walkers": walker_rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
