"""`jaxgeom tune`: tune nu (optionally eps_Sigma, dt, temperature) by gradient through whole
simulations, print the iterations and the values found with their standard errors, and with
--out write tune.json and tune.png.

By default it solves a problem with a known answer: it simulates the swarm at --true-nu
(eps_Sigma at --true-eps-sigma), records the seed-averaged velocity variance and mean
fitness over the second half of the run, and tunes nu from --nu on the loss that matches
them (`jaxgeom.simulation_loss(objective="match")`); the parameters not tuned are held at
their true values, so the loss is 0 at the truth. The defaults are chosen so that the
problem is identifiable and its loss smooth enough for a gradient method (measured,
bench/README.md "Tuning: recovery and error bars"): 10 steps of dt 0.05 (at 20 steps the
chaotic small-scale roughness of the loss stops BFGS 13% from the truth), one graph per
run (--rebuild-every: no Delaunay flip inside a run), anisotropic noise D = g^-1 (so the run
depends on eps_Sigma), 8 seeds. `--tune nu eps_sigma` tunes both: the two observables then
leave a valley (more nu and less eps_Sigma damp alike), which the standard errors show.
`--objective mean_fitness` (or final_fitness, best_fitness) tunes for the landscape instead.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxgeom

from ..apps._landscapes import LANDSCAPES
from ..base._progress import raise_if_interrupted, take_interrupt
from ..geometry._forces import VISCOUS_WEIGHTS
from ..geometry._metric import HESSIAN_FLOORS
from ..swarm._divergence import likely_cause
from ..swarm._tune import SOLVERS
from ..swarm._tuning import OBJECTIVES
from ._simulate import HelpFormatter, add_progress_flag, load_landscape, progress_choice, say_interrupted

TUNED_CHOICES = ("nu", "eps_sigma", "dt", "temperature")
MATCHED = ("velocity_variance", "mean_fitness")


def add_tune_parser(sub) -> argparse.ArgumentParser:
    tune = sub.add_parser(
        "tune",
        help="tune nu and eps_Sigma by gradient through whole simulations",
        description=__doc__,
        formatter_class=HelpFormatter,
    )
    tune.add_argument(
        "--landscape", default="rastrigin", help=f"one of {', '.join(sorted(LANDSCAPES))}, or a .py file defining V(x)"
    )
    tune.add_argument("--n", type=int, default=200, help="walkers per simulation")
    tune.add_argument("--dim", type=int, default=2, help="dimension of the walkers' space")
    tune.add_argument("--steps", type=int, default=10, help="steps of each simulation (longer runs: rougher losses)")
    tune.add_argument("--seeds", type=int, default=8, help="runs averaged per loss evaluation (vmapped)")
    tune.add_argument(
        "--rebuild-every",
        type=int,
        default=None,
        help="steps between graph rebuilds inside each simulation (None: --steps, one graph per "
        "run following the walkers, so no Delaunay flip breaks the loss's smoothness)",
    )
    tune.add_argument(
        "--tune",
        nargs="+",
        default=["nu"],
        choices=TUNED_CHOICES,
        metavar="NAME",
        help=f"parameters to tune, from {', '.join(TUNED_CHOICES)}",
    )
    tune.add_argument(
        "--objective",
        default="match",
        choices=OBJECTIVES,
        help="match: recover --true-* from their observables; the others: minimise that fitness",
    )
    tune.add_argument("--nu", type=float, default=0.05, help="viscous coupling nu: start value")
    tune.add_argument("--eps-sigma", type=float, default=0.2, help="Hessian-metric floor eps_Sigma: start value")
    tune.add_argument("--dt", type=float, default=0.05, help="time step: start value (fixed unless tuned)")
    tune.add_argument("--temperature", type=float, default=0.5, help="start value (fixed unless tuned)")
    tune.add_argument("--true-nu", type=float, default=0.3, help="objective match: the value to recover")
    tune.add_argument("--true-eps-sigma", type=float, default=0.05, help="objective match: the value to recover")
    tune.add_argument("--true-dt", type=float, default=None, help="objective match (None: --dt)")
    tune.add_argument("--true-temperature", type=float, default=None, help="objective match (None: --temperature)")
    tune.add_argument("--gamma", type=float, default=0.5, help="friction gamma")
    tune.add_argument("--weights", default="metric_full", choices=VISCOUS_WEIGHTS, help="viscous edge weights")
    tune.add_argument(
        "--floor",
        default="clip",
        choices=HESSIAN_FLOORS,
        help="the Hessian metric's floor: clip (max(lambda, 0) + eps_Sigma) or softabs (smooth)",
    )
    tune.add_argument(
        "--anisotropic",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="diffusion D = g^-1 (on: it makes the run depend on eps_Sigma)",
    )
    tune.add_argument(
        "--cloning",
        action=argparse.BooleanOptionalAction,
        default=False,
        help="cloning (off: its gradient is pathwise, selection held fixed)",
    )
    tune.add_argument("--graph", choices=["delaunay", "knn"], default="delaunay", help="neighbour graph")
    tune.add_argument(
        "--solver", default="bfgs", choices=SOLVERS, help="optimistix BFGS / nonlinear CG, or jaxopt's L-BFGS-B"
    )
    tune.add_argument("--max-steps", type=int, default=30, help="solver steps")
    tune.add_argument("--grid", type=int, default=6, help="contour grid points per axis in the figure (0: none)")
    tune.add_argument("--seed", type=int, default=0, help="seed of the initial swarm and the noise")
    tune.add_argument("--out", type=Path, help="directory for tune.json and tune.png")
    add_progress_flag(tune)
    return tune


def _validate(args) -> None:
    if args.n < 10 or args.steps < 2 or args.seeds < 1 or args.max_steps < 1 or args.grid < 0:
        raise ValueError(
            f"need --n >= 10, --steps >= 2, --seeds >= 1, --max-steps >= 1, --grid >= 0; got {args.n}, "
            f"{args.steps}, {args.seeds}, {args.max_steps}, {args.grid}."
        )
    if args.rebuild_every is not None and args.rebuild_every < 1:
        raise ValueError(f"--rebuild-every must be >= 1; got {args.rebuild_every}.")
    if len(set(args.tune)) != len(args.tune):
        raise ValueError(f"--tune names a parameter twice: {args.tune}.")
    for flag in ("dt", "temperature", "true_nu", "true_eps_sigma", "true_dt", "true_temperature"):
        value = getattr(args, flag)
        if value is not None and not (np.isfinite(value) and value > 0):
            raise ValueError(f"--{flag.replace('_', '-')} must be a finite number > 0; got {value}.")
    for flag in ("nu", "eps_sigma"):
        if flag in args.tune and not getattr(args, flag) > 0:
            raise ValueError(
                f"--{flag.replace('_', '-')} must be > 0 to be tuned (log parameters); got {getattr(args, flag)}."
            )


def _params(args, **values) -> jaxgeom.SwarmParams:
    fields = {"dt": args.dt, "temperature": args.temperature, "nu": args.nu, "eps_sigma": args.eps_sigma, **values}
    return jaxgeom.SwarmParams(
        gamma=args.gamma,
        weights=args.weights,
        anisotropic=args.anisotropic,
        cloning=args.cloning,
        floor=args.floor,
        **fields,
    )


def build_loss(args, target_key=None):
    """(loss, start values, true values or None) for the command line's problem. The targets of
    "match" come from the loss's own seeds (the loss is then 0 at the truth), or from the
    independent seeds of `target_key` (an int), as data would (bench/tune_coverage.py)."""
    _validate(args)
    fitness, (lo, hi) = load_landscape(args.landscape, args.dim)
    x0 = np.random.default_rng(args.seed).uniform(lo, hi, (args.n, args.dim)).astype(np.dtype(args.precision))
    state = jaxgeom.init_swarm(fitness, x0, key=args.seed, graph=args.graph)
    start = {name: getattr(args, name) for name in args.tune}
    common = dict(
        n_steps=args.steps, tuned=tuple(args.tune), n_seeds=args.seeds, rebuild_every=args.rebuild_every or args.steps
    )
    if args.objective != "match":
        return jaxgeom.simulation_loss(fitness, state, args.objective, params=_params(args), **common), start, None
    truth = {
        "nu": args.true_nu,
        "eps_sigma": args.true_eps_sigma,
        "dt": args.true_dt or args.dt,
        "temperature": args.true_temperature or args.temperature,
    }
    record = jaxgeom.simulation_loss(
        fitness,
        state,
        lambda h: h["mean_fitness"][-1],
        params=_params(args, **truth),
        observe=MATCHED,
        key=target_key,
        **common,
    )
    _, history = eqx.filter_jit(lambda loss, t: loss.histories(t))(record, record.to_theta())
    diverged = np.asarray(history["diverged_step"])
    if (diverged >= 0).any():
        cause = likely_cause(fitness, record.to_params(record.to_theta()), state).replace("reduce dt", "reduce --dt")
        raise ValueError(
            f"the simulation at the true values diverged by step {int(diverged[diverged >= 0].min())} "
            f"in {int((diverged >= 0).sum())} of {diverged.size} runs, so it gives no targets to match. "
            f"{cause}"
        )
    late = args.steps // 2
    targets = {name: float(np.mean(np.asarray(history[name])[:, late:])) for name in MATCHED}
    held = {name: value for name, value in truth.items() if name not in args.tune}  # the loss is 0 at the truth
    loss = jaxgeom.simulation_loss(fitness, state, "match", params=_params(args, **held), targets=targets, **common)
    return loss, start, {name: truth[name] for name in args.tune}


def loss_grid(loss, result, truth, points: int):
    """The loss on a points x points grid of the first two tuned parameters (log-spaced around
    the path and the truth), under one vmap; the others at the result's values."""
    names = loss.tuned[:2]
    seen = {name: [it["values"][name] for it in result.iterations] + ([truth[name]] if truth else []) for name in names}
    axes = [np.geomspace(min(seen[n]) / 1.5, max(seen[n]) * 1.5, points) for n in names]
    mesh = np.meshgrid(*axes, indexing="ij")
    values = [
        {**result.values, **{n: float(m.ravel()[i]) for n, m in zip(names, mesh, strict=True)}}
        for i in range(mesh[0].size)
    ]
    thetas = jnp.stack([loss.to_theta(v) for v in values])
    losses = eqx.filter_jit(lambda l, t: jax.vmap(l)(t))(loss, thetas)
    return {
        "names": list(names),
        "axes": [a.tolist() for a in axes],
        "loss": np.asarray(losses).reshape(mesh[0].shape).tolist(),
    }


def iteration_table(result, truth) -> str:
    names = list(result.values)
    rows = [f"{'iter':>4}{'loss':>14}{'|grad|':>12}" + "".join(f"{n:>14}" for n in names)]
    for it in result.iterations:
        rows.append(
            f"{it['iteration']:>4}{it['loss']:>14.6g}{it['grad_norm']:>12.3g}"
            + "".join(f"{it['values'][n]:>14.6g}" for n in names)
        )
    rows.append(f"{result.solver}: {result.message} after {result.n_steps} solver steps, {result.seconds:.1f} s")
    errors = result.standard_errors
    rows.append(
        "found:  " + "  ".join(f"{n}={result.values[n]:.6g} +- {errors.get(n, float('nan')):.2g}" for n in names)
    )
    rows.append(
        "+- one standard error (sandwich): the spread of fits to independent data of as many runs as --seeds"
        if not result.error_note
        else f"no standard errors: {result.error_note}"
    )
    if truth:
        rows.append(
            "true values:  "
            + "  ".join(f"{n}={v:.6g} ({100 * abs(result.values[n] / v - 1):.2f}% off)" for n, v in truth.items())
        )
        rows.append(
            "The loss is 0 at the true values: the targets come from the same seeds, and the parameters "
            "not tuned are held at their true values."
        )
    return "\n".join(rows)


def tune_main(args) -> int:
    """Every Ctrl-C ends in the same way, whenever it comes (while the targets compile, in any
    iteration, in the last one, while the grid is computed): the iterations that ran, the
    one-line message and exit status 130 (`take_interrupt` reads a Ctrl-C no loop consumed)."""
    began, interrupted = time.perf_counter(), None
    try:
        loss, start, truth = build_loss(args)
        raise_if_interrupted()  # a Ctrl-C while the targets were simulated (and compiled)
        result = jaxgeom.tune(
            loss,
            start,
            solver=args.solver,
            max_steps=args.max_steps,
            target_seeds=args.seeds,
            progress=progress_choice(args),
        )
    except (ValueError, TypeError, OSError, FloatingPointError) as err:
        print(f"jaxgeom tune: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:  # Ctrl-C: report and write the iterations accepted so far
        partial = getattr(stop, "result", None)
        if partial is None:
            return say_interrupted("tune", "iteration", 0, args.max_steps, None)
        result, interrupted = partial, len(partial.iterations) - 1
    grid = None
    if interrupted is None and args.out is not None and args.grid >= 2 and len(loss.tuned) >= 2:
        grid = loss_grid(loss, result, truth, args.grid)
    if interrupted is None and take_interrupt():  # after the last iteration: every iteration ran
        interrupted, grid = len(result.iterations) - 1, None
    print(iteration_table(result, truth))
    if args.out is not None:
        for name, path in write_outputs(args, result, truth, grid, time.perf_counter() - began).items():
            print(f"wrote {name}: {path}")
    if interrupted is not None:
        return say_interrupted("tune", "iteration", interrupted, args.max_steps, args.out is not None)
    return 0


def write_outputs(args, result, truth, grid, seconds: float) -> dict:
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    payload = {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "solver": result.solver,
        "message": result.message,
        "converged": result.converged,
        "values": result.values,
        "loss": result.loss,
        "truth": truth,
        "iterations": result.iterations,
        "n_steps": result.n_steps,
        "scale": result.scale,
        "grid": grid,
        "seconds_total": seconds,
        "standard_errors": result.standard_errors,
        "error_note": result.error_note,
    }
    (out / "tune.json").write_text(json.dumps(payload, indent=1, default=float))
    figure = plot_tuning(result, truth, grid, out / "tune.png")
    return {"json": str(out / "tune.json"), "figure": str(figure)}


def _sparse_log_ticks(ax) -> None:
    """Log axes spanning less than a decade label their minor ticks, which overlap: label
    1, 2, 5 x 10^k only."""
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator, NullFormatter

    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(LogFormatterSciNotation(labelOnlyBase=False))
        axis.set_minor_formatter(NullFormatter())


def plot_tuning(result, truth, grid, path) -> Path:
    from ..apps._plots import subplots

    fig, axes = subplots(1, 2, figsize=(11, 4.5))
    losses = [it["loss"] for it in result.iterations]
    axes[0].semilogy([it["iteration"] for it in result.iterations], np.maximum(losses, 1e-300), "o-")
    axes[0].set(xlabel="iteration", ylabel="loss", title=f"{result.solver}: {result.message}")
    names = list(result.values)[:2]
    if grid is not None:
        x, y = np.asarray(grid["axes"][0]), np.asarray(grid["axes"][1])
        z = np.log10(np.maximum(np.asarray(grid["loss"], float), 1e-300))
        contour = axes[1].contourf(x, y, z.T, levels=14, cmap="viridis")
        fig.colorbar(contour, ax=axes[1], label="log10 loss")
        axes[1].set(xscale="log", yscale="log")
        _sparse_log_ticks(axes[1])
    if len(names) == 2:
        path_x = [it["values"][names[0]] for it in result.iterations]
        path_y = [it["values"][names[1]] for it in result.iterations]
        axes[1].plot(path_x, path_y, "w.-", label="iterates")
        axes[1].plot(path_x[:1], path_y[:1], "ws", label="start")
        if truth:
            axes[1].plot([truth[names[0]]], [truth[names[1]]], "r*", ms=14, label="truth")
        axes[1].set(xlabel=names[0], ylabel=names[1], title="path over the loss")
        axes[1].legend(loc="best")
    else:
        axes[1].plot([it["values"][names[0]] for it in result.iterations], "o-", label="iterates")
        found, error = result.values[names[0]], result.standard_errors.get(names[0], float("nan"))
        if np.isfinite(error):
            axes[1].axhspan(found - error, found + error, color="C0", alpha=0.15, label="found +- 1 s.e.")
        if truth:
            axes[1].axhline(truth[names[0]], color="r", ls="--", label=f"truth {truth[names[0]]:.4g}")
        axes[1].set(xlabel="iteration", ylabel=names[0], title=f"{names[0]} against iteration")
        axes[1].legend(loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return Path(path)
