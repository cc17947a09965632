"""The scutoids of one step and the Voronoi facets, against one `delaunay` call on the same walkers.

Run: python bench/scutoids.py [--sizes 10000 100000] [--repeat 7] [--out bench/results/scutoids.json]

2D, float32, uniform walkers moved by a tenth of their spacing (with 2% clones) between the two
graphs, side by side in one process, interleaved, warm (compiled) calls, median (min, max):

- `delaunay(x)` (the default triangulator);
- `scutoids(before, after, parents)` with the volumes passed in (what `simulate`'s scutoid
  observables compute: the classification), and without them (each graph's volumes computed);
- `voronoi_facets(before)` (an analysis kernel, not in a step: O(N K^2) in 2D).

Target (issue 48): the classification at N = 1e5 costs at most 0.2 of one `delaunay` call.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import numpy as np
from _timing import summary, timed

import jaxgeom


def row(n: int, repeat: int) -> dict:
    rng = np.random.default_rng(0)
    x0 = rng.random((n, 2)).astype(np.float32)
    spacing = 1.0 / np.sqrt(n)
    x1 = x0 + (0.1 * spacing * rng.standard_normal((n, 2))).astype(np.float32)
    parents = np.arange(n, dtype=np.int32)
    clones = rng.choice(n, n // 50, replace=False)
    parents[clones] = rng.integers(0, n, clones.size)
    x1[clones] = x0[parents[clones]] + (1e-3 * spacing * rng.standard_normal((clones.size, 2))).astype(np.float32)
    before, after = jaxgeom.delaunay(x0), jaxgeom.delaunay(x1)
    vb, va = jaxgeom.voronoi_volumes(before), jaxgeom.voronoi_volumes(after)
    cases = {
        "delaunay": lambda: jaxgeom.delaunay(x1).neighbors,
        "scutoids_with_volumes": lambda: (
            jaxgeom.scutoids(before, after, parents, volumes_before=vb, volumes_after=va).kind
        ),
        "scutoids": lambda: jaxgeom.scutoids(before, after, parents).kind,
        "voronoi_facets": lambda: jaxgeom.voronoi_facets(before).areas,
    }
    for fn in cases.values():  # compile
        timed(fn)
    times = {name: [] for name in cases}
    for _ in range(repeat):
        for name, fn in cases.items():
            times[name].append(timed(fn))
    s = jaxgeom.scutoids(before, after, parents)
    out = {
        "n": n,
        "seconds": {name: summary(t) for name, t in times.items()},
        "fractions_prism_simple_complex": np.asarray(s.fractions()).tolist(),
    }
    base = np.median(times["delaunay"])
    out["over_delaunay"] = {name: float(np.median(t) / base) for name, t in times.items() if name != "delaunay"}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "scutoids.json")
    args = parser.parse_args()
    rows = []
    for n in args.sizes:
        rows.append(row(n, args.repeat))
        print(json.dumps(rows[-1], indent=1))
    args.out.write_text(
        json.dumps(
            {
                "rows": rows,
                "jax": jax.__version__,
                "device": str(jax.devices()[0]),
                "machine": platform.machine(),
                "cpus": __import__("os").cpu_count(),
                "date": time.strftime("%Y-%m-%d"),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
