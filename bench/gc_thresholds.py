"""Tracing and lowering time under CPython's default collector thresholds (700, 10, 10) and
under the test suite's (tests/conftest.py: 50000, 20, 100), side by side in one run: each
round starts one fresh process per setting, in alternating order.

Run: python bench/gc_thresholds.py [--rounds 5] [--out bench/results/gc_thresholds.json]

The program: the gradient of a `simulation_loss` in nu and T (2D, 120 walkers, 12 steps,
`weights="metric_full"`, cloning on, `rebuild="device"`: a large traced program, ~37k
equations), float64. Measured: CPU seconds of `jax.jit(jax.grad(loss)).lower(theta)` (tracing
and lowering; XLA's compilation is not part of it), median (min, max) over the rounds, and
the peak resident memory of each process.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
from _timing import summary

CHILD = r"""
import gc, resource, sys, time
if sys.argv[1] == "suite":
    gc.set_threshold(50_000, 20, 100)
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
import jaxgeom
V = lambda x: jnp.sum(x**2 - 2.0 * jnp.cos(3.0 * x))
state = jaxgeom.init_swarm(V, np.random.default_rng(0).uniform(-3, 3, (120, 2)), key=0)
params = jaxgeom.SwarmParams(dt=0.02, temperature=0.3, gamma=1.0, nu=0.3, weights="metric_full", clone_rate=0.5)
loss = jaxgeom.simulation_loss(V, state, "mean_fitness", n_steps=12, params=params, tuned=("nu", "temperature"),
                               rebuild="device")
theta = loss.to_theta()
start = time.process_time()
jax.jit(jax.grad(loss)).lower(theta)
print(time.process_time() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, gc.get_threshold())
"""


def run(setting: str) -> tuple[float, float]:
    out = subprocess.run([sys.executable, "-c", CHILD, setting], capture_output=True, text=True, check=True)
    seconds, megabytes = out.stdout.split()[:2]
    return float(seconds), float(megabytes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "gc_thresholds.json")
    args = parser.parse_args()
    settings = ("default", "suite")
    seconds = {s: [] for s in settings}
    memory = {s: [] for s in settings}
    for r in range(args.rounds):
        for s in settings if r % 2 == 0 else settings[::-1]:
            t, m = run(s)
            seconds[s].append(t)
            memory[s].append(m)
            print(f"round {r}: {s:8s} {t:6.2f} s CPU, peak {m:.0f} MB", flush=True)
    result = {
        "what": "CPU seconds of tracing + lowering jax.grad(simulation_loss) (rebuild='device'), fresh process each",
        "thresholds": {"default": [700, 10, 10], "suite": [50000, 20, 100]},
        "seconds": {s: summary(v) for s, v in seconds.items()},
        "peak_rss_mb": {s: summary(v) for s, v in memory.items()},
        "ratio_suite_over_default": float(np.median(seconds["suite"]) / np.median(seconds["default"])),
        "rounds": args.rounds,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
        "jax": __import__("jax").__version__,
    }
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["seconds"], indent=2), "ratio", round(result["ratio_suite_over_default"], 3))


if __name__ == "__main__":
    main()
