"""Gradient/Hessian estimation: convergence, FD-geometric agreement, and speed.

Run: python bench/estimation.py [--out bench/results/estimation.json]
- convergence: validate_on_synthetic_function for Rosenbrock and Rastrigin in 2D,
  N = 1e2 ... 1e5 (uniform walkers, k-NN graph with k = 10). The quadratic fit has
  gradient error O(h^2) ~ N^-1 and Hessian error O(h) ~ N^-1/2 in 2D.
- agreement: compare_estimation_methods on walkers drawn from exp(-x^T A x / 2) and
  uniformly, Delaunay graph, fitness V = x^T A x / 2, eps_Sigma = 0.1.
- timing: full Hessian (jitted, warm) at N = 1e5 in 2D and 3D against jaxgeom.delaunay
  on the same points; target <= 0.25x.
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


def convergence(sizes) -> list:
    rows = []
    for name in ("rosenbrock", "rastrigin"):
        for n in sizes:
            r = jaxgeom.validate_on_synthetic_function(name, n_walkers=n)
            rows.append(
                {
                    k: r[k]
                    for k in (
                        "function",
                        "n_walkers",
                        "k",
                        "n_scored",
                        "gradient_rmse",
                        "gradient_relative_rmse",
                        "hessian_frobenius_error",
                        "fd_geometric_correlation",
                        "passed",
                    )
                }
            )
            print(json.dumps(rows[-1]))
    return rows


def agreement(n: int, seed: int) -> list:
    rng = np.random.default_rng(seed)
    a = np.array([[3.0, 1.0], [1.0, 1.5]])
    samples = {
        "gaussian exp(-x^T A x / 2)": rng.multivariate_normal(np.zeros(2), np.linalg.inv(a), size=n),
        "uniform [-2, 2]^2": rng.uniform(-2, 2, size=(n, 2)),
    }
    rows = []
    for label, x in samples.items():
        tess = jaxgeom.delaunay(x)
        values = 0.5 * np.einsum("ni,ij,nj->n", x, a, x)
        out = jaxgeom.compare_estimation_methods(tess, values, eps_sigma=0.1)
        h_geo = np.asarray(out["hessian_geometric"])[out["valid"]]
        rows.append(
            {
                "walkers": label,
                "n": n,
                **out["metrics"],
                "median_fd_hessian_error": float(
                    np.median(
                        np.linalg.norm(np.asarray(out["hessian_fd"])[out["valid"]] - a, axis=(1, 2)) / np.linalg.norm(a)
                    )
                ),
                "median_geometric_eigenvalues": np.median(np.linalg.eigvalsh(h_geo), axis=0).tolist(),
                "true_eigenvalues": np.linalg.eigvalsh(a).tolist(),
            }
        )
        print(json.dumps(rows[-1]))
    return rows


def timing(n: int, seed: int) -> list:
    rows = []
    for d in (2, 3):
        x = np.random.default_rng(seed).random((n, d))
        times = []
        for _ in range(2):
            start = time.perf_counter()
            tess = jaxgeom.delaunay(x)
            times.append(time.perf_counter() - start)
        values = jnp.asarray(np.sum(np.sin(3 * x), axis=1))
        fn = jax.jit(lambda t, v: jaxgeom.estimate_hessian(t, v))
        jax.block_until_ready(fn(tess, values))
        best = np.inf
        for _ in range(3):
            start = time.perf_counter()
            jax.block_until_ready(fn(tess, values))
            best = min(best, time.perf_counter() - start)
        rows.append(
            {
                "dim": d,
                "n": n,
                "delaunay_s": min(times),
                "full_hessian_s": best,
                "hessian_over_delaunay": best / min(times),
            }
        )
        print(json.dumps(rows[-1]))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 1000, 10_000, 100_000])
    parser.add_argument("--n", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "estimation.json")
    args = parser.parse_args()
    result = {
        "meta": {
            "machine": platform.machine(),
            "jax": jax.__version__,
            "dtype": "float64",
            "target": "hessian_over_delaunay <= 0.25",
        },
        "timing": timing(args.n, args.seed),
        "convergence": convergence(args.sizes),
        "agreement": agreement(5000, args.seed),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
