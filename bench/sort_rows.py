"""Sorting the neighbour rows of the 2D fan walk: Batcher's merge network against XLA's sort,
side by side in one run, and where `sort_rows` switches (`MERGE_NETWORK_MIN_ROWS`).

Run: python bench/sort_rows.py [--sizes 1000 10000 100000 1000000] [--out bench/results/sort_rows.json]

Random int32 rows (N, K), K = 16 and 24 (a 2D Delaunay graph's buckets), jitted, XLA's default
settings: the first call (trace + compile + run) and the warm run of each, median (min, max)
of `--repeat` rounds, the two variants interleaved, caches cleared before each first call.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary, timed

from jaxgeom.tessellation import _planar


def measure(n: int, k: int, network: bool, repeat: int) -> dict:
    cols = jnp.asarray(np.random.default_rng(n + k).integers(0, n, (k, n)), jnp.int32)
    first, warm = [], []
    for _ in range(repeat):
        jax.clear_caches()
        fn = jax.jit(lambda c: _planar.sort_rows(c, network=network))
        first.append(timed(lambda: fn(cols)))
        warm.append(min(timed(lambda: fn(cols)) for _ in range(3)))
    out = np.asarray(fn(cols))
    assert np.array_equal(out, np.sort(np.asarray(cols).T, axis=1))
    return {"first_call_s": summary(first), "warm_ms": summary([1e3 * w for w in warm])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 100000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sort_rows.json")
    args = parser.parse_args()
    rows = []
    for n in args.sizes:
        for k in (16, 24):
            row = {"n": n, "k": k}
            for name, network in (("network", True), ("xla_sort", False)):
                row[name] = measure(n, k, network, args.repeat)
            row["default"] = "network" if n >= _planar.MERGE_NETWORK_MIN_ROWS else "xla_sort"
            net, xla = row["network"], row["xla_sort"]
            print(
                f"N={n:>8} K={k}: network first {net['first_call_s']['median']:.2f} s, warm "
                f"{net['warm_ms']['median']:.2f} ms | XLA sort first {xla['first_call_s']['median']:.2f} s, "
                f"warm {xla['warm_ms']['median']:.2f} ms | default {row['default']}"
            )
            rows.append(row)
    meta = {
        "jax": jax.__version__,
        "device": str(jax.devices()[0]),
        "machine": platform.processor() or platform.machine(),
        "merge_network_min_rows": _planar.MERGE_NETWORK_MIN_ROWS,
        "repeat": args.repeat,
    }
    args.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
