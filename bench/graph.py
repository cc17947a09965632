"""Graph proxies: timings against the tessellation, and geodesic convergence tables.

Run: python bench/graph.py [--n 100000] [--out bench/results/graph.json]
Timings (2D, N = --n, one run): jaxgeom.delaunay, spectral_gap (scipy), single-source
geodesics by Dijkstra (host) and Bellman-Ford (jitted, warm). Targets: spectral gap
<= 2x and Dijkstra <= 0.5x the tessellation time.

Convergence (uniform walkers in the coordinate disk |x| < 0.5, source at the walker
nearest the centre, targets with |x| > 0.3): graph distance over straight-line
distance (flat), and over great-circle distance for the unit sphere in
stereographic coordinates g = 4 / (1 + |x|^2)^2 I. Shortest paths on a random
Delaunay graph are longer than geodesics by a stretch factor that tends to a
constant > 1, so the sphere error is also reported after dividing by the flat
stretch measured at the same N.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxgeom

jax.config.update("jax_enable_x64", True)


def sphere(x):
    return 4.0 / (1.0 + jnp.sum(x * x)) ** 2 * jnp.eye(2)


def to_sphere(x):
    sq = np.sum(x * x, axis=-1, keepdims=True)
    return np.concatenate([2 * x, sq - 1], axis=-1) / (1 + sq)


def timed(fn, repeat=3):
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(repeat):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best


def timings(n: int, seed: int) -> dict:
    x = np.random.default_rng(seed).random((n, 2))
    row = {"dim": 2, "n": n, "delaunay_s": timed(lambda: jaxgeom.delaunay(x), repeat=2)}
    tess = jaxgeom.delaunay(x)
    row["spectral_gap_scipy_s"] = timed(lambda: jaxgeom.spectral_gap(tess, k=6), repeat=2)
    row["geodesic_dijkstra_s"] = timed(lambda: jaxgeom.geodesic_distances(tess, 0))
    row["geodesic_bellman_ford_s"] = timed(lambda: jaxgeom.geodesic_distances(tess, 0, method="bellman_ford"))
    row["spectral_gap_over_delaunay"] = row["spectral_gap_scipy_s"] / row["delaunay_s"]
    row["dijkstra_over_delaunay"] = row["geodesic_dijkstra_s"] / row["delaunay_s"]
    print(json.dumps(row))
    return row


def convergence(sizes, seed: int) -> list:
    rows = []
    for n in sizes:
        rng = np.random.default_rng(seed + n)
        x = rng.uniform(-0.5, 0.5, (3 * n, 2))
        x = x[np.linalg.norm(x, axis=1) < 0.5][:n]
        tess = jaxgeom.delaunay(x)
        src = int(np.argmin(np.linalg.norm(x, axis=1)))
        far = np.linalg.norm(x, axis=1) > 0.3
        flat = np.asarray(jaxgeom.geodesic_distances(tess, src))[0][far]
        straight = np.linalg.norm(x[far] - x[src], axis=1)
        curved = np.asarray(jaxgeom.geodesic_distances(tess, src, metric=sphere))[0][far]
        great = np.arccos(np.clip(to_sphere(x[far]) @ to_sphere(x[src]), -1, 1))
        stretch = float(np.median(flat / straight))
        rows.append({"n": n, "flat_ratio_median": stretch, "flat_ratio_min": float(np.min(flat / straight)),
                     "flat_ratio_max": float(np.max(flat / straight)),
                     "sphere_rel_error_median": float(np.median(np.abs(curved / great - 1))),
                     "sphere_rel_error_after_stretch_median": float(np.median(np.abs(curved / (stretch * great) - 1)))})
        print(json.dumps(rows[-1]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 3000, 10_000, 30_000, 100_000])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "graph.json")
    args = parser.parse_args()
    result = {"meta": {"machine": platform.machine(), "jax": jax.__version__, "dtype": "float64",
                       "targets": {"spectral_gap_over_delaunay": "<= 2", "dijkstra_over_delaunay": "<= 0.5"}},
              "timings": timings(args.n, args.seed), "geodesic_convergence": convergence(args.sizes, args.seed)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
