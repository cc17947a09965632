"""Issue 62's moonshot: 3D periodic `delaunay` + `voronoi_facets` at N = 1e6 against freud's
periodic Voronoi, each in its own child process so that each one's peak memory (max RSS) is its
own. Float32 walkers, uniform in the unit cube; two calls each, the second (warm) reported.
Target: within 2x freud, under 8 GB. Writes bench/results/cells_3d_moonshot.json (Qhull) or,
with `--triangulator shull` (the `gpl` extra), cells_3d_moonshot_shull.json.

Run alone (2 cores; ~4 minutes at 1e6):
    .venv/bin/python bench/cells_3d_moonshot.py [--n 1000000] [--triangulator shull]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def child(kind: str, n: int, triangulator: str) -> dict:
    x = np.random.default_rng(n).random((n, 3))
    seconds = []
    if kind == "freud":
        import freud

        box = freud.box.Box.cube(1.0)
        for _ in range(2):
            start = time.perf_counter()
            voro = freud.locality.Voronoi()
            voro.compute((box, x - 0.5))
            _ = voro.volumes, voro.nlist.weights
            seconds.append(time.perf_counter() - start)
        parts = {}
    else:
        import jax

        import jaxgeom

        xd = np.minimum(x.astype(np.float32), np.float32(0.99999994))
        graph = []
        for _ in range(2):
            start = time.perf_counter()
            tess = jaxgeom.delaunay(xd, box=(0.0, 1.0), periodic=True, triangulator=triangulator)
            jax.block_until_ready(tess.neighbors)
            graph.append(time.perf_counter() - start)
            jax.block_until_ready(jaxgeom.voronoi_facets(tess).areas)
            seconds.append(time.perf_counter() - start)
        parts = {"delaunay_seconds": graph[-1], "triangulator": triangulator}
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB -> GiB (Linux)
    return {"kind": kind, "n": n, "seconds": seconds[-1], "first_call_seconds": seconds[0], "peak_gib": peak, **parts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000)
    parser.add_argument("--triangulator", choices=["qhull", "shull"], default="qhull")
    parser.add_argument("--child", choices=["freud", "jaxgeom"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.n, args.triangulator)), flush=True)
        return
    rows = {}
    for kind in ("freud", "jaxgeom"):
        out = subprocess.run(
            [sys.executable, __file__, "--child", kind, "--n", str(args.n), "--triangulator", args.triangulator],
            capture_output=True,
            text=True,
            check=True,
        )
        rows[kind] = json.loads([line for line in out.stdout.splitlines() if line.startswith("{")][-1])
        print(json.dumps(rows[kind]), flush=True)
    result = {
        "rows": rows,
        "over_freud": rows["jaxgeom"]["seconds"] / rows["freud"]["seconds"],
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(f"jaxgeom / freud: {result['over_freud']:.2f}x")
    name = "cells_3d_moonshot.json" if args.triangulator == "qhull" else f"cells_3d_moonshot_{args.triangulator}.json"
    out = Path(__file__).parent / "results" / name
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
