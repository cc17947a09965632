"""Time of each curvature/cell proxy (jitted, warm) against jaxgeom.delaunay on the same points.

Run: python bench/proxies.py [--n 100000] [--out bench/results/proxies.json]
The metric is the emergent metric (proxy 6), as a pipeline without a fitness Hessian
would use. Both float32 (the library default) and float64 are measured. "all_proxies" runs every proxy of the
curvature issue in one jitted call
that shares the Voronoi volumes, as a pipeline does. Target: all_proxies <= 0.25 x delaunay.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import numpy as np

import jaxgeom

jax.config.update("jax_enable_x64", True)


def best(fn, *args, repeat=3):
    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return min(times)


@jax.jit
def all_proxies(tess, before):
    vol = jaxgeom.voronoi_volumes(tess)
    metric = jaxgeom.emergent_metric(tess)
    riem = jaxgeom.riemannian_volumes(tess, metric=metric, volumes=vol)
    return {
        "ricci": jaxgeom.ricci_scalar(tess, metric=metric, volumes=vol),
        "volume_distortion": jaxgeom.volume_distortion(tess, riem),
        "shape": jaxgeom.shape_distortion(tess),
        "theta": jaxgeom.raychaudhuri_expansion(before, vol, 0.01, valid=tess.interior),
    }


def bench_dim(d: int, n: int, seed: int, dtype: str) -> dict:
    with jax.enable_x64(dtype == "float64"):
        return _bench_dim(d, n, seed, dtype)


def _bench_dim(d: int, n: int, seed: int, dtype: str) -> dict:
    x = np.random.default_rng(seed).random((n, d)).astype(dtype)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        tess = jaxgeom.delaunay(x)
        times.append(time.perf_counter() - start)
    row = {"dim": d, "n": n, "dtype": dtype, "delaunay_s": min(times)}
    vol = jaxgeom.voronoi_volumes(tess)
    metric = jaxgeom.emergent_metric(tess)
    proxies = {
        "voronoi_volumes": (jaxgeom.voronoi_volumes, tess),
        "emergent_metric (proxy 6)": (jaxgeom.emergent_metric, tess),
        "riemannian_volumes (proxy 8)": (
            jax.jit(lambda t, g, v: jaxgeom.riemannian_volumes(t, metric=g, volumes=v)),
            tess,
            metric,
            vol,
        ),
        "ricci_scalar (proxy 1)": (
            jax.jit(lambda t, g, v: jaxgeom.ricci_scalar(t, metric=g, volumes=v)),
            tess,
            metric,
            vol,
        ),
        "deficit_angles": (jax.jit(lambda t, g: jaxgeom.deficit_angles(t, metric=g)), tess, metric),
        "volume_distortion (proxy 2)": (jax.jit(lambda t, v: jaxgeom.volume_distortion(t, v)), tess, vol),
        "shape_distortion (proxy 3)": (jaxgeom.shape_distortion, tess),
        "raychaudhuri_expansion (proxy 4)": (
            jax.jit(lambda a, b: jaxgeom.raychaudhuri_expansion(a, b, 0.01)),
            vol,
            vol,
        ),
        "all_proxies": (all_proxies, tess, vol),
    }
    row["seconds"] = {name: best(fn, *args) for name, (fn, *args) in proxies.items()}
    row["all_proxies_over_delaunay"] = row["seconds"]["all_proxies"] / row["delaunay_s"]
    print(json.dumps(row))
    return row


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "proxies.json")
    args = parser.parse_args()
    rows = [bench_dim(d, args.n, args.seed, dtype) for dtype in ("float32", "float64") for d in (2, 3)]
    meta = {
        "machine": platform.machine(),
        "jax": jax.__version__,
        "dtypes": "float32 (library default), float64",
        "metric": "emergent_metric(tess)",
        "target": "all_proxies_over_delaunay <= 0.25",
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"meta": meta, "results": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
