"""`jaxgeom analyze --trajectory FILE`: `simulate`'s observables measured on a recorded
trajectory (`jaxgeom.analyze_trajectory`), printed as `simulate`'s table; with --out,
observables.json, observables.h5md (H5MD `observables` group), observables.png and a
swarm.png of chosen frames."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import jaxgeom

from ..apps._plots import plot_observables, plot_swarm_snapshots
from ..base._h5md import write_h5md_observables
from ..swarm._dynamics import metric_field
from ..swarm._trajectory import TrajectoryInterrupted, _Source
from ._legend import UNITS, simulate_definition
from ._simulate import INTERRUPTED, _gap_rows, _json_ready, _steps, load_landscape, observable_rows

# analyze's options that describe one swarm (a sample or --points), not a recorded trajectory
SNAPSHOT_ONLY = ("points", "n", "dim", "seed", "beta", "metric", "length_scale")
TRAJECTORY_ONLY = ("every", "frames", "gap_every", "snapshots")


def frame_range(text: str) -> tuple[int, int | None]:
    """--frames A:B (A or B may be left out) as (start, stop)."""
    first, colon, last = text.partition(":")
    try:
        start = int(first) if first else 0
        stop = int(last) if last else None
    except ValueError:
        start = stop = -1
    if not colon or start < 0 or (stop is not None and stop <= start):
        raise ValueError(f"--frames must be A:B with 0 <= A < B (either may be left out: 10:, :50); got {text!r}")
    return start, stop


def add_trajectory_arguments(parser) -> None:
    parser.add_argument(
        "--trajectory",
        type=Path,
        help="a recorded trajectory: an H5MD file (.h5md, .h5, .hdf5: positions, box, velocities, "
        "fitness, clone parents), a .npy (frames, N, d) or an .npz (positions and optionally "
        "fitness, velocities, parents, box, periodic, times); reports simulate's observables "
        "frame by frame (jaxgeom.analyze_trajectory). --landscape adds the fitness and the "
        "Hessian metric; --box and --periodic replace the file's box",
    )
    parser.add_argument("--every", type=int, default=1, help="with --trajectory: analyse every M-th frame")
    parser.add_argument(
        "--frames",
        default=None,
        metavar="A:B",
        help="with --trajectory: frames A (included) to B (excluded); 10: or :50 leave one end open",
    )
    parser.add_argument(
        "--gap-every", type=int, default=50, help="with --trajectory: the spectral gap every M analysed frames (0: off)"
    )
    parser.add_argument(
        "--snapshots",
        type=int,
        default=4,
        help="with --trajectory --out: frames drawn in swarm.png, spread evenly over those analysed",
    )


def refuse_mixed_options(args, defaults: dict) -> None:
    """An option of the other mode given a value is refused, naming it."""
    if args.trajectory is not None:
        wrong = [name for name in SNAPSHOT_ONLY if getattr(args, name) != defaults[name]]
        if wrong:
            flags = ", ".join("--" + name.replace("_", "-") for name in wrong)
            raise ValueError(
                f"{flags} describe(s) one swarm (a sample or --points), not a recorded trajectory: "
                "leave it out with --trajectory (the metric is the landscape's Hessian metric with "
                "--landscape, else Euclidean)."
            )
    else:
        wrong = [name for name in TRAJECTORY_ONLY if getattr(args, name) != defaults[name]]
        if wrong:
            flags = ", ".join("--" + name.replace("_", "-") for name in wrong)
            raise ValueError(f"{flags} appl(y/ies) to --trajectory FILE only.")


def run_trajectory(args, src: _Source) -> dict:
    """analyze_trajectory of the open trajectory `src` with the command line's options, timed;
    Ctrl-C keeps the frames done."""
    start_time = time.perf_counter()
    start, stop = frame_range(args.frames) if args.frames else (0, None)
    d = src.dim
    if args.k is None:
        from ._analyze import default_k  # _analyze imports this module

        args.k = default_k(d)
    landscape = load_landscape(args.landscape, d)[0] if args.landscape else None
    box = src.box if args.box is None else (np.full(d, args.box[0]), np.full(d, args.box[1]))
    periodic = True if args.periodic else src.periodic
    if args.graph == "delaunay" and d not in (2, 3):
        raise ValueError(
            f"{args.trajectory} holds {d}D walkers: Delaunay observables need 2 or 3 dimensions; give --graph knn."
        )
    params = jaxgeom.SwarmParams(eps_sigma=args.eps_sigma)
    interrupted = False
    try:
        history = jaxgeom.analyze_trajectory(
            src,
            landscape=landscape,
            box=box,
            periodic=periodic,
            params=params,
            every=args.every,
            start=start,
            stop=stop,
            graph=args.graph,
            k=args.k,
            spectral_gap_every=args.gap_every,
            dtype=args.precision,
            progress="auto",
        )
    except TrajectoryInterrupted as stop_early:
        history, interrupted = stop_early.history, True
        if not len(history["frame"]):
            raise KeyboardInterrupt from None
    return {
        "history": history,
        "landscape": landscape,
        "params": params,
        "box": box,
        "periodic": periodic,
        "n_frames": src.n_frames,
        "interrupted": interrupted,
        "seconds_total": time.perf_counter() - start_time,
    }


def observable_series(history: dict) -> dict:
    """{name: (T',)} of the observables measured, and "time"."""
    skip = {"frame", "step", "time", "unavailable", "n_reallocations", "seconds_rebuild", "seconds_steps"}
    series = {
        name: np.asarray(v) for name, v in history.items() if name not in skip and not name.startswith("spectral_")
    }
    series["time"] = np.asarray(history["time"])
    return series


def trajectory_table(result: dict, args) -> str:
    """`simulate`'s table over the analysed frames, the observables the file cannot give with
    the reason, and where the time went."""
    h = result["history"]
    rows, names = observable_rows(observable_series(h))
    gap = {
        "spectral_gap": h["spectral_gap"],
        "spectral_components": h["spectral_components"],
        "spectral_gap_rounding": h["spectral_gap_rounding"],
    }
    if gap["spectral_gap"].size:
        rows += _gap_rows(gap)
        names += ["spectral_gap", "kernel_graph_components"]
        at = h["frame"][h["spectral_gap_step"]]
        rows.append(
            f"spectral_gap and kernel_graph_components measured at frames {_steps(at)}"
            + (
                f"; at rounding level at frames {_steps(at[gap['spectral_gap_rounding']])}"
                if gap["spectral_gap_rounding"].any()
                else ""
            )
            + "."
        )
    for name, why in h["unavailable"].items():
        rows.append(f"not measured: {name}: {why}")
    frames = h["frame"]
    of = f" of {result['n_frames']}" if result["n_frames"] is not None else ""
    other = result["seconds_total"] - float(h["seconds_rebuild"]) - float(h["seconds_steps"])
    rows.append(
        f"frames analysed {len(frames)}{of} ({frames[0]} to {frames[-1]}, every {args.every}), capacity "
        f"reallocations {int(h['n_reallocations'])}, time {result['seconds_total']:.1f} s = reading and "
        f"graphs {float(h['seconds_rebuild']):.1f} s + observables (incl. compile) "
        f"{float(h['seconds_steps']):.1f} s + other {other:.1f} s"
    )
    if args.explain:
        rows += ["", "Rows (initial and final: the first and last analysed frame):"]
        rows += [f"  {name:<26}{simulate_definition(name)}" for name in names] + [UNITS]
    else:
        rows.append("--explain defines every row and its unit.")
    return "\n".join(rows)


def write_trajectory_outputs(result: dict, args, src: _Source) -> dict:
    out, h = args.out, result["history"]
    out.mkdir(parents=True, exist_ok=True)
    series = observable_series(h)
    gap_index = np.asarray(h["spectral_gap_step"], int)
    gap_at = {
        "frame": h["frame"][gap_index].tolist(),
        "step": h["step"][gap_index].tolist(),
        "time": h["time"][gap_index].tolist(),
    }
    config = {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}
    payload = {
        "source": str(args.trajectory),
        "config": config,
        "frame": h["frame"].tolist(),
        "step": h["step"].tolist(),
        "series": {k: _json_ready(v) for k, v in series.items()},
        "spectral_gap": gap_at
        | {
            "value": _json_ready(h["spectral_gap"]),
            "components": h["spectral_components"].tolist(),
            "at_rounding_level": h["spectral_gap_rounding"].tolist(),
        },
        "unavailable": h["unavailable"],
        "interrupted": result["interrupted"],
        "n_reallocations": int(h["n_reallocations"]),
        "seconds_total": result["seconds_total"],
        "seconds_rebuild": float(h["seconds_rebuild"]),
        "seconds_steps": float(h["seconds_steps"]),
    }
    (out / "observables.json").write_text(json.dumps(payload, indent=1))
    h5 = {name: (values, h["step"], h["time"]) for name, values in series.items() if name != "time"}
    if gap_index.size:
        h5["spectral_gap"] = (h["spectral_gap"], gap_at["step"], gap_at["time"])
        h5["kernel_graph_components"] = (h["spectral_components"], gap_at["step"], gap_at["time"])
    written = {"observables": str(out / "observables.json")}
    try:
        written["h5md"] = str(write_h5md_observables(out / "observables.h5md", h5, creator_version=jaxgeom.__version__))
    except ImportError as err:  # h5py missing: the rest is still written
        print(f"jaxgeom analyze: observables.h5md not written: {err}", file=sys.stderr)
    written["figure"] = str(
        plot_observables(
            series,
            gap_index,
            h["spectral_gap"],
            out / "observables.png",
            gap_rounding=h["spectral_gap_rounding"],
            gap_times=gap_at["time"],
            time_label="time (of the recorded frames)",
        )
    )
    written["swarm"] = str(write_swarm(result, args, src, out / "swarm.png"))
    return written


def write_swarm(result: dict, args, src: _Source, path: Path) -> Path:
    """swarm.png of `--snapshots` frames spread over those analysed, coloured by the Ricci scalar
    of the Hessian metric with a landscape, else by the recorded fitness, else by the cells'
    volumes (k-NN: the distance to the k-th neighbour), log10."""
    h, landscape = result["history"], result["landscape"]
    frames = h["frame"]
    pick = np.unique(np.round(np.linspace(0, len(frames) - 1, min(args.snapshots, len(frames)))).astype(int))
    box = result["box"]
    snapshots = [
        _snapshot(
            src.frame(int(frames[i])),
            int(frames[i]),
            int(h["step"][i]),
            landscape,
            result["params"],
            box,
            result["periodic"],
            args,
        )
        for i in pick
    ]
    colour = snapshots[0].pop("colour")
    for snap in snapshots[1:]:
        snap.pop("colour")
    everything = np.concatenate([s["positions"][:, :2] for s in snapshots])
    lower, upper = (
        (everything.min(axis=0), everything.max(axis=0))
        if box is None
        else (
            np.broadcast_to(np.asarray(box[0], float), (src.dim,))[:2],
            np.broadcast_to(np.asarray(box[1], float), (src.dim,))[:2],
        )
    )
    return plot_swarm_snapshots(landscape, snapshots, (lower, upper), path, colour=colour)


def _snapshot(frame: dict, t: int, step: int, landscape, params, box, periodic, args) -> dict:
    x = np.asarray(frame["positions"], np.dtype(args.precision))
    snap: dict[str, Any] = {"step": f"{step} (frame {t})", "positions": x, "ricci": None, "colour": None}
    tess = jaxgeom.delaunay(x, box=box, periodic=periodic) if args.graph == "delaunay" else None
    if landscape is not None:
        if tess is not None:
            snap["ricci"] = np.asarray(
                jaxgeom.ricci_scalar(tess, metric=metric_field(landscape, params, params.eps_sigma, x))
            )
        return snap
    if "fitness" in frame:
        snap.update(
            values=np.asarray(frame["fitness"], float),
            colour=("V at the walkers (recorded)", "walkers coloured by their recorded fitness V"),
        )
    elif tess is not None:
        volumes = np.asarray(jaxgeom.voronoi_volumes(tess), float)
        snap.update(
            values=np.log10(np.where(volumes > 0, volumes, np.nan)),
            colour=(
                "log10 Voronoi cell volume",
                "walkers coloured by their Voronoi cell's volume (black: unbounded hull cells)",
            ),
        )
    else:
        from scipy.spatial import cKDTree

        shift = np.zeros(x.shape[1]) if box is None else np.broadcast_to(np.asarray(box[0], float), (x.shape[1],))
        held, size = x - shift, None
        if periodic:
            size = np.broadcast_to(np.asarray(box[1], float), (x.shape[1],)) - shift
            held = np.mod(held, size)
        kth = cKDTree(held, boxsize=size).query(held, k=args.k + 1)[0][:, -1]
        snap.update(
            values=np.log10(kth),
            colour=(
                f"log10 distance to the {args.k}th neighbour",
                f"walkers coloured by the distance to their {args.k}th neighbour",
            ),
        )
    return snap


def trajectory_main(args) -> int:
    """The trajectory is opened once: read for the analysis, then for swarm.png's frames."""
    try:
        src = _Source(args.trajectory)
    except (ValueError, TypeError, OSError, ImportError) as err:
        print(f"jaxgeom analyze: error: {err}", file=sys.stderr)
        return 2
    try:
        return _report(args, src)
    finally:
        src.close()


def _report(args, src: _Source) -> int:
    try:
        result = run_trajectory(args, src)
    except (ValueError, TypeError, OSError, ImportError) as err:
        print(f"jaxgeom analyze: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxgeom analyze: interrupted before the first frame; nothing written", file=sys.stderr)
        return INTERRUPTED
    print(trajectory_table(result, args))
    if args.out is not None:
        for name, path in write_trajectory_outputs(result, args, src).items():
            print(f"wrote {name}: {path}")
    if result["interrupted"]:
        print(
            f"jaxgeom analyze: interrupted after frame {int(result['history']['frame'][-1])}"
            + ("; the frames analysed are written" if args.out is not None else ""),
            file=sys.stderr,
        )
        return INTERRUPTED
    return 0
