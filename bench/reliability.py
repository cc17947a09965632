"""Cost of the degenerate inputs of issue 12, each in a fresh process (peak memory is per process).

- a walker ringed by R others (R = 30 ... 1000): 2D `delaunay` wall time (with compilation,
  as a rebuild with a new capacity bucket pays it) and peak resident memory;
- periodic square and cubic lattices: `delaunay(..., periodic=True)` time, volume sum.

Writes bench/results/reliability.json. Run alone: `python bench/reliability.py`.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

RING = """
import resource, time, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jaxgeom
n = {n}
t = np.linspace(0, 2 * np.pi, n, endpoint=False)
x = np.vstack([np.c_[np.cos(t), np.sin(t)], [[0.0, 0.0]]])
start = time.perf_counter()
tess = jaxgeom.delaunay(x)
tess.neighbors.block_until_ready()
print(time.perf_counter() - start, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3, int(tess.degree[n]))
"""

LATTICE = """
import time, numpy as np, jax
jax.config.update("jax_enable_x64", True)
import jaxgeom
d, m = {d}, {m}
x = np.stack(np.meshgrid(*[np.arange(float(m))] * d, indexing="ij"), -1).reshape(-1, d)
start = time.perf_counter()
tess = jaxgeom.delaunay(x, box=(0.0, float(m)), periodic=True)
vol = np.asarray(jaxgeom.voronoi_volumes(tess))
degrees = sorted(set(np.asarray(tess.degree).tolist()))
print(time.perf_counter() - start, float(vol.sum()), float(abs(vol - 1).max()), degrees)
"""


def run(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.split(maxsplit=3)


def main() -> None:
    rings = []
    for n in (30, 60, 200, 1000):
        seconds, rss_mb, degree = run(RING.format(n=n))
        rings.append(
            {
                "ring": n,
                "seconds_with_compilation": float(seconds),
                "peak_rss_mb": float(rss_mb),
                "hub_degree": int(degree),
            }
        )
        print(rings[-1])
    lattices = []
    for d, m in ((2, 30), (3, 10)):
        seconds, total, worst, degrees = run(LATTICE.format(d=d, m=m))
        lattices.append(
            {
                "dim": d,
                "side": m,
                "seconds_with_compilation": float(seconds),
                "volume_sum": float(total),
                "max_cell_error": float(worst),
                "degrees": json.loads(degrees),
            }
        )
        print(lattices[-1])
    out = Path(__file__).parent / "results" / "reliability.json"
    out.write_text(
        json.dumps(
            {
                "ring_plus_hub_2d": rings,
                "periodic_lattices": lattices,
                "note": "targets: a 1000-ring in < 2 s and < 500 MB; lattices exact",
            },
            indent=1,
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
