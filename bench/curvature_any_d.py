"""Cost of `metric_curvature` in any dimension (issue 33), and the 2D/3D comparison with Regge.

Run: python bench/curvature_any_d.py [--quick] [--out bench/results/curvature_any_d.json]

Landscape: V(x) = log(1 + sum_i exp x_i) + |x|^2 / 4 (the categorical log-partition plus a
bowl: convex, not separable, O(d) to evaluate), metric g = Hess V + 0.1 I, walkers N(0, 0.5^2 I).
Per dimension d = 2, 5, 10, 20, 50, 100 and form (Christoffel reference, exact Hessian form,
stochastic Hessian form at the m probe pairs that give a 1% median relative standard error
per walker): seconds per 1e3 walkers (median of 3 warm runs, with min and max), the compile
time, and XLA's peak temporary memory of one call (`memory_analysis`, bytes). Then the two
targets: the stochastic form at d = 100, N = 1e4 (float32 and float64), and in 2D and 3D
the exact Hessian form against `ricci_scalar` on the same 1e5 walkers.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxgeom

EPS = 0.1


def fitness(x):
    return jnp.log1p(jnp.sum(jnp.exp(x))) + 0.25 * jnp.sum(x * x)


def walkers(n, d, dtype, seed=0):
    return jnp.asarray(np.random.default_rng(seed).normal(scale=0.5, size=(n, d)), dtype)


def timed(fn, *args, repeats=3):
    """(compile seconds, [warm seconds], peak temporary bytes) of a jitted fn."""
    jitted = jax.jit(fn)
    start = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - start
    memory = compiled.memory_analysis()
    peak = int(memory.temp_size_in_bytes + memory.output_size_in_bytes) if memory is not None else None
    jax.block_until_ready(compiled(*args))
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - start)
    return compile_s, runs, peak


def summary(runs, per):
    runs = np.asarray(runs) * per
    return {"median_s": float(np.median(runs)), "min_s": float(runs.min()), "max_s": float(runs.max())}


def probes_for_one_percent(metric, d, dtype):
    """m with a 1% median relative standard error per walker, from a 256-probe pilot."""
    x = walkers(50, d, dtype, seed=1)
    s, info = jaxgeom.metric_curvature(metric, x, probes=256, key=jax.random.key(0), with_info=True)
    relative_std = float(np.median(np.asarray(info.standard_error) / np.abs(np.asarray(s)))) * math.sqrt(256)
    return max(2, math.ceil((relative_std / 0.01) ** 2)), relative_std


def cost_table(dims, christoffel_walkers, dtype):
    metric = jaxgeom.hessian_metric(fitness, EPS)
    rows = []
    for d in dims:
        row = {"d": d}
        m, relative_std = probes_for_one_percent(metric, d, dtype)
        row.update(probes_for_1pct=m, relative_std_per_probe=relative_std)
        plain = lambda y: jax.hessian(fitness)(y) + EPS * jnp.eye(y.shape[0], dtype=y.dtype)  # noqa: E731
        forms = {
            "exact_hessian": (lambda x: jaxgeom.metric_curvature(metric, x), 1000),
            "stochastic_hessian": (
                lambda x: jaxgeom.metric_curvature(metric, x, probes=m, key=jax.random.key(2)),
                1000,
            ),
            "christoffel": (lambda x: jaxgeom.metric_curvature(plain, x), christoffel_walkers.get(d, 0)),
        }
        for name, (fn, n) in forms.items():
            if n == 0:
                row[name] = "not run"
                continue
            compile_s, runs, peak = timed(fn, walkers(n, d, dtype))
            row[name] = summary(runs, 1000 / n) | {"walkers_timed": n, "compile_s": compile_s, "peak_temp_bytes": peak}
        print(json.dumps(row), flush=True)
        rows.append(row)
    return rows


def variance_against_m(d=100, dtype=jnp.float64):
    """Median relative standard error per walker against m at d = 100 (and its 1/sqrt(m) law)."""
    metric = jaxgeom.hessian_metric(fitness, EPS)
    x = walkers(100, d, dtype, seed=3)
    exact = np.asarray(jaxgeom.metric_curvature(metric, x))
    out = []
    for m in (16, 64, 256, 1024):
        s, info = jaxgeom.metric_curvature(metric, x, probes=m, key=jax.random.key(m), with_info=True)
        rel_se = np.asarray(info.standard_error) / np.abs(exact)
        z = (np.asarray(s) - exact) / np.asarray(info.standard_error)
        out.append(
            {
                "m": m,
                "median_relative_se": float(np.median(rel_se)),
                "rms_relative_error": float(np.sqrt(np.mean(((np.asarray(s) - exact) / exact) ** 2))),
                "fraction_within_3_se": float(np.mean(np.abs(z) < 3)),
            }
        )
        print(json.dumps(out[-1]), flush=True)
    return out


def target_d100(n, dtype):
    metric = jaxgeom.hessian_metric(fitness, EPS)
    m, _ = probes_for_one_percent(metric, 100, dtype)
    x = walkers(n, 100, dtype)
    start = time.perf_counter()
    s, info = jax.block_until_ready(
        jaxgeom.metric_curvature(metric, x, probes=m, key=jax.random.key(4), with_info=True)
    )
    first = time.perf_counter() - start
    compile_s, runs, peak = timed(
        lambda p: jaxgeom.metric_curvature(metric, p, probes=m, key=jax.random.key(4)), x, repeats=1
    )
    out = {
        "n": n,
        "d": 100,
        "dtype": str(jnp.dtype(dtype)),
        "probes": m,
        "first_call_s": first,
        "warm_s": runs[0],
        "peak_temp_bytes": peak,
        "median_relative_se": float(np.median(np.asarray(info.standard_error) / np.abs(np.asarray(s)))),
    }
    print(json.dumps(out), flush=True)
    return out


def against_regge(n, d, dtype):
    """The exact Hessian form and `ricci_scalar` (Hessian metric, Delaunay graph built first) on
    the same n walkers in a box, each timed warm (median of 3)."""
    metric = jaxgeom.hessian_metric(fitness, EPS)
    x = np.asarray(np.random.default_rng(5).uniform(-2, 2, (n, d)), dtype)
    start = time.perf_counter()
    tess = jaxgeom.delaunay(x)
    build = time.perf_counter() - start
    _, exact_runs, _ = timed(lambda p: jaxgeom.metric_curvature(metric, p), jnp.asarray(x))
    _, regge_runs, _ = timed(lambda t: jaxgeom.ricci_scalar(t, metric=metric), tess)
    out = {
        "n": n,
        "d": d,
        "exact_hessian_s": float(np.median(exact_runs)),
        "ricci_scalar_s": float(np.median(regge_runs)),
        "delaunay_build_s": build,
    }
    out["ratio_exact_over_ricci_scalar"] = out["exact_hessian_s"] / out["ricci_scalar_s"]
    print(json.dumps(out), flush=True)
    return out


def regge_convergence(sizes, d, region=1.2, seeds=3):
    """Region average of the Regge proxy and of the exact S (same walkers: tier 2 with |x|_inf
    < region, same weights: Riemannian cell volumes) on uniform walkers in [-2, 2]^d, by N;
    mean and spread over `seeds` samples."""
    metric = jaxgeom.hessian_metric(fitness, EPS)
    rows = []
    for n in sizes:
        regge, exact = [], []
        for seed in range(seeds):
            x = np.random.default_rng(1000 * seed + n + d).uniform(-2, 2, (n, d))
            tess = jaxgeom.delaunay(x)
            weights = jaxgeom.riemannian_volumes(tess, metric=metric)
            inside = tess.interior & jnp.asarray(np.max(np.abs(x), axis=1) < region)
            regge.append(float(jaxgeom.riemannian_mean(jaxgeom.ricci_scalar(tess, metric=metric), weights, inside)))
            exact.append(
                float(jaxgeom.riemannian_mean(jaxgeom.metric_curvature(metric, jnp.asarray(x)), weights, inside))
            )
        diff = np.asarray(regge) - np.asarray(exact)
        rows.append(
            {
                "d": d,
                "n": n,
                "regge_mean": float(np.mean(regge)),
                "exact_mean": float(np.mean(exact)),
                "relative_difference_mean": float(np.mean(diff) / np.mean(exact)),
                "relative_difference_rms": float(np.sqrt(np.mean(diff**2)) / abs(np.mean(exact))),
                "seeds": seeds,
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="d <= 10 and small N only")
    parser.add_argument("--regge", action="store_true", help="only the Regge convergence table (its own JSON)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/curvature_any_d.json"))
    args = parser.parse_args()
    jax.config.update("jax_enable_x64", True)
    if args.regge:
        sizes = (1_000, 3_000, 10_000, 30_000, 100_000)
        result = {
            "landscape": "log(1 + sum exp x) + |x|^2/4, eps_Sigma = 0.1; walkers U[-2, 2]^d; region: tier 2, "
            "|x|_inf < 1.2; float64",
            "2D": regge_convergence(sizes, 2),
            "3D": regge_convergence(sizes, 3),
        }
        out = args.out.with_name("curvature_regge_vs_exact.json")
        out.write_text(json.dumps(result, indent=1))
        print(f"wrote {out}")
        return
    dims = (2, 5, 10) if args.quick else (2, 5, 10, 20, 50, 100)
    christoffel_walkers = {2: 1000, 5: 1000, 10: 200, 20: 20, 50: 2, 100: 1}
    result = {
        "landscape": "log(1 + sum exp x) + |x|^2/4, eps_Sigma = 0.1, walkers N(0, 0.25 I)",
        "machine": f"{jax.devices()[0].platform}, {jax.local_device_count()} device(s)",
        "cost_per_1e3_walkers_float64": cost_table(dims, christoffel_walkers, jnp.float64),
    }
    if not args.quick:
        result["variance_against_m_d100"] = variance_against_m()
        result["target_d100_n1e4"] = [target_d100(10_000, jnp.float32), target_d100(10_000, jnp.float64)]
    n = 10_000 if args.quick else 100_000
    result["against_ricci_scalar"] = [
        against_regge(n, 2, np.float32),
        against_regge(n, 3, np.float32),
        against_regge(n, 2, np.float64),
        against_regge(n, 3, np.float64),
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
