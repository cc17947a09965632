"""Ollivier-Ricci curvature (issue 34): speed against GraphRicciCurvature, and convergence of the
ORC scalar estimate on the round sphere and hyperbolic space.

Run:
  python bench/ollivier.py speed [--out bench/results/ollivier_speed.json]
  python bench/ollivier.py convergence [--sizes 1000,10000] [--dims 2,3,4,6]
      [--out bench/results/ollivier_convergence.json]
  python bench/ollivier.py table   (the convergence JSON as the markdown table of bench/README.md)
  python bench/ollivier.py batch [--batches 512,4096,32768,131072] [--out ...]

speed: uniform points in the unit square, N = 1e4, k = 10 (the undirected k-NN graph), in one
process: GraphRicciCurvature 0.6 (its defaults: OTD = exact transport with POT, all-pairs
shortest paths with networkit, proc = --proc, default 2 = this machine's cores) on the unweighted graph against
`ollivier_ricci(cost="hops")` (the same definition; per-edge max difference reported), and
GRC on the Euclidean-weighted graph against cost="graph", measure="grc"; ours warm, median of 3
(2 for the weighted graph; min, max), float64 and float32. Then N = 1e5, cost="hops", float32: the
first call (with compilation), one warm call and the peak resident memory, in a fresh subprocess.

batch: `ollivier_ricci(cost="hops", batch_size=b)` on the speed graph in float32 for each b: the
first call and the median of 3 warm calls (min, max), and the largest difference from the first b's
curvature (the batch changes only the order of the float32 reductions).

convergence: Riemannian-uniform samples of the unit round sphere S^d (southern hemisphere in
stereographic coordinates, g = 4 / (1 + |u|^2)^2 I, S = d (d - 1)) and of hyperbolic space H^d
(Poincare ball, geodesic ball of radius 2 artanh(0.75), g = 4 / (1 - |u|^2)^2 I,
S = -d (d - 1)); the coordinate metric is given. A flat sample (uniform in the unit ball, no
metric) gives the discreteness bias of kappa at this k, which `table` subtracts in its
flat-corrected column. k-NN graph with k = 10, alpha = 0, uniform
measure, cost "direct" (the metric length of the segment) and, in d = 2, 3, also "graph".
Reported: the mean ORC scalar estimate over the walkers with |u| < 0.5 (away from the sample's
rim), its standard error over those walkers, and the ratio to the closed form; in d = 2, 3 the
Regge region average (`ricci_scalar` on the Delaunay graph of the same points, same metric).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxgeom

REGION = 0.5
HYPERBOLIC_RADIUS = 2 * np.arctanh(0.75)


def sphere_sample(n, d, rng):
    y = rng.standard_normal((n, d + 1))
    y /= np.linalg.norm(y, axis=1, keepdims=True)
    y[:, -1] = -np.abs(y[:, -1])  # southern hemisphere: |u| <= 1
    return y[:, :-1] / (1 - y[:, -1:])


def hyperbolic_sample(n, d, rng):
    r_grid = np.linspace(0, HYPERBOLIC_RADIUS, 20001)
    cdf = np.cumsum(np.sinh(r_grid) ** (d - 1))
    r = np.interp(rng.random(n) * cdf[-1], cdf, r_grid)
    direction = rng.standard_normal((n, d))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return direction * np.tanh(r / 2)[:, None]


def sphere_metric(u):
    return 4.0 / (1.0 + jnp.sum(u * u)) ** 2 * jnp.eye(u.shape[0], dtype=u.dtype)


def hyperbolic_metric(u):
    return 4.0 / (1.0 - jnp.sum(u * u)) ** 2 * jnp.eye(u.shape[0], dtype=u.dtype)


def flat_sample(n, d, rng):
    direction = rng.standard_normal((n, d))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return direction * rng.random((n, 1)) ** (1.0 / d)


SPACES = {
    "sphere": (sphere_sample, sphere_metric, 1.0),
    "hyperbolic": (hyperbolic_sample, hyperbolic_metric, -1.0),
    "flat": (flat_sample, None, 0.0),
}


def region_stats(values, region):
    v = np.asarray(values)[region]
    v = v[np.isfinite(v)]
    return float(v.mean()), float(v.std(ddof=1) / np.sqrt(len(v))), int(len(v))


def convergence_row(space, d, n, k, seed, costs):
    sample, metric, sign = SPACES[space]
    x = sample(n, d, np.random.default_rng(seed))
    region = np.linalg.norm(x, axis=1) < REGION
    exact = sign * d * (d - 1)
    row = {"space": space, "d": d, "n": n, "k": k, "exact": exact, "region_walkers": int(region.sum())}
    tess = jaxgeom.knn_graph(x, k)
    for cost in costs:
        start = time.perf_counter()
        orc = jaxgeom.ollivier_ricci(tess, alpha=0.0, metric=metric, cost=cost)
        mean, se, _ = region_stats(orc.scalar_curvature, region)
        kappa, kappa_se, _ = region_stats(orc.walker_curvature, region)
        row[cost] = {
            "mean": mean,
            "standard_error": se,
            "ratio": mean / exact if exact else float("nan"),
            "mean_kappa": kappa,
            "mean_kappa_standard_error": kappa_se,
            "mean_second_moment": region_stats(orc.second_moment, region)[0],
            "seconds": time.perf_counter() - start,
        }
    if d <= 3:
        dtess = jaxgeom.delaunay(x)
        regge = np.asarray(jaxgeom.ricci_scalar(dtess, metric=metric))
        mean, se, _ = region_stats(regge, region & np.asarray(dtess.interior))
        row["regge"] = {"mean": mean, "standard_error": se, "ratio": mean / exact if exact else float("nan")}
    return row


def convergence(args):
    rows = []
    for d in args.dims:
        for n in args.sizes:
            for space in SPACES:
                costs = ("direct", "graph") if d <= 3 and n <= 3000 else ("direct",)
                row = convergence_row(space, d, n, args.k, seed=d * 1000 + n % 997, costs=costs)
                print(json.dumps(row), flush=True)
                rows.append(row)
    return {"k": args.k, "alpha": 0.0, "measure": "uniform", "region": f"|u| < {REGION}", "rows": rows}


def markdown_table(result):
    """The convergence rows as a markdown table; `flat-corrected` subtracts the flat sample's
    mean kappa at the same d and N (the discreteness bias at this k) before scaling."""
    rows = result["rows"]
    flat = {(r["d"], r["n"]): r["direct"]["mean_kappa"] for r in rows if r["space"] == "flat"}
    lines = [
        "| space | d | N | region walkers | closed form | ORC estimate (direct) +- se | mean kappa +- se | "
        "flat-corrected | ORC estimate (graph) | Regge |",
        "| --- " * 10 + "|",
    ]
    for r in rows:
        o = r["direct"]
        corrected = 2 * r["d"] ** 2 * (o["mean_kappa"] - flat[(r["d"], r["n"])]) / o["mean_second_moment"]
        graph = f"{r['graph']['mean']:.3g}" if "graph" in r else "-"
        regge = f"{r['regge']['mean']:.3g}" if "regge" in r else "-"
        lines.append(
            f"| {r['space']} | {r['d']} | {r['n']:.0e} | {r['region_walkers']} | {r['exact']:g} | "
            f"{o['mean']:.3g} +- {o['standard_error']:.2g} | {o['mean_kappa']:.4f} +- "
            f"{o['mean_kappa_standard_error']:.4f} | {corrected if r['space'] != 'flat' else 0.0:.3g} | "
            f"{graph} | {regge} |"
        )
    return "\n".join(lines)


def grc_curvature(tess, weighted, proc=2):
    import networkx as nx
    from GraphRicciCurvature.OllivierRicci import OllivierRicci

    x, nbrs = np.asarray(tess.points, np.float64), np.asarray(tess.neighbors)
    graph = nx.Graph()
    graph.add_nodes_from(range(len(x)))
    rows, cols = np.nonzero(nbrs < len(x))
    for i, j in zip(rows.tolist(), nbrs[rows, cols].tolist(), strict=True):
        graph.add_edge(i, j, **({"weight": float(np.linalg.norm(x[i] - x[j]))} if weighted else {}))
    start = time.perf_counter()
    orc = OllivierRicci(graph, alpha=0.5, method="OTD", proc=proc, verbose="ERROR")
    orc.compute_ricci_curvature()
    return time.perf_counter() - start, orc.G


def ours_timed(tess, repeats=3, **kwargs):
    """(result, timings): the first call (compilation included) apart, then `repeats` warm calls."""
    runs = []
    for _ in range(1 + repeats):
        start = time.perf_counter()
        orc = jaxgeom.ollivier_ricci(tess, **kwargs)
        jax.block_until_ready(orc.edge_curvature)
        runs.append(time.perf_counter() - start)
    warm = runs[1:]
    return orc, {
        "median_s": float(np.median(warm)),
        "min_s": float(min(warm)),
        "max_s": float(max(warm)),
        "first_s": runs[0],
    }


def max_difference(orc, graph):
    nbrs, kappa = np.asarray(orc.neighbors), np.asarray(orc.edge_curvature)
    rows, cols = np.nonzero(nbrs < len(nbrs))
    ours = kappa[rows, cols]
    theirs = np.array(
        [graph[i][j]["ricciCurvature"] for i, j in zip(rows.tolist(), nbrs[rows, cols].tolist(), strict=True)]
    )
    return float(np.max(np.abs(ours - theirs))), int(len(rows) // 2)


def speed(args):
    x = np.random.default_rng(0).random((10**4, 2))
    out = {"n": 10**4, "k": 10, "configurations": []}
    for label, weighted, repeats, kwargs in (
        ("unweighted, uniform", False, 3, {"cost": "hops"}),
        ("Euclidean-weighted, GRC's e^{-w^2}", True, 2, {"cost": "graph", "measure": "grc"}),
    ):
        grc_s, graph = grc_curvature(jaxgeom.knn_graph(x, 10), weighted, proc=args.proc)
        entry = {"graph": label, "grc_seconds": grc_s, "ours": {}}
        for dtype in ("float64", "float32"):
            jax.config.update("jax_enable_x64", dtype == "float64")
            tess = jaxgeom.knn_graph(x.astype(dtype), 10)
            orc, timing = ours_timed(tess, repeats=repeats, alpha=0.5, **kwargs)
            diff, edges = max_difference(orc, graph)
            entry["ours"][dtype] = {
                **timing,
                "ratio_grc_over_ours": grc_s / timing["median_s"],
                "max_abs_difference": diff,
                "edges": edges,
            }
        jax.config.update("jax_enable_x64", True)
        print(json.dumps(entry), flush=True)
        out["configurations"].append(entry)
    out["n_1e5"] = [large_run("hops")]
    return out


def batch_sweep(args):
    tess = jaxgeom.knn_graph(np.random.default_rng(0).random((10**4, 2)).astype(np.float32), 10)
    rows, first_kappa = [], None
    for b in args.batches:
        orc, timing = ours_timed(tess, cost="hops", batch_size=b)
        kappa = np.asarray(orc.edge_curvature)
        first_kappa = kappa if first_kappa is None else first_kappa
        rows.append({"batch": b, **timing, "max_diff_vs_first_batch": float(np.nanmax(np.abs(kappa - first_kappa)))})
        print(json.dumps(rows[-1]), flush=True)
    return {"n": 10**4, "k": 10, "dtype": "float32", "cost": "hops", "rows": rows}


def large_run(cost):
    code = (
        "import time, resource, numpy as np, jax, jaxgeom\n"
        "x = np.random.default_rng(1).random((100000, 2)).astype(np.float32)\n"
        "t = jaxgeom.knn_graph(x, 10)\n"
        "s = time.perf_counter(); o = jaxgeom.ollivier_ricci(t, cost=COST); jax.block_until_ready(o.edge_curvature)\n"
        "first = time.perf_counter() - s\n"
        "s = time.perf_counter(); o = jaxgeom.ollivier_ricci(t, cost=COST); jax.block_until_ready(o.edge_curvature)\n"
        "stats = jax.devices()[0].memory_stats() or {}\n"
        "print(first, time.perf_counter() - s, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,"
        " int(o.edge_mask.sum()) // 2,"
        " stats.get('peak_bytes_in_use', -1))\n"
    ).replace("COST", repr(cost))
    first, warm, rss_kb, edges, device_peak = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout.split()
    row = {
        "n": 10**5,
        "k": 10,
        "dtype": "float32",
        "cost": cost,
        "first_call_s": float(first),
        "warm_s": float(warm),
        "peak_rss_mb": int(rss_kb) / 1024,
        "edges": int(edges),
    }
    if int(device_peak) >= 0:  # an accelerator's allocator reports its peak; the CPU's does not
        row["device_peak_mb"] = int(device_peak) / 2**20
    print(json.dumps(row), flush=True)
    return row


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("what", choices=("speed", "convergence", "table", "batch"))
    parser.add_argument("--sizes", default="1000,10000")
    parser.add_argument("--dims", default="2,3,4,6")
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--batches", default="512,4096,32768,131072")
    parser.add_argument("--proc", type=int, default=2, help="GraphRicciCurvature's processes (speed)")
    parser.add_argument("--out")
    args = parser.parse_args()
    args.sizes = [int(v) for v in args.sizes.split(",")]
    args.dims = [int(v) for v in args.dims.split(",")]
    args.batches = [int(v) for v in args.batches.split(",")]
    if args.what == "table":
        print(markdown_table(json.loads(Path(args.out or "bench/results/ollivier_convergence.json").read_text())))
        return
    jax.config.update("jax_enable_x64", args.what != "batch")
    result = {"speed": speed, "convergence": convergence, "batch": batch_sweep}[args.what](args)
    result["machine"] = {
        "cores": os.cpu_count(),
        "grc_processes": args.proc,
        "device": jax.devices()[0].device_kind,
        "jax": jax.__version__,
        "peak_rss_mb_this_process": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    out = Path(args.out or f"bench/results/ollivier_{args.what}.json")
    out.write_text(json.dumps(result, indent=1) + "\n")
    print("wrote", out)


if __name__ == "__main__":
    main()
