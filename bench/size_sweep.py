"""`jaxgeom.delaunay` over a sweep of swarm sizes, with the host build's jitted steps compiled
once per bucket of walker counts (`bucket_walkers`, the library's behaviour) and once per N
(the walkers unpadded), side by side in one run: each round starts one fresh process per
setting, in alternating order, without JAX's persistent compilation cache.

Run: python bench/size_sweep.py [--rounds 3] [--out bench/results/size_sweep.json]

The sweep: N = 1000, 1025, ..., 1500 (21 sizes) uniform in the unit square or cube, Qhull,
float64, XLA's default settings. Measured: wall seconds of the first pass over the sizes
(compilation included) and of a second pass (programs compiled), median (min, max) over the
rounds; the graphs are the same in both settings (tests/tessellation/test_delaunay.py).
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
import sys, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import jaxgeom
from jaxgeom.tessellation import _delaunay
setting, d = sys.argv[1], int(sys.argv[2])
if setting == "per_n":
    _delaunay.bucket_walkers = lambda n: n
rng = np.random.default_rng(0)
xs = [rng.random((n, d)) for n in range(1000, 1501, 25)]
passes = []
for _ in range(2):
    start = time.perf_counter()
    for x in xs:
        jax.block_until_ready(jaxgeom.delaunay(x, triangulator="qhull").neighbors)
    passes.append(time.perf_counter() - start)
print(*passes)
"""


def run(setting: str, d: int) -> tuple[float, float]:
    env = {**os.environ, "JAX_ENABLE_COMPILATION_CACHE": "false"}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, setting, str(d)], capture_output=True, text=True, check=True, env=env
    )
    first, second = out.stdout.split()[:2]
    return float(first), float(second)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "size_sweep.json")
    args = parser.parse_args()
    settings = ("bucketed", "per_n")
    result = {
        "what": "wall seconds of jaxgeom.delaunay over N = 1000, 1025, ..., 1500 (Qhull, float64), "
        "first pass (compiling) and second pass; fresh process each, no persistent cache",
        "rounds": args.rounds,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        "python": platform.python_version(),
        "jax": __import__("jax").__version__,
    }
    for d in (2, 3):
        first = {s: [] for s in settings}
        second = {s: [] for s in settings}
        for r in range(args.rounds):
            for s in settings if r % 2 == 0 else settings[::-1]:
                a, b = run(s, d)
                first[s].append(a)
                second[s].append(b)
                print(f"{d}D round {r}: {s:8s} first pass {a:6.2f} s, second {b:5.2f} s", flush=True)
        result[f"{d}d"] = {
            "first_pass_s": {s: summary(v) for s, v in first.items()},
            "second_pass_s": {s: summary(v) for s, v in second.items()},
            "first_pass_ratio_per_n_over_bucketed": float(np.median(first["per_n"]) / np.median(first["bucketed"])),
        }
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k in ("2d", "3d")}, indent=2))


if __name__ == "__main__":
    main()
