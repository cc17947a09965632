"""Where 3D `voronoi_facets` spends its time on a built graph (issue 62), by parts of the dual.

For uniform walkers in the unit cube at each N, on one boxed and one open graph built once,
side by side in one process (every case once per round, interleaved): `voronoi_facets`
(boxed), `dual_faces_3d` with and without vertex counts (boxed and open), and the per-simplex
stage alone (`_in_blocks` over every simplex: circumcentres, flags, areas, volumes). The
differences are the parts: boxed clipping = boxed without counts - the stage; counts = with -
without. Medians (min, max) of warm calls, and the median of each call's minor page faults
(the fresh memory it touched: XLA maps a program's temporaries anew on every call, and on
this VM a first touch costs ~1 ms per MB). Writes bench/results/cells_3d_parts_<dtype>.json.

Run alone (2 cores: anything beside it skews the times):
    .venv/bin/python bench/cells_3d_parts.py [--n 10000 100000] [--repeat 5] [--dtype float64]
"""

from __future__ import annotations

import argparse
import functools
import resource

import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary, timed, write_rows


def stage_alone(tess):
    """The per-simplex stage of `dual_faces_3d` over every simplex, nothing after it."""
    from jaxgeom.geometry import _dual

    tess = _dual.with_sorted_simplices(tess)
    n, k = tess.neighbors.shape
    dtype = tess.points.dtype
    sums = (jnp.zeros(n * k + 1, dtype), jnp.zeros(n + 1, dtype), jnp.zeros((n + 1, 3), dtype))
    return _dual._in_blocks(tess, functools.partial(_dual._simplex_stage_3d, rows=_dual._sorted_rows(tess)), sums)


def cases(boxed, open_):
    import jaxgeom
    from jaxgeom.geometry import _dual

    facets = jax.jit(jaxgeom.voronoi_facets)
    counted = jax.jit(_dual.dual_faces_3d)
    uncounted = jax.jit(functools.partial(_dual.dual_faces_3d, counts=False))
    stage = jax.jit(stage_alone)
    return {
        "voronoi_facets boxed": lambda: facets(boxed),
        "dual boxed, counts": lambda: counted(boxed),
        "dual boxed, no counts": lambda: uncounted(boxed),
        "stage alone boxed": lambda: stage(boxed),
        "dual open, counts": lambda: counted(open_),
        "dual open, no counts": lambda: uncounted(open_),
        "stage alone open": lambda: stage(open_),
    }


def row(n: int, repeat: int, dtype) -> dict:
    import jaxgeom

    x = np.random.default_rng(n).random((n, 3))
    xd = np.minimum(x.astype(dtype), np.nextafter(dtype.type(1), dtype.type(0)))
    boxed, open_ = jaxgeom.delaunay(xd, box=(0.0, 1.0)), jaxgeom.delaunay(xd)
    fns = cases(boxed, open_)
    for fn in fns.values():  # compile and warm
        timed(fn)
    times = {name: [] for name in fns}
    faults = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            times[name].append(timed(fn))
            faults[name].append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {
        "n": n,
        "dtype": str(np.dtype(dtype)),
        "simplices": int(boxed.simplices.shape[0]),
        "tier0": int(np.sum(np.asarray(boxed.tier) == 0)),
        "seconds": {k: summary(v) for k, v in times.items()},
        "minor page faults per call (median)": {k: int(np.median(v)) for k, v in faults.items()},
        "parts (medians)": {
            "boxed: stage": med["stage alone boxed"],
            "boxed: clipping and the rest (no counts - stage)": med["dual boxed, no counts"] - med["stage alone boxed"],
            "boxed: vertex counts (counts - no counts)": med["dual boxed, counts"] - med["dual boxed, no counts"],
            "open: vertex counts (counts - no counts)": med["dual open, counts"] - med["dual open, no counts"],
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    args = parser.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    rows = [row(n, args.repeat, np.dtype(args.dtype)) for n in args.n]
    for r in rows:
        print(f"N = {r['n']} ({r['dtype']}), {r['simplices']} simplex slots, {r['tier0']} tier-0 walkers")
        for name, s in r["seconds"].items():
            faults = r["minor page faults per call (median)"][name]
            spread = f"{1e3 * s['min']:.1f}-{1e3 * s['max']:.1f}"
            print(f"  {name:<26} {1e3 * s['median']:8.1f} ms ({spread}), {faults} faults")
        for name, seconds in r["parts (medians)"].items():
            print(f"  = {name:<50} {1e3 * seconds:8.1f} ms")
    write_rows(f"cells_3d_parts_{args.dtype}.json", rows)


if __name__ == "__main__":
    main()
