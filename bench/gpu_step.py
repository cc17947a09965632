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
- `delaunay`: one `jaxgeom.delaunay` of the walkers with that backend;
- `parts` (with `--parts`): where one rebuild's time goes, warm: the bare triangulation
  (`triangulate`: for CuPy the host-to-device copy, gDel2D, the device check and the simplices'
  copy back with their adjacency), `planar_triangles` (that plus degrees and padding) and
  `build_delaunay` (that plus the input checks and the jitted fan walk; for CuPy the device
  build below from a host array), and for CuPy gDel2D alone on device float64 points and
  `planar_graph_on_device` from the JAX device array as `simulate` rebuilds (no host round trip),
  with its steps (`device_parts`); the cProfile of the last call goes to stdout.

A row that raises is recorded with its error and the run goes on; the JSON is rewritten after
each row, so a run cut short keeps the rows it finished. `--stand-in` runs "cupy" on a CPU with
scipy's Qhull and numpy in place of gDel2D and CuPy: the device path's own cost, without a GPU.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import platform
import pstats
import time
from pathlib import Path

import jax
import numpy as np
from _timing import summary, timed

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.tessellation import _triangulators as triangulators
from jaxgeom.tessellation._delaunay import (
    _cut_to_walkers,
    _pad_walkers,
    _planar_rows,
    build_delaunay,
    planar_graph_on_device,
    planar_triangles,
)
from jaxgeom.tessellation._device_check import planar_summary, sort_by_two_keys, sort_in_two_radix_passes
from jaxgeom.tessellation._graph import bucket_neighbors, bucket_walkers

OBSERVE = ("mean_fitness", "best_fitness", "n_clones")


def row(n: int, backend: str, steps: int, repeat: int) -> dict:
    x0 = np.random.default_rng(0).uniform(-5.12, 5.12, (n, 2)).astype(np.float32)
    state = jaxgeom.init_swarm(rastrigin, x0, key=0, triangulator=backend)
    params = jaxgeom.SwarmParams(
        dt=0.01, gamma=2.0, temperature=1.0, nu=0.1, eps_sigma=0.1, weights="kernel", clone_rate=0.1
    )
    state, _ = jaxgeom.simulate(rastrigin, state, params, n_steps=10, observe=OBSERVE)  # warm, and a real swarm
    jaxgeom.simulate(rastrigin, state, params, n_steps=10, rebuild_every=10, observe=OBSERVE)  # compile 10-step chunks
    every, tenth = [], []
    for _ in range(repeat):
        every.append(
            timed(lambda: jaxgeom.simulate(rastrigin, state, params, n_steps=steps, observe=OBSERVE)[0].positions)
            / steps
        )
        tenth.append(
            timed(
                lambda: (
                    jaxgeom.simulate(rastrigin, state, params, n_steps=10, rebuild_every=10, observe=OBSERVE)[
                        0
                    ].positions
                )
            )
            / 10
        )
    tess, v = state.tess, state.velocities
    fitness_gradient = jax.jit(jax.vmap(jax.grad(rastrigin)))
    kernels = {
        "voronoi_volumes": lambda: jaxgeom.voronoi_volumes(tess),
        "viscous_force": lambda: jaxgeom.viscous_force(tess, v, nu=0.1),
        "ricci_scalar": lambda: jaxgeom.ricci_scalar(tess),
        "fitness_gradient": lambda: fitness_gradient(state.positions),
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
    return {
        "n": n,
        "triangulator": backend,
        "step": summary(every),
        "step_10": summary(tenth),
        "no_rebuild": (10 * step_10 - step) / 9,
        "kernels": warm,
        "kernel_sum_force_twice": kernel_sum,
        "delaunay": summary(build),
    }


def parts(x: np.ndarray, backend: str, repeat: int, stand_in: bool = False) -> dict:
    calls = {
        "triangulate": lambda: triangulators.triangulate(x, backend).tri.simplices,
        "planar_triangles": lambda: planar_triangles(x, None, backend)[0],
        "build_delaunay": lambda: build_delaunay(x, triangulator=backend)[0].neighbors,
    }
    if backend == "cupy" and not stand_in:
        import cupy
        from cupyx.scipy.spatial import Delaunay as CupyDelaunay

        xd = cupy.asarray(x, cupy.float64)

        def gdel2d():
            out = CupyDelaunay(xd).simplices
            cupy.cuda.runtime.deviceSynchronize()
            return out

        calls = {"gdel2d": gdel2d, **calls}
    if backend in triangulators.DEVICE_BACKENDS:
        calls.update(device_parts(jax.numpy.asarray(x, jax.numpy.float32), backend))
    out = {}
    for name, fn in calls.items():
        fn()
        out[name] = summary([timed(fn) for _ in range(repeat)])
    profiled = list(calls)[-1]
    profile = cProfile.Profile()
    profile.enable()
    jax.block_until_ready(calls[profiled]())
    profile.disable()
    text = io.StringIO()
    pstats.Stats(profile, stream=text).sort_stats("cumulative").print_stats(18)
    print(f"== cProfile of one {profiled}, n = {len(x)}, {backend}\n{text.getvalue()}", flush=True)
    return out


def device_parts(xj, backend: str) -> dict:
    """The steps of `planar_graph_on_device` from the device positions `xj`, one call each, and
    the whole: the backend's padded triangles, `planar_summary` (check, adjacency, degrees: one
    sort), the fan walk and tiers (`_planar_rows`), the rows cut to the walkers; and the edge
    sort both ways (`_device_check`: one sort with two keys, the CPU's choice, against two radix
    passes, the GPU's)."""
    n = xj.shape[0]
    m = bucket_walkers(n)
    triangles, flat = triangulators.device_triangles(xj, 2 * m, m, backend)
    padded, n_walkers = _pad_walkers(xj, m), jax.numpy.asarray(n, jax.numpy.int32)
    (counts, _), adjacency = planar_summary(padded, triangles, flat, n_walkers)
    k_cap = bucket_neighbors(int(counts[2]))
    rows = _planar_rows(padded, triangles, adjacency, None, n_walkers, k_cap=k_cap)
    a, b = jax.numpy.roll(triangles, -1, axis=1).ravel(), jax.numpy.roll(triangles, -2, axis=1).ravel()
    lo, hi = jax.numpy.minimum(a, b), jax.numpy.maximum(a, b)
    one_sort, two_passes = jax.jit(sort_by_two_keys), jax.jit(sort_in_two_radix_passes)
    return {
        "edge_sort_two_keys": lambda: one_sort(lo, hi)[2],
        "edge_sort_two_radix_passes": lambda: two_passes(lo, hi)[2],
        "device_triangles": lambda: triangulators.device_triangles(xj, 2 * m, m, backend)[0],
        "planar_summary": lambda: planar_summary(padded, triangles, flat, n_walkers)[1],
        "planar_rows": lambda: _planar_rows(padded, triangles, adjacency, None, n_walkers, k_cap=k_cap)[0],
        "cut_to_walkers": lambda: _cut_to_walkers(xj, triangles, None, *rows, s_cap=2 * n).neighbors,
        "planar_graph_on_device": lambda: planar_graph_on_device(xj, None, None, backend)[0].neighbors,
    }


def safe_row(n: int, backend: str, args) -> dict:
    out = {"n": n, "triangulator": backend}
    try:
        out.update(row(n, backend, args.steps, args.repeat))
        if n in args.parts and backend in args.parts_triangulators:
            x = np.random.default_rng(1).uniform(-5.12, 5.12, (n, 2))
            out["parts"] = parts(x, backend, args.repeat, args.stand_in)
    except Exception as err:  # noqa: BLE001 - a bench run records a failing backend and goes on
        out["error"] = f"{type(err).__name__}: {err}"[:2000]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--triangulators", nargs="+", default=["cupy", "cdt"])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--parts", type=int, nargs="*", default=[], help="sizes at which to break one rebuild into its parts"
    )
    parser.add_argument("--parts-triangulators", nargs="+", default=["cupy"])
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "gpu_step.json")
    parser.add_argument(
        "--stand-in",
        action="store_true",
        help="scipy and numpy in place of gDel2D and CuPy: a dry run of the device path on a CPU",
    )
    args = parser.parse_args()
    if args.stand_in:
        from scipy.spatial import Delaunay

        triangulators.DEVICE_BACKENDS["cupy"] = lambda: (Delaunay, np)
        triangulators.installed = lambda name: True
    rows, device = [], jax.devices()[0]
    for n in args.sizes:
        for backend in args.triangulators:  # side by side, size by size
            rows.append(safe_row(n, backend, args))
            print(json.dumps(rows[-1]), flush=True)
            args.out.write_text(
                json.dumps(
                    {
                        "rows": rows,
                        "device": f"{device.platform}: {device.device_kind}",
                        "jax": jax.__version__,
                        "machine": platform.machine(),
                        "cpus": os.cpu_count(),
                        "date": time.strftime("%Y-%m-%d"),
                        "stand_in": args.stand_in,
                    },
                    indent=1,
                )
            )


if __name__ == "__main__":
    main()
