"""A recorded trajectory analysed by `analyze_trajectory`, against its parts alone.

Run: python bench/trajectory.py [--n 10000] [--frames 200] [--repeat 3] [--memory]
                                [--out bench/results/trajectory.json]

N walkers, T frames of a random walk (steps of a tenth of the spacing, 2% of the walkers
cloned onto another each frame) in the unit box, written to an H5MD file on disk (positions,
and clone parents), float32, side by side in one process, interleaved, warm (compiled), median
(min, max) over the repeats:

- `delaunay`: `jaxgeom.delaunay(x)` on every frame, from memory, its graph ready;
- `kernels`: the observables of every frame on graphs built beforehand (the same jitted
  program `analyze_trajectory` runs: volumes, shape, expansion, scutoids, and with a landscape
  the fitness and the Regge curvature in its Hessian metric), from memory;
- `analyze_trajectory`: the whole run from the file (reading, triangulating, observing).

Cases: 2D without a landscape (target, issue 64: analyze_trajectory at most 1.3x delaunay);
2D and 3D with a landscape (target: at most 1.1x delaunay + kernels).

--memory: the peak resident memory of `analyze_trajectory` (2D, no landscape) on T = 100 and
T = 1000 frames of the same N, each in a fresh process (target: within 10%).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary

import jaxgeom
from jaxgeom.swarm._observables import prepare_scutoid_trace
from jaxgeom.swarm._trajectory import _default_observe, _determined, _first_state, _graph, _observe_frame

DTYPE = np.float32


def landscape(x):
    return jnp.sum(x**2 - 0.1 * jnp.cos(8.0 * jnp.pi * x))


def write_frames(path: Path, n: int, d: int, frames: int, seed: int = 0) -> np.ndarray:
    """The random walk with clones, written to `path` (H5MD); returns the positions (T, N, d)."""
    rng = np.random.default_rng(seed)
    spacing = n ** (-1.0 / d)
    x = rng.uniform(0.1, 0.9, (n, d))
    out = np.empty((frames, n, d), DTYPE)
    with jaxgeom.H5MDWriter(path, n, d, elements=("position", "parents")) as h5:
        for t in range(frames):
            parents = np.arange(n, dtype=np.int32)
            if t:
                clones = rng.choice(n, n // 50, replace=False)
                parents[clones] = rng.integers(0, n, clones.size)
                x = x[parents] + 0.1 * spacing * rng.standard_normal((n, d))
                x[clones] += 1e-3 * spacing * rng.standard_normal((clones.size, d))
                x = np.clip(x, 0.0, 1.0)
            out[t] = x
            h5.append(t, 0.01 * t, position=x.astype(DTYPE), parents=parents)
    return out


def delaunay_alone(frames: np.ndarray) -> float:
    start = time.perf_counter()
    for x in frames:
        jax.block_until_ready(jaxgeom.delaunay(x).neighbors)
    return time.perf_counter() - start


def prebuilt(frames: np.ndarray):
    """Every frame's graph at one capacity bucket, as analyze_trajectory keeps them."""
    graphs, capacity = [], None
    for x in frames:
        tess, capacity, grew = _graph(x, "delaunay", 12, None, False, "auto", capacity)
        if grew:  # one bucket for all: rebuild the earlier frames at the grown capacity
            graphs = [_graph(y, "delaunay", 12, None, False, "auto", capacity)[0] for y in frames[: len(graphs)]]
        graphs.append(tess)
    return graphs


def kernels_alone(frames, graphs, parents, fn, observe) -> float:
    """The observables of every frame on its prebuilt graph: analyze_trajectory's loop without
    the reading and the triangulation."""
    n, params = frames.shape[1], jaxgeom.SwarmParams()
    state = prepare_scutoid_trace(_first_state(frames[0], graphs[0], DTYPE), observe)
    start, out = time.perf_counter(), []
    for t, (x, tess) in enumerate(zip(frames, graphs, strict=True)):
        xj = jnp.asarray(x)
        state = eqx.tree_at(lambda s: s.tess, state, eqx.tree_at(lambda g: g.points, tess, xj))
        values = None if fn is not None else jnp.zeros(n, DTYPE)  # a landscape is evaluated in the program
        state, obs = _observe_frame(
            fn,
            params,
            state,
            (xj, jnp.zeros_like(xj), values, jnp.asarray(parents[t])),
            jnp.asarray(t, jnp.int32),
            jnp.asarray(0.01, DTYPE),
            observe,
        )
        out.append(obs)
    jax.block_until_ready(out)
    return time.perf_counter() - start


def case(name: str, d: int, fn, n: int, n_frames: int, repeat: int, folder: Path) -> dict:
    path = folder / f"{name}.h5md"
    frames = write_frames(path, n, d, n_frames)
    with jaxgeom.H5MDTrajectory(path) as h5:
        parents = np.stack([h5.frame(t)["parents"] for t in range(n_frames)])
    observe = _default_observe(
        _determined({"parents", "fitness"} if fn else {"parents"}, fn, jaxgeom.SwarmParams(), "delaunay")
    )
    graphs = prebuilt(frames)

    def analyze():
        start = time.perf_counter()
        h = jaxgeom.analyze_trajectory(path, landscape=fn, dtype=DTYPE, observe=observe)
        return time.perf_counter() - start, h

    # warm: compile every program once
    jaxgeom.analyze_trajectory(path, landscape=fn, dtype=DTYPE, observe=observe, stop=3)
    kernels_alone(frames[:3], graphs[:3], parents, fn, observe)
    delaunay_alone(frames[:3])
    times = {"delaunay": [], "kernels": [], "analyze_trajectory": []}
    parts = {"reading_and_graphs": [], "observables": []}
    for _ in range(repeat):
        times["delaunay"].append(delaunay_alone(frames))
        times["kernels"].append(kernels_alone(frames, graphs, parents, fn, observe))
        seconds, h = analyze()
        times["analyze_trajectory"].append(seconds)
        parts["reading_and_graphs"].append(float(h["seconds_rebuild"]))
        parts["observables"].append(float(h["seconds_steps"]))
    med = {k: float(np.median(v)) for k, v in times.items()}
    out = {
        "case": name,
        "d": d,
        "landscape": fn is not None,
        "n": n,
        "frames": n_frames,
        "observe": list(observe),
        "seconds": {k: summary(v) for k, v in times.items()},
        "analyze_trajectory_parts": {k: summary(v) for k, v in parts.items()},
        "over_delaunay": med["analyze_trajectory"] / med["delaunay"],
        "over_delaunay_plus_kernels": med["analyze_trajectory"] / (med["delaunay"] + med["kernels"]),
        "per_frame_ms": {k: 1e3 * v / n_frames for k, v in med.items()},
    }
    print(json.dumps(out, indent=1), flush=True)
    return out


def peak_memory(n: int, n_frames: int, folder: Path) -> dict:
    """Peak resident memory of a fresh process that analyses T frames (2D, no landscape)."""
    path = folder / f"memory_{n_frames}.h5md"
    write_frames(path, n, 2, n_frames, seed=1)
    code = (
        "import resource, sys, time, jaxgeom, numpy as np; t = time.perf_counter(); "
        f"h = jaxgeom.analyze_trajectory({str(path)!r}, dtype=np.float32); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, len(h['frame']), time.perf_counter() - t)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    kib, frames, seconds = done.stdout.split()[-3:]
    return {
        "frames": int(frames),
        "peak_rss_mib": int(kib) / 1024,
        "seconds": float(seconds),
        "file_mib": path.stat().st_size / 2**20,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=10_000)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--cases", nargs="+", default=["2d", "2d_landscape", "3d_landscape"])
    parser.add_argument("--memory", action="store_true", help="also the T = 100 against T = 1000 peak memory")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "trajectory.json")
    args = parser.parse_args()
    specs = {"2d": (2, None), "2d_landscape": (2, landscape), "3d_landscape": (3, landscape)}
    result = {
        "rows": [],
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "date": time.strftime("%Y-%m-%d"),
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases:
            d, fn = specs[name]
            result["rows"].append(case(name, d, fn, args.n, args.frames, args.repeat, Path(tmp)))
        if args.memory:
            small, large = peak_memory(args.n, 100, Path(tmp)), peak_memory(args.n, 1000, Path(tmp))
            result["memory"] = {"T100": small, "T1000": large, "ratio": large["peak_rss_mib"] / small["peak_rss_mib"]}
            print(json.dumps(result["memory"], indent=1), flush=True)
    args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
