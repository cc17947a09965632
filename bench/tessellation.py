"""Tessellation benchmark: bare scipy Delaunay vs jaxgeom.delaunay, jitted volumes, freud;
and the host triangulators side by side.

Run: python bench/tessellation.py [--sizes 10000 100000] [--out bench/results/tessellation.json]
     python bench/tessellation.py --triangulators [--tri-sizes 10000 100000 1000000]
         [--out bench/results/triangulators.json]
All timings of one configuration are taken side by side in this one run (best of
`--repeat`), on the same points: uniform in a box of unit density, so that freud's
absolute duplicate tolerance is never hit. Times are wall seconds, warm (compiled).
`--triangulators`: float32 walkers; per dimension and N, bare `scipy.spatial.Delaunay`
(default options, float64), each backend alone, and `jaxgeom.delaunay(x, triangulator=t)`
for every installed backend (until its arrays are ready), interleaved, median of `--repeat`
runs with min and max; ratios to bare Qhull. Periodic 3D against freud at the largest N.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import numpy as np
from graph import timed  # median and spread of warm runs (bench/graph.py)
from scipy.spatial import Delaunay
from tqdm.auto import tqdm

import jaxgeom

jax.config.update("jax_enable_x64", True)


def best_time(fn, repeat: int) -> tuple[float, object]:
    """Best of `repeat` warm calls (one untimed call first: backend start-up, compilation)."""
    jax.block_until_ready(fn())
    best, out = np.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - start)
    return best, out


def freud_periodic(points: np.ndarray, length: float, repeat: int):
    try:
        import freud
    except ImportError:
        return None
    d = points.shape[1]
    box = freud.box.Box.square(length) if d == 2 else freud.box.Box.cube(length)
    pts3 = np.zeros((len(points), 3), np.float32)
    pts3[:, :d] = points - length / 2

    def run():
        vor = freud.locality.Voronoi()
        vor.compute((box, pts3))
        return vor.volumes, vor.nlist.neighbor_counts

    seconds, (vols, _) = best_time(run, repeat)
    return {"seconds": seconds, "volume_sum_rel_error": float(abs(vols.sum() / length**d - 1))}


def bench_one(d: int, n: int, repeat: int, seed: int) -> dict:
    length = n ** (1.0 / d)
    x = np.random.default_rng(seed).random((n, d)) * length
    row = {"dim": d, "n": n}
    row["scipy_delaunay_s"], _ = best_time(lambda: Delaunay(x), repeat)
    start = time.perf_counter()
    tess = jaxgeom.delaunay(x)
    jax.block_until_ready(jaxgeom.voronoi_volumes(tess))
    row["first_delaunay_plus_volumes_s"] = time.perf_counter() - start  # includes compilation
    row["jaxgeom_delaunay_s"], tess = best_time(lambda: jaxgeom.delaunay(x), repeat)
    row["voronoi_volumes_s"], _ = best_time(lambda: jaxgeom.voronoi_volumes(tess), repeat)
    row["delaunay_over_scipy"] = row["jaxgeom_delaunay_s"] / row["scipy_delaunay_s"]

    def periodic():
        torus = jaxgeom.delaunay(x, box=(0.0, length), periodic=True)
        return torus, jaxgeom.voronoi_volumes(torus)

    row["periodic_delaunay_plus_volumes_s"], (torus, vols) = best_time(periodic, repeat)
    row["periodic_volume_sum_rel_error"] = float(abs(np.asarray(vols).sum() / length**d - 1))
    row["periodic_capacity"] = list(torus.capacity)
    freud_row = freud_periodic(x, length, repeat)
    if freud_row is not None:
        row["freud_voronoi_s"] = freud_row["seconds"]
        row["freud_volume_sum_rel_error"] = freud_row["volume_sum_rel_error"]
        row["periodic_over_freud"] = row["periodic_delaunay_plus_volumes_s"] / freud_row["seconds"]
    return row


def median_spread(fn, repeat: int) -> dict:
    median, (low, high) = timed(fn, repeat)
    return {"median_s": median, "min_s": low, "max_s": high}


def triangulator_rows(d: int, n: int, repeat: int, seed: int) -> dict:
    from jaxgeom.tessellation import _triangulators as backends

    x = (np.random.default_rng(seed).random((n, d)) * n ** (1.0 / d)).astype(np.float32)
    x64 = x.astype(np.float64)
    installed = [t for t in ("qhull", "cdt", "shull") if d in backends.DIMENSIONS[t] and backends.installed(t)]
    timings = {"bare_qhull": lambda: Delaunay(x64)}
    for t in installed:
        if t != "qhull":
            timings[f"bare_{t}"] = lambda t=t: backends.BUILDERS[t](x64)
        timings[f"delaunay_{t}"] = lambda t=t: jaxgeom.delaunay(x, triangulator=t)
    timings["delaunay_auto"] = lambda: jaxgeom.delaunay(x)
    row = {"dim": d, "n": n, "dtype": "float32", "auto": backends.resolve_triangulator("auto", d)}
    for name, fn in timings.items():
        row[name] = median_spread(fn, repeat)
    base = row["bare_qhull"]["median_s"]
    row["over_bare_qhull"] = {name: row[name]["median_s"] / base for name in timings if name != "bare_qhull"}
    return row


def periodic_vs_freud(d: int, n: int, repeat: int, seed: int) -> dict:
    length = n ** (1.0 / d)
    x = np.random.default_rng(seed).random((n, d)) * length
    row = {"dim": d, "n": n, "dtype": "float64"}
    for t in ("qhull", "auto"):
        row[f"periodic_{t}"] = median_spread(
            lambda t=t: jaxgeom.voronoi_volumes(jaxgeom.delaunay(x, box=(0.0, length), periodic=True, triangulator=t)),
            repeat,
        )
    freud_row = freud_periodic(x, length, 1)
    if freud_row is not None:
        row["freud"] = median_spread(lambda: freud_periodic(x, length, 1), repeat)
        row["over_freud"] = {t: row[f"periodic_{t}"]["median_s"] / row["freud"]["median_s"] for t in ("qhull", "auto")}
    return row


def main_triangulators(args) -> None:
    rows = [
        triangulator_rows(d, n, args.repeat, args.seed)
        for d in args.dims
        for n in args.tri_sizes
        if not (d == 3 and n > 100_000)
    ]
    for row in rows:
        print(
            json.dumps(
                {
                    "dim": row["dim"],
                    "n": row["n"],
                    "auto": row["auto"],
                    "bare_qhull_s": round(row["bare_qhull"]["median_s"], 4),
                    **{k: round(v, 3) for k, v in row["over_bare_qhull"].items()},
                }
            )
        )
    periodic = periodic_vs_freud(3, 100_000, args.repeat, args.seed)
    print(json.dumps(periodic.get("over_freud")))
    meta = {
        "machine": platform.machine(),
        "cpus": __import__("os").cpu_count(),
        "jax": jax.__version__,
        "targets": {
            "2D delaunay_auto over bare_qhull": "<= 0.35 at 1e4, <= 0.2 at 1e5, <= 0.15 at 1e6",
            "periodic 3D over freud at 1e5": "<= 1",
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "results": rows, "periodic_3d": periodic}, indent=2))
    print(f"wrote {args.out}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--triangulators", action="store_true", help="the host backends side by side")
    parser.add_argument("--tri-sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    args = parser.parse_args()
    if args.triangulators:
        args.out = args.out or Path(__file__).parent / "results" / "triangulators.json"
        return main_triangulators(args)
    args.out = args.out or Path(__file__).parent / "results" / "tessellation.json"
    rows = []
    for d, n in tqdm([(d, n) for d in args.dims for n in args.sizes], desc="tessellation bench", disable=None):
        row = bench_one(d, n, args.repeat, args.seed)
        rows.append(row)
        tqdm.write(json.dumps({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}))
    meta = {
        "machine": platform.machine(),
        "cpus": __import__("os").cpu_count(),
        "jax": jax.__version__,
        "targets": {"delaunay_over_scipy": "<= 1.3", "periodic_over_freud": "< 1 (2D), <= 1.2 (3D) at N=1e5"},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "results": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
