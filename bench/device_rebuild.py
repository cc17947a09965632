"""The device Delaunay rebuild (jaxgeom.rebuild) against Qhull (jaxgeom.delaunay), side by side.

Run: python bench/device_rebuild.py [--sizes 1000 10000 100000] [--out bench/results/device_rebuild.json]

float32 (the library default), 2D, on this machine's CPU, in one run:

- per size and sample (uniform in a box; Gaussian, no box; the clustered swarm of a
  `simulate` run on the default Rastrigin landscape), the median of 3 calls of
  `jaxgeom.delaunay` (host Qhull and the jitted assembly) and of `jaxgeom.rebuild` from the
  graph of slightly earlier positions (compiled first, compile time reported apart), whether
  the rebuild was certified, its repair rounds and repaired cells, and the share of its time
  in the first pass (cell list + clipping of every cell);
- `simulate` with a rebuild every step, rebuild="device" against "callback" (both one
  jitted scan), steps per second and the device mode's Qhull fallbacks.
"""

from __future__ import annotations

import argparse
import functools
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.tessellation._cellclip import first_candidates, triangulate, voronoi_cycles


def median_seconds(fn, repeats=3):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return float(np.median(times)), times


def clustered_swarm(n: int) -> np.ndarray:
    x0 = np.random.default_rng(0).uniform(-5.12, 5.12, (n, 2)).astype(np.float32)
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    state = jaxgeom.init_swarm(rastrigin, x0, key=0)
    state, _ = jaxgeom.simulate(rastrigin, state, params, n_steps=40, observe=())
    return np.asarray(state.positions)


def sample(kind: str, n: int) -> tuple[np.ndarray, object]:
    rng = np.random.default_rng(1)
    if kind == "uniform_box":
        return rng.random((n, 2)).astype(np.float32), (0.0, 1.0)
    if kind == "gaussian":
        return rng.normal(size=(n, 2)).astype(np.float32), None
    return clustered_swarm(n), None


def compare(kind: str, n: int) -> dict:
    x0, box = sample(kind, n)
    spacing = float(np.sqrt(np.ptp(x0[:, 0]) * np.ptp(x0[:, 1]) / n))
    x = x0 + (0.05 * spacing * np.random.default_rng(2).normal(size=x0.shape)).astype(np.float32)
    if box is not None:
        x = np.clip(x, 1e-6, 1 - 1e-6).astype(np.float32)
    tess = jaxgeom.delaunay(x0, box=box)
    qhull, qhull_runs = median_seconds(lambda: jaxgeom.delaunay(x, box=box, capacity=tess).neighbors)
    xj = jnp.asarray(x)
    start = time.perf_counter()
    new = jaxgeom.rebuild(tess, xj)
    jax.block_until_ready(new.neighbors)
    compile_seconds = time.perf_counter() - start
    device, device_runs = median_seconds(lambda: jaxgeom.rebuild(tess, xj).neighbors)
    first_pass = jax.jit(lambda p: voronoi_cycles(p, first_candidates(p)[0])[0])
    jax.block_until_ready(first_pass(xj))
    first, _ = median_seconds(lambda: first_pass(xj))
    result = jax.jit(functools.partial(triangulate, s_cap=tess.capacity.simplices))(xj)
    row = {
        "sample": kind,
        "n": n,
        "qhull_seconds": qhull,
        "device_seconds": device,
        "device_over_qhull": device / qhull,
        "first_pass_seconds": first,
        "compile_seconds": compile_seconds,
        "certified": bool(~new.overflow),
        "repair_rounds": int(result.rounds),
        "repaired_cells": int(result.n_repaired),
        "runs": {"qhull": qhull_runs, "device": device_runs},
    }
    print(json.dumps(row))
    return row


def simulate_modes(n: int, n_steps: int) -> dict:
    x0 = np.random.default_rng(0).uniform(-5.12, 5.12, (n, 2)).astype(np.float32)
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    state = jaxgeom.init_swarm(rastrigin, x0, key=0)
    out = {"n": n, "n_steps": n_steps}
    for mode in ("callback", "device"):
        run = lambda: jaxgeom.simulate(
            rastrigin,
            state,
            params,
            n_steps=n_steps,
            rebuild=mode,  # noqa: E731
            observe=("mean_fitness",),
        )
        jax.block_until_ready(run()[0].positions)  # compile
        seconds, _ = median_seconds(lambda: run()[0].positions)
        out[f"{mode}_steps_per_second"] = n_steps / seconds
        out[f"{mode}_fallbacks"] = int(run()[1]["n_fallbacks"])
    print(json.dumps(out))
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000])
    parser.add_argument("--simulate-n", type=int, default=1000)
    parser.add_argument("--out", default="bench/results/device_rebuild.json")
    args = parser.parse_args()
    rows = [compare(kind, n) for n in args.sizes for kind in ("uniform_box", "gaussian", "clustered_swarm")]
    report = {
        "machine": platform.processor() or platform.machine(),
        "cpus": jax.local_device_count(),
        "device": str(jax.devices()[0]),
        "jax": jax.__version__,
        "dtype": "float32",
        "rebuild_vs_qhull": rows,
        "simulate": simulate_modes(args.simulate_n, 30),
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
