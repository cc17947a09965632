"""3D Voronoi cells against freud (voro++), side by side in one process (issue 62).

For uniform walkers in the unit cube at each N: freud's periodic Voronoi (volumes and the
face areas of every neighbour pair), and jaxgeom's `delaunay` + `voronoi_facets` (periodic,
boxed) and `delaunay` + clipped `voronoi_volumes` (boxed), with `delaunay` alone and bare
Qhull (scipy) on the same walkers as the floors, and (Qhull) the open `delaunay` with its
Qhull in one call instead of in slabs (`_slabs`, from 3e4 walkers). Medians (min, max) of
warm calls; ratios against freud at the same N: of the medians, and per round (every case
once, interleaved) that round's time over freud's, median (min, max). Writes
bench/results/cells_3d_<dtype>.json, or cells_3d_<dtype>_<triangulator>.json for a
triangulator other than Qhull ("shull", the `gpl` extra's: its bare call is then timed too).

Run alone (2 cores: anything beside it skews the ratios):
    .venv/bin/python bench/cells_3d.py [--n 10000 100000] [--repeat 5] [--dtype float64]
        [--triangulator qhull|shull]
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
import scipy.spatial
from _timing import summary, timed, write_rows


def cases(x, dtype, triangulator: str):
    import freud

    import jaxgeom

    def delaunay(points, **kwargs):
        return jaxgeom.delaunay(points, triangulator=triangulator, **kwargs)

    box = freud.box.Box.cube(1.0)
    centred = (x - 0.5).astype(np.float64)

    def freud_voronoi():
        voro = freud.locality.Voronoi()
        voro.compute((box, centred))
        return voro.volumes, voro.nlist.weights

    xd = np.minimum(x.astype(dtype), np.nextafter(dtype.type(1), dtype.type(0)))  # float32 rounds 1 - 1e-9 up to 1
    fns = {
        "freud periodic (volumes + face areas)": freud_voronoi,
        "qhull alone (scipy)": lambda: scipy.spatial.Delaunay(x).simplices,
    }
    if triangulator == "shull":
        import shull

        fns["shull alone"] = lambda: shull.Delaunay(np.ascontiguousarray(x, dtype=np.float64)).simplices
    if triangulator == "qhull":
        fns["delaunay open, one Qhull call"] = lambda: one_call(lambda: delaunay(xd).neighbors)
    return fns | {
        "delaunay open": lambda: delaunay(xd).neighbors,
        "delaunay periodic": lambda: delaunay(xd, box=(0.0, 1.0), periodic=True).neighbors,
        "delaunay periodic + voronoi_facets": lambda: (
            jaxgeom.voronoi_facets(delaunay(xd, box=(0.0, 1.0), periodic=True)).areas
        ),
        "delaunay boxed + voronoi_facets": lambda: jaxgeom.voronoi_facets(delaunay(xd, box=(0.0, 1.0))).areas,
        "delaunay boxed + voronoi_volumes (clipped)": lambda: jaxgeom.voronoi_volumes(delaunay(xd, box=(0.0, 1.0))),
    }


def one_call(build):
    """`build()` with the open and boxed graphs' Qhull in one call, not in slabs (`_slabs`)."""
    from jaxgeom.tessellation import _slabs

    least, _slabs.SLAB_MIN_POINTS = _slabs.SLAB_MIN_POINTS, 2**62
    try:
        return build()
    finally:
        _slabs.SLAB_MIN_POINTS = least


def row(n: int, repeat: int, dtype, triangulator: str) -> dict:
    x = np.random.default_rng(n).random((n, 3))
    fns = cases(x, dtype, triangulator)
    for fn in fns.values():  # compile and warm
        timed(fn)
    times = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():  # interleaved: the ratios are measured side by side
            times[name].append(timed(fn))
    freud = times["freud periodic (volumes + face areas)"]
    freud_median = float(np.median(freud))
    return {
        "n": n,
        "dtype": str(np.dtype(dtype)),
        "triangulator": triangulator,
        "seconds": {k: summary(v) for k, v in times.items()},
        "over_freud": {k: float(np.median(v)) / freud_median for k, v in times.items()},
        # each round's time over freud's in the same round: the VM's slow spells (+-20% between
        # runs) hit both, so the spread of these is the ratio's own
        "over_freud_by_round": {k: summary([a / b for a, b in zip(v, freud, strict=True)]) for k, v in times.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--triangulator", default="qhull", choices=["qhull", "shull"])
    args = parser.parse_args()
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    rows = [row(n, args.repeat, np.dtype(args.dtype), args.triangulator) for n in args.n]
    for r in rows:
        print(f"N = {r['n']} ({r['dtype']})")
        for name, s in r["seconds"].items():
            by_round = r["over_freud_by_round"][name]
            print(
                f"  {name:<46} {s['median']:8.3f} s ({s['min']:.3f}-{s['max']:.3f})  "
                f"{r['over_freud'][name]:6.2f}x freud (by round {by_round['min']:.2f}-{by_round['max']:.2f})"
            )
    suffix = "" if args.triangulator == "qhull" else f"_{args.triangulator}"
    write_rows(f"cells_3d_{args.dtype}{suffix}.json", rows)


if __name__ == "__main__":
    main()
