"""Graph proxies: timings against the tessellation, and geodesic convergence tables.

Run: python bench/graph.py [--n 100000] [--out bench/results/graph.json]
Timings (2D, N = --n, uniform in the unit square; medians of --repeat runs): jaxgeom.delaunay,
spectral_gap (scipy), single-source graph distances by Dijkstra (host) and Bellman-Ford
(jitted, warm), and heat-method distances (solver "direct"): the first call (three sparse LU
factorisations and the compilation), then with the factorisations cached, 1 source and 100
sources. Targets: spectral gap <= 2x, Dijkstra <= 0.5x, heat 1 source <= 1x and 100 sources
<= 3x the tessellation time.

Convergence (uniform walkers in the coordinate ball |x| < 0.5; 4 sources inside, |x| < 0.25;
errors over tier-2 walkers): median relative error of the heat method (default t, and the
fixed t = h^2 for comparison) and of Dijkstra's graph distance, against the straight-line
distance (flat, 2D and 3D) and the great-circle distance for the unit sphere in
stereographic coordinates g = 4 / (1 + |x|^2)^2 I (2D). Shortest paths on a random
Delaunay graph are longer than geodesics by a stretch factor that tends to a constant > 1:
Dijkstra's error plateaus, the heat method's shrinks.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import jaxgeom

jax.config.update("jax_enable_x64", True)


def sphere(x):
    return 4.0 / (1.0 + jnp.sum(x * x)) ** 2 * jnp.eye(2)


def to_sphere(x):
    sq = np.sum(x * x, axis=-1, keepdims=True)
    return np.concatenate([2 * x, sq - 1], axis=-1) / (1 + sq)


def timed(fn, repeat=3):
    """Median and spread (min, max) of `repeat` warm runs, in seconds."""
    jax.block_until_ready(fn())
    runs = []
    for _ in range(repeat):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - start)
    return float(np.median(runs)), [float(min(runs)), float(max(runs))]


def timings(n: int, seed: int, repeat: int) -> dict:
    x = np.random.default_rng(seed).random((n, 2))
    row = {"dim": 2, "n": n}
    row["delaunay_s"], row["delaunay_spread_s"] = timed(lambda: jaxgeom.delaunay(x), repeat)
    tess = jaxgeom.delaunay(x)
    row["spectral_gap_scipy_s"], _ = timed(lambda: jaxgeom.spectral_gap(tess, k=6), repeat)
    row["geodesic_dijkstra_s"], _ = timed(lambda: jaxgeom.geodesic_distances(tess, 0, method="dijkstra"), repeat)
    row["geodesic_bellman_ford_s"], _ = timed(
        lambda: jaxgeom.geodesic_distances(tess, 0, method="bellman_ford"), repeat
    )
    start = time.perf_counter()
    jax.block_until_ready(jaxgeom.geodesic_distances(tess, 1, solver="direct"))
    row["heat_first_call_s"] = time.perf_counter() - start  # factorisations + compilation
    sources = np.random.default_rng(seed + 1).choice(n, 100, replace=False)
    row["heat_1_source_s"], row["heat_1_source_spread_s"] = timed(
        lambda: jaxgeom.geodesic_distances(tess, 2, solver="direct"), repeat
    )
    row["heat_100_sources_s"], row["heat_100_sources_spread_s"] = timed(
        lambda: jaxgeom.geodesic_distances(tess, sources, solver="direct"), repeat
    )
    for key in ("spectral_gap_scipy", "geodesic_dijkstra", "heat_1_source", "heat_100_sources"):
        row[f"{key}_over_delaunay"] = row[f"{key}_s"] / row["delaunay_s"]
    print(json.dumps(row), flush=True)
    return row


def ball(n: int, d: int, seed: int) -> np.ndarray:
    x = np.random.default_rng(seed).uniform(-0.5, 0.5, (4 * n, d))
    return x[np.linalg.norm(x, axis=1) < 0.5][:n]


def median_error(tess, dist, true) -> float:
    sel = np.asarray(tess.interior)[None] & (true > 0)
    return float(np.median(np.abs(dist[sel] / true[sel] - 1)))


def convergence_row(case: str, n: int, seed: int, fixed_t_up_to: int) -> dict:
    d = 3 if case == "flat_3d" else 2
    x = ball(n, d, seed + n)
    tess = jaxgeom.delaunay(x)
    sources = np.flatnonzero(np.linalg.norm(x, axis=1) < 0.25)[:4]
    metric = sphere if case == "sphere_2d" else None
    if metric is None:
        true = np.linalg.norm(x[None] - x[sources][:, None], axis=-1)
    else:
        s = to_sphere(x)
        true = np.arccos(np.clip(s[sources] @ s.T, -1.0, 1.0))
    start = time.perf_counter()
    heat = np.asarray(jaxgeom.geodesic_distances(tess, sources, metric, solver="direct"))
    row = {
        "case": case,
        "n": n,
        "heat_median_rel_error": median_error(tess, heat, true),
        "heat_s": time.perf_counter() - start,
    }
    graph = np.asarray(jaxgeom.geodesic_distances(tess, sources, metric, method="dijkstra"))
    row["dijkstra_median_rel_error"] = median_error(tess, graph, true)
    sel = np.asarray(tess.interior)[None] & (true > 0)
    row["dijkstra_median_ratio"] = float(np.median(graph[sel] / true[sel]))
    if n <= fixed_t_up_to:  # the first proposal, t = h^2 (h: mean metric simplex edge)
        h = float(np.mean(np.asarray(jaxgeom.edge_lengths(tess, metric=metric))[np.asarray(tess.neighbor_mask)]))
        fixed = np.asarray(jaxgeom.geodesic_distances(tess, sources, metric, t=h * h, solver="direct"))
        row["heat_fixed_t_h2_median_rel_error"] = median_error(tess, fixed, true)
    tqdm.write(json.dumps(row))
    return row


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 3000, 10_000, 30_000, 100_000])
    parser.add_argument("--cases", nargs="+", default=["flat_2d", "sphere_2d", "flat_3d"])
    parser.add_argument("--fixed-t-up-to", type=int, default=30_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "graph.json")
    args = parser.parse_args()
    result = {
        "meta": {
            "machine": platform.machine(),
            "cores": os.cpu_count(),
            "jax": jax.__version__,
            "dtype": "float64",
            "targets": {
                "spectral_gap_over_delaunay": "<= 2",
                "dijkstra_over_delaunay": "<= 0.5",
                "heat_1_source_over_delaunay": "<= 1",
                "heat_100_sources_over_delaunay": "<= 3",
                "heat_median_rel_error_at_1e5": "flat_2d <= 0.01, flat_3d <= 0.02",
            },
        },
        "timings": timings(args.n, args.seed, args.repeat),
        "geodesic_convergence": [
            convergence_row(case, n, args.seed, args.fixed_t_up_to)
            for case, n in tqdm(
                [(c, n) for c in args.cases for n in args.sizes], desc="geodesic convergence", disable=None
            )
        ],
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
