"""A `simulate` step with the graph rebuilt every step, by triangulator, side by side in one
process: the figures of issue 46 (on a GPU, `triangulator="cupy"` against `"cdt"`; on a CPU,
the host backends).

Run: python bench/gpu_step.py [--sizes 100000 1000000] [--triangulators cupy cdt] [--steps 10]
     [--out bench/results/gpu_step.json]

2D Rastrigin, float32, the command line's defaults (T = 1, gamma = 2, nu = 0.1, kernel weights,
clone rate 0.1), observables mean and best fitness and clones, `rebuild="host"`. Per size and
backend, medians (min, max) over `--repeat` calls after a warm-up call (compilation):

- `step`: seconds per step with the graph rebuilt every step;
- `step_10`: seconds per step with one rebuild per 10 steps (10-step calls);
- `no_rebuild`: the step without its rebuild, (10 step_10 - step) / 9;
- `kernels`: the warm kernels of a step on the state's graph (Voronoi volumes, viscous force,
  Ricci scalar, fitness gradient), and their sum with the force twice;
- `delaunay`: one `jaxgeom.delaunay` of the walkers with that backend.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

import jaxgeom
from _timing import summary, timed
from jaxgeom.apps._landscapes import rastrigin

OBSERVE = ("mean_fitness", "best_fitness", "n_clones")


def row(n: int, backend: str, steps: int, repeat: int) -> dict:
    x0 = np.random.default_rng(0).uniform(-5.12, 5.12, (n, 2)).astype(np.float32)
    state = jaxgeom.init_swarm(rastrigin, x0, key=0, triangulator=backend)
    params = jaxgeom.SwarmParams(dt=0.01, gamma=2.0, temperature=1.0, nu=0.1, eps_sigma=0.1, weights="kernel",
                                 clone_rate=0.1)
    state, _ = jaxgeom.simulate(rastrigin, state, params, n_steps=10, observe=OBSERVE)  # warm, and a real swarm
    every, tenth = [], []
    for _ in range(repeat):
        every.append(timed(lambda: jaxgeom.simulate(rastrigin, state, params, n_steps=steps, observe=OBSERVE)[0]
                           .positions) / steps)
        tenth.append(timed(lambda: jaxgeom.simulate(rastrigin, state, params, n_steps=10, rebuild_every=10,
                                                    observe=OBSERVE)[0].positions) / 10)
    tess, v = state.tess, state.velocities
    kernels = {
        "voronoi_volumes": lambda: jaxgeom.voronoi_volumes(tess),
        "viscous_force": lambda: jaxgeom.viscous_force(tess, v, nu=0.1),
        "ricci_scalar": lambda: jaxgeom.ricci_scalar(tess),
        "fitness_gradient": lambda: jax.jit(jax.vmap(jax.grad(rastrigin)))(state.positions),
    }
    warm = {}
    for name, fn in kernels.items():
        timed(fn)
        warm[name] = float(np.median([timed(fn) for _ in range(repeat)]))
    x = np.asarray(state.positions)
    jaxgeom.delaunay(x, triangulator=backend)
    build = [timed(lambda: jaxgeom.delaunay(x, triangulator=backend).neighbors) for _ in range(repeat)]
    step, step_10 = float(np.median(every)), float(np.median(tenth))
    kernel_sum = sum(warm.values()) + warm["viscous_force"]
    return {"n": n, "triangulator": backend, "step": summary(every), "step_10": summary(tenth),
            "no_rebuild": (10 * step_10 - step) / 9, "kernels": warm, "kernel_sum_force_twice": kernel_sum,
            "delaunay": summary(build)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--triangulators", nargs="+", default=["cupy", "cdt"])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "gpu_step.json")
    args = parser.parse_args()
    rows = []
    for n in args.sizes:
        for backend in args.triangulators:  # side by side, size by size
            rows.append(row(n, backend, args.steps, args.repeat))
            print(json.dumps(rows[-1]), flush=True)
    device = jax.devices()[0]
    args.out.write_text(json.dumps({"rows": rows, "device": f"{device.platform}: {device.device_kind}",
                                    "jax": jax.__version__, "machine": platform.machine(), "cpus": os.cpu_count(),
                                    "date": time.strftime("%Y-%m-%d")}, indent=1))


if __name__ == "__main__":
    main()
