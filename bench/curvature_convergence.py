"""Convergence of region-averaged Regge curvature to the analytic scalar curvature.

Run: python bench/curvature_convergence.py [--sizes ...] [--out bench/results/curvature_convergence.json]
Walkers are uniform in the coordinate ball |x| < 0.5; the region is |x| < 0.35 on
tier 2. Metrics: the unit sphere in stereographic coordinates (R = d(d-1)) and the
Poincare ball (R = -d(d-1)). Also: the sum of Riemannian volumes over a periodic box
against the exact integral of sqrt(det g).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

import jaxgeom

jax.config.update("jax_enable_x64", True)


def sphere(x):
    return 4.0 / (1.0 + jnp.sum(x * x)) ** 2 * jnp.eye(x.shape[0])


def hyperbolic(x):
    return 4.0 / (1.0 - jnp.sum(x * x)) ** 2 * jnp.eye(x.shape[0])


def periodic_metric(x):
    return (1.0 + 0.5 * jnp.sin(2 * jnp.pi * x[0])) ** 2 * jnp.eye(2)  # integral of sqrt(det g) = 1.125


def ball(n, d, seed):
    x = np.random.default_rng(seed).uniform(-0.5, 0.5, size=(3 * n + 1000, d))
    return x[np.linalg.norm(x, axis=1) < 0.5][:n]


def curvature_rows(sizes, seed):
    rows = []
    for d, n in tqdm([(d, n) for d in (2, 3) for n in sizes], desc="curvature convergence", disable=None):
        x = ball(n, d, seed)
        start = time.perf_counter()
        tess = jaxgeom.delaunay(x)
        t_tess = time.perf_counter() - start
        region = tess.interior & jnp.asarray(np.linalg.norm(x, axis=1) < 0.35)
        vol = jaxgeom.voronoi_volumes(tess)
        for name, metric, exact in (("sphere", sphere, d * (d - 1.0)), ("hyperbolic", hyperbolic, -d * (d - 1.0))):
            r = jaxgeom.ricci_scalar(tess, metric=metric, volumes=vol)
            avg = float(
                jaxgeom.riemannian_mean(r, jaxgeom.riemannian_volumes(tess, metric=metric, volumes=vol), region)
            )
            rows.append(
                {
                    "dim": d,
                    "n": n,
                    "metric": name,
                    "exact_R": exact,
                    "region_average_R": avg,
                    "relative_error": abs(avg / exact - 1),
                    "region_walkers": int(region.sum()),
                    "delaunay_s": t_tess,
                }
            )
            tqdm.write(json.dumps(rows[-1]))
    return rows


def volume_rows(sizes, seed):
    rows = []
    for n in sizes:
        x = np.random.default_rng(seed + n).random((n, 2))
        tess = jaxgeom.delaunay(x, box=(0.0, 1.0), periodic=True)
        total = float(jnp.sum(jaxgeom.riemannian_volumes(tess, metric=periodic_metric)))
        rows.append(
            {"dim": 2, "n": n, "sum_riemannian_volumes": total, "exact": 1.125, "abs_error": abs(total - 1.125)}
        )
        print(json.dumps(rows[-1]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 3000, 10_000, 30_000, 100_000])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "curvature_convergence.json")
    args = parser.parse_args()
    result = {
        "curvature": curvature_rows(args.sizes, args.seed),
        "riemannian_volume": volume_rows(args.sizes, args.seed),
        "targets": {"2D at N=1e5": "relative error < 0.01", "3D at N=1e5": "relative error < 0.02"},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
