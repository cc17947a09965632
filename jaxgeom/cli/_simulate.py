"""`jaxgeom simulate`: run a swarm on a landscape, print a summary, write a time series and figures."""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxgeom

from ..apps._landscapes import LANDSCAPES
from ..apps._plots import plot_observables, plot_swarm_snapshots
from ..base._progress import close_bar, open_bar, take_interrupt
from ..geometry._forces import VISCOUS_WEIGHTS
from ..swarm._drivers import SimulationInterrupted
from ..swarm._dynamics import metric_field
from ..swarm._observables import OBSERVABLE_TABLE, SCUTOID_OBSERVABLES
from ..swarm._swarm_init import check_traceable_fitness
from ..tessellation._triangulators import TRIANGULATORS, resolve_triangulator
from ._legend import UNITS, simulate_definition

N_SNAPSHOTS = 4  # figure panels at t = 0, T/3, 2T/3, T
INTERRUPTED = 130  # the shell's exit status for SIGINT (128 + 2)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help shows every option's default and keeps the description's line breaks."""


def add_progress_flag(parser) -> None:
    parser.add_argument(
        "--progress",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="a progress bar on stderr (None: only when stderr is a terminal)",
    )


def progress_choice(args):
    """The `progress` argument of jaxgeom.simulate / tune for --progress / --no-progress."""
    return "auto" if args.progress is None else args.progress


SIMULATE_DESCRIPTION = """\
Run N walkers on a landscape: underdamped Langevin dynamics with the scutoidal viscous force
and Fractal Gas cloning, the Delaunay (or k-NN) graph rebuilt as they move; print a table of
the observables, and with --out write history.json, swarm.png and observables.png.

The command line's defaults (temperature 1, gamma 2) are hotter and more damped than
jaxgeom.SwarmParams' (temperature 0.1, gamma 1): the built-in landscapes span boxes of half
width 2 to 5.12 with barriers of order 10, which a swarm at T = 0.1 does not cross within a
few hundred steps. The library's defaults suit a unit-scale landscape."""


def add_simulate_parser(sub) -> argparse.ArgumentParser:
    sim = sub.add_parser(
        "simulate",
        help="run a swarm (Langevin + viscous force + cloning) on a landscape",
        description=SIMULATE_DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    sim.add_argument(
        "--landscape",
        default="rastrigin",
        help=f"one of {', '.join(sorted(LANDSCAPES))}, or a .py file defining V(x) (and optionally "
        "BOX = (lower, upper))",
    )
    sim.add_argument("--n", type=int, default=3000, help="walkers")
    sim.add_argument("--dim", type=int, default=2, help="2 or 3 (higher with --graph knn)")
    sim.add_argument("--steps", type=int, default=300, help="time steps")
    sim.add_argument("--dt", type=float, default=0.01, help="time step")
    sim.add_argument("--gamma", type=float, default=2.0, help="friction (SwarmParams default: 1.0)")
    sim.add_argument("--temperature", type=float, default=1.0, help="temperature T (SwarmParams default: 0.1)")
    sim.add_argument("--weights", default="kernel", choices=VISCOUS_WEIGHTS, help="viscous edge weights")
    sim.add_argument("--nu", type=float, default=0.1, help="viscous coupling nu")
    sim.add_argument(
        "--eps-sigma",
        type=float,
        default=0.1,
        help="Hessian-metric floor eps_Sigma (curvature, metric weights, --anisotropic)",
    )
    sim.add_argument("--clone-rate", type=float, default=0.1, help="scale of the cloning probability, in [0, 1]")
    sim.add_argument("--cloning", action=argparse.BooleanOptionalAction, default=True, help="Fractal Gas cloning")
    sim.add_argument("--anisotropic", action="store_true", help="diffusion D = g^-1 (adaptive gas)")
    sim.add_argument("--graph", choices=["delaunay", "knn"], default="delaunay", help="neighbour graph")
    sim.add_argument("--k", type=int, default=12, help="neighbours with --graph knn")
    sim.add_argument(
        "--triangulator",
        choices=TRIANGULATORS,
        default="auto",
        help="host Delaunay backend (auto: the fastest installed; jaxgeom.delaunay)",
    )
    sim.add_argument("--rebuild-every", type=int, default=1, help="steps between graph rebuilds")
    sim.add_argument("--gap-every", type=int, default=50, help="spectral gap every M steps (0: off)")
    sim.add_argument("--explain", action="store_true", help="define every row of the table, with its unit")
    sim.add_argument(
        "--scutoids",
        action="store_true",
        help="also observe each step's scutoids (jaxgeom.scutoids): the fractions of prisms, simple "
        "and complex scutoids among the walkers tier 2 at both steps, and their mean neighbour "
        "change (Delaunay graphs)",
    )
    sim.add_argument("--seed", type=int, default=0, help="seed of the initial swarm and the noise")
    sim.add_argument("--out", type=Path, help="directory for history.json, swarm.png, observables.png")
    sim.add_argument(
        "--trajectory",
        action="store_true",
        help="also write DIR/trajectory.h5md (H5MD: positions, velocities, fitness and clone parents "
        "every --save-every steps (clone parents with --save-every 1 only: a state holds its "
        "last step's), the observables' series); needs --out and h5py "
        "(pip install 'jaxgeom[h5md]')",
    )
    sim.add_argument("--save-every", type=int, default=1, help="steps between saved frames with --trajectory")
    add_progress_flag(sim)
    return sim


def load_landscape(spec: str, dim: int):
    """(V, (lower, upper)) for a built-in name or a user .py file defining V."""
    if spec in LANDSCAPES:
        fitness, _, half = LANDSCAPES[spec]
        return fitness, (-half, half)
    path = Path(spec)
    if path.suffix != ".py" or not path.is_file():
        raise ValueError(
            f"--landscape must be one of {', '.join(sorted(LANDSCAPES))} or an existing .py file "
            f"defining V(x); got {spec!r}."
        )
    module_spec = importlib.util.spec_from_file_location("jaxgeom_user_landscape", path)
    if module_spec is None or module_spec.loader is None:  # not for a .py file that exists
        raise ValueError(f"--landscape {path} cannot be loaded as a Python module.")
    module = importlib.util.module_from_spec(module_spec)
    try:
        module_spec.loader.exec_module(module)
    except Exception as err:  # the user's file: a syntax error, a failing import, ...
        raise ValueError(f"--landscape {path} could not be loaded: {type(err).__name__}: {err}") from None
    if not callable(getattr(module, "V", None)):
        raise ValueError(f"{path} must define a function V(x) mapping a ({dim},) array to a scalar.")
    try:
        check_traceable_fitness(module.V, dim, jnp.zeros(0).dtype)
    except TypeError as err:  # say which file
        raise ValueError(f"V in {path}: {err}".replace("`fitness` must", "it must")) from None
    return module.V, landscape_box(getattr(module, "BOX", (-3.0, 3.0)), path)


def landscape_box(box, path) -> tuple[float, float]:
    """BOX = (lower, upper) of a landscape file: two finite numbers, lower < upper."""
    try:
        lo, hi = (float(b) for b in box)
    except (TypeError, ValueError):
        raise ValueError(f"BOX in {path} must be (lower, upper), two numbers; got {box!r}.") from None
    if not (np.isfinite(lo) and np.isfinite(hi) and lo < hi):
        raise ValueError(f"BOX in {path} must satisfy lower < upper (finite); got {box!r}.")
    return lo, hi


def _validate(args) -> None:
    if args.n < 10 or args.steps < 1 or args.rebuild_every < 1:
        raise ValueError(
            f"need --n >= 10, --steps >= 1, --rebuild-every >= 1; got {args.n}, {args.steps}, {args.rebuild_every}."
        )
    if args.graph == "delaunay" and args.dim not in (2, 3):
        raise ValueError(f"--dim {args.dim} needs --graph knn (Delaunay simulations run in 2 or 3 dimensions).")
    if args.gap_every < 0:
        raise ValueError(f"--gap-every must be >= 0 (0: no spectral gap); got {args.gap_every}.")
    if args.scutoids and args.graph != "delaunay":
        raise ValueError("--scutoids needs --graph delaunay: scutoids join Voronoi cells, which a k-NN graph has not.")
    if args.gap_every % args.rebuild_every:
        raise ValueError("--gap-every must be a multiple of --rebuild-every.")
    if args.graph == "delaunay":
        resolve_triangulator(args.triangulator, args.dim)  # installed, and built for this dimension
    if args.trajectory and args.out is None:
        raise ValueError("--trajectory writes DIR/trajectory.h5md: give --out DIR.")
    if args.save_every < 1 or args.save_every % args.rebuild_every:
        raise ValueError(f"--save-every must be a positive multiple of --rebuild-every; got {args.save_every}.")


def run_simulation(args) -> dict:
    _validate(args)
    fitness, (lo, hi) = load_landscape(args.landscape, args.dim)
    dtype = np.dtype(args.precision)
    x0 = np.random.default_rng(args.seed).uniform(lo, hi, (args.n, args.dim)).astype(dtype)
    params = jaxgeom.SwarmParams(
        dt=args.dt,
        gamma=args.gamma,
        temperature=args.temperature,
        nu=args.nu,
        eps_sigma=args.eps_sigma,
        weights=args.weights,
        clone_rate=args.clone_rate,
        cloning=args.cloning,
        anisotropic=args.anisotropic,
    )
    start = time.perf_counter()
    state = jaxgeom.init_swarm(fitness, x0, key=args.seed, graph=args.graph, k=args.k, triangulator=args.triangulator)
    seconds_init = time.perf_counter() - start
    segment = args.rebuild_every * math.ceil(args.steps / (N_SNAPSHOTS - 1) / args.rebuild_every)
    snapshots, parts, done = [_snapshot(fitness, params, state, 0)], [], 0
    writer = _open_trajectory(args, state)
    bar, owned = open_bar(progress_choice(args), args.steps, "simulate")
    interrupted = False
    try:
        while done < args.steps:
            if writer is not None and done % args.save_every == 0:
                _save_frame(writer, state, done, args.dt)
            n = min(segment - done % segment, args.steps - done)
            if writer is not None:
                n = min(n, args.save_every - done % args.save_every)
            try:
                state, history = jaxgeom.simulate(
                    fitness,
                    state,
                    params,
                    n_steps=n,
                    observe=observed(args),
                    rebuild_every=args.rebuild_every,
                    spectral_gap_every=args.gap_every,
                    progress=bar if bar is not None else False,
                )
            except SimulationInterrupted as stop:  # Ctrl-C: keep the steps that ran
                state, history, n, interrupted = stop.state, stop.history, stop.steps, True
            parts.append((done, {key: np.asarray(value) for key, value in history.items()}))
            done += n
            if done % segment == 0 or done == args.steps or interrupted:
                snapshots.append(_snapshot(fitness, params, state, done))
            if interrupted:
                break
        if writer is not None and done % args.save_every == 0 and not interrupted:
            _save_frame(writer, state, done, args.dt)
        interrupted = interrupted or take_interrupt()  # a Ctrl-C in the last step or snapshot: all ran
    except KeyboardInterrupt:  # outside a simulate call (a snapshot): the segments so far
        interrupted = True
    finally:
        close_bar(bar, owned)
    if not parts:  # interrupted before the first segment returned anything
        if writer is not None:
            writer.close()
        raise KeyboardInterrupt
    result = _merge(parts, float(args.dt))
    if writer is not None:
        steps = np.arange(len(next(iter(result["series"].values()))))
        writer.write_observables(
            {k: v for k, v in result["series"].items() if k != "time"}, steps, float(args.dt) * steps
        )
        writer.close()
        result["trajectory"] = str(writer.path)
    result["interrupted_at"] = done if interrupted else None
    result.update(
        config={k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        seconds_total=time.perf_counter() - start,
        seconds_init=seconds_init,
        seconds_snapshots=sum(snap.pop("seconds") for snap in snapshots),
        snapshots=snapshots,
        fitness=fitness,
        box=(lo, hi),
        dtype=str(jnp.dtype(dtype)),
    )
    return result


def _open_trajectory(args, state):
    """The H5MD writer of --trajectory (None without it)."""
    if not args.trajectory:
        return None
    args.out.mkdir(parents=True, exist_ok=True)
    n, d = state.positions.shape
    # a state knows its last step's clone parents only: frames further apart would record a part
    elements = ("position", "velocity", "fitness") + (("parents",) if args.save_every == 1 else ())
    return jaxgeom.H5MDWriter(
        args.out / "trajectory.h5md", n, d, elements=elements, creator_version=jaxgeom.__version__
    )


def _save_frame(writer, state, step: int, dt: float) -> None:
    """The state entering `step` (the one its observables describe) as one H5MD frame."""
    data = {
        "position": state.positions,
        "velocity": state.velocities,
        "fitness": state.fitness,
        "parents": state.scutoid_trace.parents,
    }
    writer.append(step, step * dt, **{name: np.asarray(data[name]) for name in writer.elements})


def _snapshot(fitness, params, state, step: int) -> dict:
    """Positions and per-walker Ricci scalar (Hessian metric) of one state, for the figure."""
    start, ricci = time.perf_counter(), None
    if state.tess.simplices is not None:
        g = metric_field(fitness, params, params.eps_sigma * state.eps_factor, state.positions)
        ricci = np.asarray(jaxgeom.ricci_scalar(state.tess, metric=g))
    return {
        "step": step,
        "positions": np.asarray(state.positions),
        "ricci": ricci,
        "seconds": time.perf_counter() - start,
    }


def observed(args) -> tuple[str, ...]:
    """The observables of the run: the default set, and the scutoids' with --scutoids."""
    return jaxgeom.OBSERVABLES + (SCUTOID_OBSERVABLES if args.scutoids else ())


def _merge(parts, dt: float) -> dict:
    """Concatenate segment histories (each segment's last entry is the next one's first)."""
    names = [k for k in parts[0][1] if k in jaxgeom.ALL_OBSERVABLES]
    series = {name: np.concatenate([h[name][:-1] for _, h in parts] + [parts[-1][1][name][-1:]]) for name in names}
    series["time"] = dt * np.arange(len(series[names[0]]))
    gap_steps = np.concatenate([done + h["spectral_gap_step"] for done, h in parts])
    gaps = np.concatenate([h["spectral_gap"] for _, h in parts])
    components = np.concatenate([h["spectral_components"] for _, h in parts])
    rounding = np.concatenate([h["spectral_gap_rounding"] for _, h in parts])
    keep = np.r_[True, np.diff(gap_steps) > 0] if gap_steps.size else np.zeros(0, bool)
    return {
        "series": series,
        "spectral_gap_step": gap_steps[keep],
        "spectral_gap": gaps[keep],
        "spectral_components": components[keep],
        "spectral_gap_rounding": rounding[keep],
        "n_reallocations": int(sum(h["n_reallocations"] for _, h in parts)),
        "seconds_rebuild": float(sum(h["seconds_rebuild"] for _, h in parts)),
        "seconds_steps": float(sum(h["seconds_steps"] for _, h in parts)),
    }


def summary_table(result: dict, explain: bool = False) -> str:
    """The table `jaxgeom simulate` prints: one row per observable (initial, final, min, max),
    the spectral gap's rows, notes, a footer; with `explain`, every row's definition and unit."""
    skipped = delaunay_only(result)
    rows, names = observable_rows(result["series"], skipped)
    if result["spectral_gap"].size:
        rows += _gap_rows(result)
        names += ["spectral_gap", "kernel_graph_components"]
    if skipped:
        rows.append(f"Not reported on a k-NN graph (they need Voronoi cells, --graph delaunay): {', '.join(skipped)}.")
    if result["spectral_gap"].size:
        rows.append(
            f"spectral_gap and kernel_graph_components measured at steps {_steps(result['spectral_gap_step'])}"
            + (
                f"; at rounding level at steps {_steps(result['spectral_gap_step'][result['spectral_gap_rounding']])}"
                if result["spectral_gap_rounding"].any()
                else ""
            )
            + "."
        )
    rows.append(
        f"total clones {int(np.nansum(result['series'].get('n_clones', [0])))}, "
        f"capacity reallocations {result['n_reallocations']}, "
        f"time {result['seconds_total']:.1f} s = {timing_breakdown(result)}"
    )
    if explain:
        rows += ["", "Rows:"] + [f"  {name:<26}{simulate_definition(name)}" for name in names] + [UNITS]
    else:
        rows.append("--explain defines every row and its unit.")
    return "\n".join(rows)


def observable_rows(series: dict, skipped=()) -> tuple[list[str], list[str]]:
    """(rows, names): the header and one row per series (initial, final, min and max of its
    finite values), "time" and the `skipped` names left out."""
    rows, names = [f"{'observable':<26}{'initial':>12}{'final':>12}{'min':>12}{'max':>12}"], []
    for name, values in series.items():
        if name == "time" or name in skipped:
            continue
        finite = values[np.isfinite(values)]
        cells = [values[0], values[-1]] + ([finite.min(), finite.max()] if finite.size else [np.nan, np.nan])
        rows.append(f"{name:<26}" + "".join(f"{c:>12.5g}" for c in cells))
        names.append(name)
    return rows, names


def delaunay_only(result: dict) -> list[str]:
    """The observables of the series that need Voronoi cells, when the run's graph is k-NN."""
    if result["config"].get("graph") != "knn":
        return []
    return [name for name in result["series"] if name in OBSERVABLE_TABLE and OBSERVABLE_TABLE[name].geometric]


def _gap_rows(result: dict) -> list[str]:
    """The spectral gap (largest component of the kernel graph; "rounding" at rounding level) and
    that graph's component count, at the first and last measured step and their extremes."""
    gaps, comps, rounding = result["spectral_gap"], result["spectral_components"], result["spectral_gap_rounding"]
    resolved = gaps[~rounding & np.isfinite(gaps)]
    low = "rounding" if rounding.any() else (f"{resolved.min():.5g}" if resolved.size else "nan")
    high = f"{resolved.max():.5g}" if resolved.size else ("rounding" if rounding.any() else "nan")
    ends = ["rounding" if r else f"{g:.5g}" for g, r in zip(gaps[[0, -1]], rounding[[0, -1]], strict=True)]
    return [
        f"{'spectral_gap':<26}" + "".join(f"{c:>12}" for c in ends + [low, high]),
        f"{'kernel_graph_components':<26}{comps[0]:>12d}{comps[-1]:>12d}{comps.min():>12d}{comps.max():>12d}",
    ]


def _steps(steps) -> str:
    """A list of steps, the middle of a long one elided."""
    steps = [int(s) for s in steps]
    return (
        str(steps) if len(steps) <= 8 else f"[{', '.join(map(str, steps[:3]))}, ..., {', '.join(map(str, steps[-2:]))}]"
    )


def timing_breakdown(result: dict) -> str:
    """Where the wall time went; compilation of the step (the first call of each chunk length)
    is inside "steps", the per-walker Ricci maps' in "snapshots"."""
    parts = {
        "initial graph + compile": result["seconds_init"],
        "steps (incl. compile)": result["seconds_steps"],
        "graph rebuilds": result["seconds_rebuild"],
        "curvature snapshots": result["seconds_snapshots"],
    }
    parts["other (spectral gaps, end-of-chunk observables, their compilation)"] = result["seconds_total"] - sum(
        parts.values()
    )
    return " + ".join(f"{name} {seconds:.1f} s" for name, seconds in parts.items())


def _json_ready(values):
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values, float)]


def write_outputs(result: dict, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    payload = {
        "config": result["config"],
        "dtype": result["dtype"],
        "series": {k: _json_ready(v) for k, v in result["series"].items()},
        "spectral_gap": {
            "step": result["spectral_gap_step"].tolist(),
            "value": _json_ready(result["spectral_gap"]),
            "components": result["spectral_components"].tolist(),
            "at_rounding_level": result["spectral_gap_rounding"].tolist(),
        },
        "interrupted_at_step": result["interrupted_at"],
        "n_reallocations": result["n_reallocations"],
        "seconds_total": result["seconds_total"],
        "seconds_rebuild": result["seconds_rebuild"],
        "seconds_steps": result["seconds_steps"],
    }
    (out / "history.json").write_text(json.dumps(payload, indent=1))
    swarm = plot_swarm_snapshots(result["fitness"], result["snapshots"], result["box"], out / "swarm.png")
    series = plot_observables(
        result["series"],
        result["spectral_gap_step"],
        result["spectral_gap"],
        out / "observables.png",
        gap_rounding=result["spectral_gap_rounding"],
    )
    return {"history": str(out / "history.json"), "swarm": str(swarm), "observables": str(series)}


def say_interrupted(command: str, unit: str, at: int, total: int, written: bool | None) -> int:
    """Print the one line of a Ctrl-C'ed command and return the exit status 130; `written`:
    whether its --out got what ran (None: nothing ran)."""
    tail = {None: "; nothing written", True: f"; the {unit}s that ran are written", False: ""}[written]
    print(f"jaxgeom {command}: interrupted at {unit} {at} of {total}{tail}", file=sys.stderr)
    return INTERRUPTED


def simulate_main(args) -> int:
    try:
        result = run_simulation(args)
    except (ValueError, TypeError, OSError, FloatingPointError) as err:
        print(f"jaxgeom simulate: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # before the first step: nothing ran
        return say_interrupted("simulate", "step", 0, args.steps, None)
    print(summary_table(result, args.explain))
    if args.out is not None:
        for name, path in write_outputs(result, args.out).items():
            print(f"wrote {name}: {path}")
        if "trajectory" in result:
            print(f"wrote trajectory: {result['trajectory']}")
    if result["interrupted_at"] is not None:
        return say_interrupted("simulate", "step", result["interrupted_at"], args.steps, args.out is not None)
    return 0
