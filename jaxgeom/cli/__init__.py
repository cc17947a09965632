"""The `jaxgeom` console script: `jaxgeom simulate` runs a swarm on a landscape
(`_simulate.py`); `jaxgeom analyze` tessellates one swarm and reports its geometry
(`_analyze.py`); `jaxgeom tune` tunes nu and eps_Sigma by gradient through whole simulations
(`_tune.py`). All refuse bad arguments before any work (`check_arguments`)."""

from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
from pathlib import Path

import jax
import numpy as np

from ..base._progress import deferred_interrupt
from ._analyze import add_analyze_parser, analyze_main
from ._simulate import INTERRUPTED, add_simulate_parser, simulate_main
from ._tune import add_tune_parser, tune_main

PRECISIONS = ("float64", "float32")
# JAX's persistent compilation cache: the command line's programs are compiled once per machine
# and read back afterwards (the README's first command: its second run takes ~half the first).
CACHE_ENV, CACHE_DIR_ENV = "JAXGEOM_COMPILE_CACHE", "JAXGEOM_COMPILE_CACHE_DIR"
CACHE_CAP_BYTES = 1 << 30  # past this, the oldest entries go until half of it is left


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxgeom", description="Geometry of walker swarms.")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in (add_analyze_parser(sub), add_simulate_parser(sub), add_tune_parser(sub)):
        command.add_argument(
            "--precision", choices=PRECISIONS, default="float64", help="floating-point type of the computation"
        )
        command.add_argument(
            "--compile-cache",
            action=argparse.BooleanOptionalAction,
            default=None,
            help=f"keep compiled programs in {default_cache_dir()} (or ${CACHE_DIR_ENV}) and reuse "
            f"them in later runs (None: on unless ${CACHE_ENV}=0)",
        )
    return parser


def default_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(os.environ.get(CACHE_DIR_ENV) or Path(base) / "jaxgeom" / "xla")


def machine_tag() -> str:
    """A short name for this CPU's instruction set: compiled CPU programs run only where every
    feature they were built for exists, so a cache shared between machines (a network home)
    keeps one folder per tag."""
    flags = None
    try:
        with open("/proc/cpuinfo") as info:
            flags = next((line for line in info if line.startswith(("flags", "Features"))), None)
    except OSError:
        pass
    if flags is None:  # not Linux; platform.processor() starts a process on some systems
        flags = platform.processor()
    return hashlib.sha1(f"{platform.machine()} {flags}".encode()).hexdigest()[:12]


def use_compile_cache(choice) -> Path | None:
    """Switch on JAX's persistent compilation cache for this process (the command line only:
    the library never changes JAX's settings), unless --no-compile-cache or $JAXGEOM_COMPILE_CACHE=0.
    An unusable directory only costs the cache. Returns the directory, or None."""
    if choice is None:
        choice = os.environ.get(CACHE_ENV, "1").strip().lower() not in ("0", "false", "no", "off")
    if not choice:
        return None
    path = default_cache_dir() / machine_tag()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    prune_cache(path)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def check_arguments(parser: argparse.ArgumentParser, args) -> None:
    """Refuse bad numbers and an unusable --out before any work (argparse's exit code 2)."""
    rules = [
        ("eps_sigma", "--eps-sigma", 0.0, None),
        ("seed", "--seed", 0, None),
        ("n", "--n", 1, None),
        ("clone_rate", "--clone-rate", 0.0, 1.0),
        ("nu", "--nu", 0.0, None),
        ("gap_every", "--gap-every", 0, None),
        ("beta", "--beta", 0.0, None),
        ("k", "--k", 1, None),
        ("seeds", "--seeds", 1, None),
        ("max_steps", "--max-steps", 1, None),
        ("steps", "--steps", 1, None),
        ("every", "--every", 1, None),
        ("snapshots", "--snapshots", 1, None),
    ]
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


def prune_cache(path: Path, cap: int = CACHE_CAP_BYTES) -> None:
    """Keep the cache directory under `cap` bytes: past it, remove the least recently written
    entries until half of it is left (JAX's own size limit needs the `filelock` package)."""
    try:
        entries = sorted((p.stat().st_mtime, p.stat().st_size, p) for p in path.iterdir() if p.is_file())
    except OSError:
        return
    total = sum(size for _, size, _ in entries)
    if total <= cap:
        return
    for _, size, entry in entries:  # the oldest first
        if total <= cap // 2:
            break
        entry.unlink(missing_ok=True)
        total -= size


def main(argv=None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    try:
        jax.config.update("jax_enable_x64", args.precision == "float64")
        if use_compile_cache(args.compile_cache) is not None and argv is None:
            quiet_false_cache_alarms()
    except KeyboardInterrupt:  # before the command began: one line and 130, as once it runs
        print(f"jaxgeom {args.command}: interrupted before it began; nothing written", file=sys.stderr)
        return INTERRUPTED
    if args.command == "analyze":  # no iterations to stop between: Ctrl-C as usual
        return analyze_main(args)
    with deferred_interrupt():  # Ctrl-C ends simulate / tune at the next step or iteration
        return {"simulate": simulate_main, "tune": tune_main}[args.command](args)


def quiet_false_cache_alarms() -> None:
    """jaxlib (0.8-0.10 at least) logs an ERROR "... could lead to execution errors such as
    SIGILL" for every CPU program read back from the cache: it takes LLVM's tuning flags
    +prefer-no-gather/-scatter for CPU features the host lacks (jax-ml/jax#38445), hundreds of
    lines per warm run. The cache has one folder per CPU type (`machine_tag`), so the alarm is
    false. XLA reads its log level once, when jaxlib loads, so the command starts again (the same
    process, `exec`, ~1.5 s) with XLA's C++ log at FATAL only; errors that matter raise in
    Python. Not where TF_CPP_MIN_LOG_LEVEL is set to another level than jax's default (1), nor
    for in-process calls of `main`."""
    if os.name != "posix" or os.environ.get("TF_CPP_MIN_LOG_LEVEL", "1") != "1" or not getattr(sys, "orig_argv", None):
        return
    os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(sys.executable, [sys.executable, *sys.orig_argv[1:]])
