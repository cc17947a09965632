"""`small_eigh` (cyclic Jacobi, d <= 4): its sweeps in a `fori_loop` against the same sweeps
unrolled (what it was before 2026-11-27), and batched LAPACK, side by side in one run.

Run: python bench/small_eigh.py [--sizes 10000 1000000] [--out bench/results/small_eigh.json]

Float32 symmetric matrices (normal entries + their transpose), d = 3 and 4, jitted:
- the first call (trace + compile + run) and the warm run time of each, interleaved,
  median (min, max) of `--repeat` rounds; the largest eigenvalue difference between them;
- `ricci_scalar(tess, metric=hessian_metric(f))` on N = 2000 walkers in 3D, first call
  (trace + compile + run, caches cleared before each), with `small_eigh` swapped for each
  variant: what a user of a Hessian metric waits for (the CLI's analyze calls several
  such kernels).
"""

from __future__ import annotations

import argparse
import itertools
import json
import platform
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary, timed

import jaxgeom
from jaxgeom.base import _simplex
from jaxgeom.geometry import _metric


def unrolled_eigh(m):
    """`small_eigh` with its sweeps unrolled in Python (the version this bench compares against)."""
    d = m.shape[-1]
    a = _simplex._entries(m)
    zero, one = jnp.zeros_like(a[0][0]), jnp.ones_like(a[0][0])
    v = [[one if i == j else zero for j in range(d)] for i in range(d)]
    for _ in range(_simplex.JACOBI_SWEEPS[d]):
        for p, q in itertools.combinations(range(d), 2):
            a, v = _simplex._jacobi_rotation(a, v, p, q)
    return _simplex.eigenpairs_ascending(a, v)


VARIANTS = {"fori_loop": _simplex.small_eigh, "unrolled": unrolled_eigh, "lapack": jnp.linalg.eigh}


def eigh_rows(sizes, repeat: int) -> list:
    rng = np.random.default_rng(0)
    rows = []
    for d, n in itertools.product((3, 4), sizes):
        m = rng.normal(size=(n, d, d)).astype(np.float32)
        m = jnp.asarray(m + np.swapaxes(m, 1, 2))
        names = [k for k in VARIANTS if k != "lapack" or n <= 100_000]  # LAPACK: ~1 min at 1e6
        first, warm = {k: [] for k in names}, {k: [] for k in names}
        for _ in range(repeat):
            for name in names:
                jax.clear_caches()
                fn = jax.jit(lambda x, f=VARIANTS[name]: f(x))
                first[name].append(timed(lambda: fn(m)))
                warm[name].append(min(timed(lambda: fn(m)) for _ in range(3)))
        values = {k: np.asarray(jax.jit(VARIANTS[k])(m)[0]) for k in names}
        rows.append(
            {
                "d": d,
                "n": n,
                "first_call_s": {k: summary(v) for k, v in first.items()},
                "warm_s": {k: summary(v) for k, v in warm.items()},
                "max_abs_eigenvalue_difference_vs_unrolled": {
                    k: float(np.max(np.abs(values[k] - values["unrolled"]))) for k in names
                },
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    return rows


def curvature_row(repeat: int, n: int = 2000) -> dict:
    x = np.random.default_rng(1).uniform(-1.0, 1.0, (n, 3)).astype(np.float32)
    tess = jaxgeom.delaunay(x)
    times = {k: [] for k in ("fori_loop", "unrolled")}
    for _ in range(repeat):
        for name in times:
            jax.clear_caches()
            _metric.small_eigh = VARIANTS[name]
            fitness = lambda y: jnp.sum(y**4) - jnp.sum(y**2)  # a new function object: no cache hit
            metric = jaxgeom.hessian_metric(fitness, 0.1)
            times[name].append(timed(lambda: jaxgeom.ricci_scalar(tess, metric=metric)))
    _metric.small_eigh = _simplex.small_eigh
    row = {"n": n, "d": 3, "ricci_scalar_hessian_metric_first_call_s": {k: summary(v) for k, v in times.items()}}
    print(json.dumps(row), flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 1_000_000])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "small_eigh.json")
    args = parser.parse_args()
    result = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].platform}",
        "jax": jax.__version__,
        "eigh": eigh_rows(args.sizes, args.repeat),
        "curvature": curvature_row(args.repeat),
    }
    args.out.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
