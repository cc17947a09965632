"""The `jaxgeom` console script: `jaxgeom simulate` runs a swarm on a landscape
(`_simulate.py`); `jaxgeom analyze` tessellates one swarm and reports its geometry
(`_analyze.py`); `jaxgeom tune` tunes nu and eps_Sigma by gradient through whole simulations
(`_tune.py`). All refuse bad arguments before any work (`check_arguments`)."""

from __future__ import annotations

import argparse
import os

import jax
import numpy as np

from ..base._progress import deferred_interrupt
from ._analyze import add_analyze_parser, analyze_main
from ._simulate import add_simulate_parser, simulate_main
from ._tune import add_tune_parser, tune_main


PRECISIONS = ("float64", "float32")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxgeom", description="Geometry of walker swarms.")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in (add_analyze_parser(sub), add_simulate_parser(sub), add_tune_parser(sub)):
        command.add_argument("--precision", choices=PRECISIONS, default="float64",
                             help="floating-point type of the computation")
    return parser


def check_arguments(parser: argparse.ArgumentParser, args) -> None:
    """Refuse bad numbers and an unusable --out before any work (argparse's exit code 2)."""
    rules = [("eps_sigma", "--eps-sigma", 0.0, None), ("seed", "--seed", 0, None), ("n", "--n", 1, None),
             ("clone_rate", "--clone-rate", 0.0, 1.0), ("nu", "--nu", 0.0, None), ("gap_every", "--gap-every", 0, None),
             ("beta", "--beta", 0.0, None), ("k", "--k", 1, None), ("seeds", "--seeds", 1, None),
             ("max_steps", "--max-steps", 1, None), ("steps", "--steps", 1, None)]
    for attr, flag, low, high in rules:
        value = getattr(args, attr, None)
        if value is not None and not (np.isfinite(value) and value >= low and (high is None or value <= high)):
            bounds = f">= {low}" + (f" and <= {high}" if high is not None else "")
            parser.error(f"{flag} must be a finite number {bounds}; got {value}")
    if getattr(args, "out", None) is not None:
        out = args.out
        if out.exists() and not out.is_dir():
            parser.error(f"--out {out} is an existing file; give a directory")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            parser.error(f"--out {out} cannot be created: {err.strerror}")
        if not os.access(out, os.W_OK):
            parser.error(f"--out {out} is not writable")


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args)

    jax.config.update("jax_enable_x64", args.precision == "float64")
    if args.command == "analyze":  # no iterations to stop between: Ctrl-C as usual
        return analyze_main(args)
    with deferred_interrupt():  # Ctrl-C ends simulate / tune at the next step or iteration
        return {"simulate": simulate_main, "tune": tune_main}[args.command](args)
