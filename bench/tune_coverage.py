"""Coverage of `tune`'s standard errors, and the recovery of the `jaxgeom tune` demo.

Run: python bench/tune_coverage.py [--fits 30] [--out bench/results/tune_coverage.json]

The problem is the command line's default demo (`jaxgeom tune`: rastrigin, 200 walkers, 10
steps, 8 seeds, nu tuned with eps_Sigma at its true value, matching the late velocity
variance and mean fitness), float64. Fit k takes its targets from 8 runs at the truth with seeds independent of the
loss's (`build_loss(args, target_key=1000 + k)`), as data would be, fits from the truth
(the estimate, not the search, is what is studied) and records the value, its standard
error (`target_seeds` = 8) and z = (value - truth) / se. Coverage: the fraction of fits whose
truth lies within 2 standard errors (95% expected), per parameter and for both at once.
The demo itself (targets from the loss's seeds, start nu 0.05) is run once:
the values found and their distance from the truth.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxgeom  # noqa: E402
from jaxgeom.base._progress import close_bar, open_bar  # noqa: E402
from jaxgeom.cli import _parser  # noqa: E402
from jaxgeom.cli._tune import build_loss  # noqa: E402


def demo_args(*extra: str):
    return _parser().parse_args(["tune", "--no-progress", *extra])


def demo_recovery() -> dict:
    args = demo_args()
    loss, start, truth = build_loss(args)
    began = time.perf_counter()
    result = jaxgeom.tune(loss, start, max_steps=args.max_steps, target_seeds=args.seeds)
    return {
        "start": start,
        "truth": truth,
        "found": result.values,
        "standard_errors": result.standard_errors,
        "relative_error": {n: abs(result.values[n] / v - 1) for n, v in truth.items()},
        "message": result.message,
        "solver_steps": result.n_steps,
        "seconds": time.perf_counter() - began,
    }


def one_fit(k: int) -> dict:
    args = demo_args()
    loss, _, truth = build_loss(args, target_key=1000 + k)
    result = jaxgeom.tune(loss, truth, max_steps=args.max_steps, target_seeds=args.seeds)
    z = {n: (result.values[n] - v) / result.standard_errors[n] for n, v in truth.items()}
    return {
        "fit": k,
        "values": result.values,
        "standard_errors": result.standard_errors,
        "z": z,
        "loss": result.loss,
        "message": result.message,
    }


def coverage(fits: list[dict]) -> dict:
    names = list(fits[0]["z"])
    z = np.array([[f["z"][n] for n in names] for f in fits])
    inside = np.abs(z) <= 2.0
    return {
        "fits": len(fits),
        "within_2_se": {n: float(inside[:, i].mean()) for i, n in enumerate(names)},
        "both_within_2_se": float(inside.all(axis=1).mean()),
        "z_std": {n: float(z[:, i].std(ddof=1)) for i, n in enumerate(names)},
        "z_mean": {n: float(z[:, i].mean()) for i, n in enumerate(names)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fits", type=int, default=30)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "tune_coverage.json")
    args = parser.parse_args()
    demo = demo_recovery()
    print("demo:", json.dumps(demo, default=float))
    fits = []
    bar, owned = open_bar("auto", args.fits, "fits")
    for k in range(args.fits):
        fits.append(one_fit(k))
        print(json.dumps(fits[-1]), flush=True)
        # the targets are static fields of the loss: every fit compiles its own programs, and
        # XLA's CPU code would exhaust the process's memory maps (vm.max_map_count) by fit ~20
        jax.clear_caches()
        gc.collect()
        if bar is not None:
            bar.update(1)
    close_bar(bar, owned)
    summary = coverage(fits)
    print("coverage:", json.dumps(summary))
    args.out.write_text(
        json.dumps(
            {
                "machine": platform.processor() or platform.machine(),
                "jax": jax.__version__,
                "demo": demo,
                "coverage": summary,
                "fits": fits,
            },
            indent=1,
            default=float,
        )
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())
