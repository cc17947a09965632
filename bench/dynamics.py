"""Swarm dynamics throughput, Qhull share, rebuild strategy, and the viscous force against numpy.

Run: python bench/dynamics.py [--sizes 10000 100000] [--out bench/results/dynamics.json]

All in float32 (the library default), 2D rastrigin swarm, default SwarmParams
(Langevin + kernel viscous force + cloning), in one run:

- steps per second at each N with rebuild every step and every 10 steps, with
  every observable and with only the fitness observables, and the share of the
  run's wall time spent inside Qhull (scipy's Delaunay constructor, clocked in
  the run). "Everything but Qhull" over Qhull (target <= 0.3 with rebuild every
  step) two ways: `rest_over_qhull_in_run` = (run time - Qhull time in the run)
  / Qhull time in the run, and `rest_over_qhull` with Qhull timed alone on each
  run's final positions instead (median of 5 calls). Medians of 3 timed runs, the
  runs themselves under "runs";
- rebuild strategy at the smallest N: host rebuild between scan chunks against
  a `jax.pure_callback` inside the scan (both rebuild every step);
- `jaxgeom.viscous_force` alone at N = --force-n (1e6) against a vectorized numpy
  gather implementation of the same formula (target >= 5x).

`--rebuild-modes host callback device` (issue 31's accelerator figures): only `simulate` with a
rebuild every step at each of --sizes, fitness observables, one rebuild mode per child process
(its own compilation, a timeout from --budget), the device named; results/dynamics_modes.json.

`--against REV [REV ...] [--rounds 3] [--only 2D]`: the N = 1e4 step configurations whose label
holds --only (2D: fitness observables, every observable, rebuild="callback"; 3D: fitness
observables) of this working tree against earlier commits, each tree in its own child process,
the trees alternating within each round, with bare Qhull on each run's final walkers;
results/dynamics_against.json.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.spatial

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin
from jaxgeom.tessellation._triangulators import MORTON_MIN_POINTS, QHULL_OPTIONS, morton_order

OBS_FITNESS = ("mean_fitness", "best_fitness", "n_clones")


def best_of(fn, repeats=3):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times)


class QhullClock:
    """Wall time spent inside scipy's Delaunay constructor (Qhull) while enabled."""

    module, name = jaxgeom.tessellation._triangulators, "Delaunay"

    def __init__(self):
        self.seconds, self.calls, self._real = 0.0, 0, getattr(self.module, self.name)

    def __enter__(self):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return self._real(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        setattr(self.module, self.name, timed)
        return self

    def __exit__(self, *exc):
        setattr(self.module, self.name, self._real)


class TriangulatorClock(QhullClock):
    """Wall time spent triangulating (the backend, its check, a fallback) while enabled."""

    module, name = jaxgeom.tessellation._delaunay, "triangulate"


def qhull_alone(positions, repeats=5) -> float:
    """Median seconds of scipy's Delaunay alone on the points as the builder hands them to
    Qhull (Morton-sorted from MORTON_MIN_POINTS on)."""
    x = np.asarray(positions, np.float64)
    if len(x) >= MORTON_MIN_POINTS:
        x = np.ascontiguousarray(x[morton_order(x)])
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        scipy.spatial.Delaunay(x, qhull_options=QHULL_OPTIONS)
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def run(state, params, n_steps, rebuild_every, observe, rebuild="host", repeats=3) -> dict:
    """A warm-up (same n_steps: a callback run compiles one scan over all of its steps), then
    `repeats` timed runs, each followed by Qhull alone on its final positions; medians and
    the per-run values (this VM's timings vary by up to ~30%)."""
    kwargs = dict(n_steps=n_steps, rebuild_every=rebuild_every, observe=observe, rebuild=rebuild)
    jaxgeom.simulate(rastrigin, state, params, **kwargs)
    per_step, in_run, alone = [], [], []
    for _ in range(repeats):
        with QhullClock() as clock:
            start = time.perf_counter()
            final, history = jaxgeom.simulate(rastrigin, state, params, **kwargs)
            jax.block_until_ready(final.positions)
            seconds = time.perf_counter() - start
        per_step.append(seconds / n_steps)
        in_run.append(clock.seconds / n_steps)
        alone.append(qhull_alone(final.positions) * clock.calls / n_steps)
    rest_alone = [(t - q) / q for t, q in zip(per_step, alone, strict=True)]
    rest_in_run = [(t - q) / q for t, q in zip(per_step, in_run, strict=True)]
    median = lambda values: float(np.median(values))  # noqa: E731
    return {
        "steps_per_second": 1.0 / median(per_step),
        "seconds_per_step": median(per_step),
        "qhull_seconds_per_step_in_run": median(in_run),
        "qhull_alone_seconds_per_step": median(alone),
        "qhull_share": median([q / t for t, q in zip(per_step, in_run, strict=True)]),
        "rest_over_qhull": median(rest_alone),
        "rest_over_qhull_in_run": median(rest_in_run),
        "runs": {"seconds_per_step": per_step, "rest_over_qhull": rest_alone, "rest_over_qhull_in_run": rest_in_run},
        "n_reallocations": int(history["n_reallocations"]),
    }


def throughput(n: int, n_steps: int) -> dict:
    rng = np.random.default_rng(0)
    state = jaxgeom.init_swarm(
        rastrigin, rng.uniform(-5.12, 5.12, (n, 2)).astype(np.float32), key=0, triangulator="qhull"
    )
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    row = {"n": n, "n_steps": n_steps}
    for observe, label in ((jaxgeom.OBSERVABLES, "all_observables"), (OBS_FITNESS, "fitness_observables")):
        for every in (1, 10):
            row[f"{label}_rebuild_every_{every}"] = run(state, params, n_steps, every, observe)
    print(json.dumps(row))
    return row


def rebuild_strategy(n: int, n_steps: int) -> dict:
    rng = np.random.default_rng(1)
    state = jaxgeom.init_swarm(
        rastrigin, rng.uniform(-5.12, 5.12, (n, 2)).astype(np.float32), key=0, triangulator="qhull"
    )
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    out = {"n": n, "n_steps": n_steps}
    for rebuild in ("host", "callback"):
        timed = run(state, params, n_steps, 1, OBS_FITNESS, rebuild)
        out[f"{rebuild}_seconds_per_step"] = timed["seconds_per_step"]
        out[f"{rebuild}_qhull_seconds_per_step_in_run"] = timed["qhull_seconds_per_step_in_run"]
        out[f"{rebuild}_qhull_alone_seconds_per_step"] = timed["qhull_alone_seconds_per_step"]
    print(json.dumps(out))
    return out


def timed_steps(state, params, n_steps, observe, rebuild, repeats=3) -> dict:
    """Seconds per step (rebuild every step): a first run (compilation included, timed apart),
    then `repeats` runs; median, min, max, the median time inside the triangulator per step,
    bare Qhull on the last run's final walkers (median of 5) and the step over it, and the
    fallbacks (host triangulator failures; device rebuilds not certified)."""
    kwargs = dict(n_steps=n_steps, rebuild_every=1, observe=observe, rebuild=rebuild)
    per_step, inside, fallbacks, device_fallbacks = [], [], [], []
    for _ in range(1 + repeats):
        with TriangulatorClock() as clock:
            start = time.perf_counter()
            final, history = jaxgeom.simulate(rastrigin, state, params, **kwargs)
            jax.block_until_ready(final.positions)
            per_step.append((time.perf_counter() - start) / n_steps)
        inside.append(clock.seconds / n_steps)
        fallbacks.append(int(history["n_triangulator_fallbacks"]))
        device_fallbacks.append(int(history["n_fallbacks"]))
    timed = per_step[1:]
    bare = qhull_alone(final.positions)
    return {
        "seconds_per_step": float(np.median(timed)),
        "bare_qhull_seconds": bare,
        "step_over_bare_qhull": float(np.median(timed)) / bare,
        "min": min(timed),
        "max": max(timed),
        "first_run_seconds": per_step[0] * n_steps,
        "triangulating_seconds_per_step": float(np.median(inside[1:])),
        "n_triangulator_fallbacks": sum(fallbacks[1:]),
        "device_fallbacks_per_run": device_fallbacks[1:],
    }


def triangulator_matrix(triangulators, configs) -> list:
    """Every configuration with each triangulator, side by side in this run (float32)."""
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    rows = []
    for label, d, n, n_steps, observe, rebuild in configs:
        rng = np.random.default_rng(0)
        x = rng.uniform(-5.12, 5.12, (n, d)).astype(np.float32)
        row = {"config": label, "dim": d, "n": n, "n_steps": n_steps, "rebuild": rebuild}
        for t in triangulators:
            backends = jaxgeom.tessellation._triangulators
            if t != "auto" and d not in backends.DIMENSIONS[t]:
                continue
            state = jaxgeom.init_swarm(rastrigin, x, key=0, triangulator=t)
            row[t] = dict(timed_steps(state, params, n_steps, observe, rebuild), backend=state.triangulator)
        base = row["qhull"]["seconds_per_step"]
        row["speedup_over_qhull"] = {t: base / row[t]["seconds_per_step"] for t in triangulators if t in row}
        print(
            json.dumps(
                {
                    "config": label,
                    **{t: round(v, 2) for t, v in row["speedup_over_qhull"].items()},
                    **{f"{t}_ms": round(1e3 * row[t]["seconds_per_step"], 2) for t in triangulators if t in row},
                    **{
                        f"{t}_over_bare_qhull": round(row[t]["step_over_bare_qhull"], 2)
                        for t in triangulators
                        if t in row
                    },
                }
            )
        )
        rows.append(row)
    return rows


MATRIX = [
    ("2D N=1e4 fitness observables", 2, 10_000, 20, OBS_FITNESS, "host"),
    ("2D N=1e4 every observable", 2, 10_000, 20, None, "host"),
    ("2D N=1e4 callback", 2, 10_000, 20, OBS_FITNESS, "callback"),
    ("2D N=1e5 fitness observables", 2, 100_000, 5, OBS_FITNESS, "host"),
    ("3D N=1e4 fitness observables", 3, 10_000, 10, OBS_FITNESS, "host"),
]


def one_mode(n: int, mode: str, n_steps: int, repeats: int) -> dict:
    """`timed_steps` of `simulate` (rebuild every step, fitness observables) in `mode`, with the
    device named."""
    x = np.random.default_rng(0).uniform(-5.12, 5.12, (n, 2)).astype(np.float32)
    state = jaxgeom.init_swarm(rastrigin, x, key=0)
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    timed = timed_steps(state, params, n_steps, OBS_FITNESS, mode, repeats=repeats)
    device = jax.devices()[0]
    return {
        "n": n,
        "rebuild": mode,
        "n_steps": n_steps,
        "triangulator": state.triangulator,
        "device": str(device),
        "device_kind": device.device_kind,
        **timed,
        "steps_per_second": 1.0 / timed["seconds_per_step"],
    }


def rebuild_modes(sizes, steps, modes, budget: float) -> list:
    """Each (size, mode) in a child process under what is left of `budget` seconds; a child
    that runs out is reported as timed out, not dropped."""
    rows, deadline = [], time.perf_counter() + budget
    for n, n_steps in zip(sizes, steps, strict=True):
        for mode in modes:
            left = deadline - time.perf_counter()
            if left <= 1.0:
                rows.append({"n": n, "rebuild": mode, "n_steps": n_steps, "skipped": "budget spent"})
                print(json.dumps(rows[-1]), flush=True)
                continue
            cmd = [sys.executable, __file__, "--one", str(n), mode, str(n_steps)]
            try:
                out = subprocess.run(cmd, capture_output=True, text=True, timeout=left)
                lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
                row = json.loads(lines[-1]) if lines else {"n": n, "rebuild": mode, "failed": out.stderr[-2000:]}
            except subprocess.TimeoutExpired:
                row = {"n": n, "rebuild": mode, "n_steps": n_steps, "timed_out_after_s": round(left, 1)}
            print(json.dumps(row), flush=True)
            rows.append(row)
    return rows


def numpy_viscous_force(x, v, nbrs, nu, ell):
    """Vectorized numpy gathers of the same formula (kernel mode), sentinel row appended."""
    n = len(x)
    mask = nbrs < n
    xp = np.concatenate([x, np.zeros((1, x.shape[1]), x.dtype)])
    vp = np.concatenate([v, np.zeros((1, v.shape[1]), v.dtype)])
    dx = xp[nbrs] - x[:, None, :]
    w = np.where(mask, np.exp(-np.sum(dx * dx, axis=-1) / (2 * ell * ell)), 0.0).astype(x.dtype)
    w = w / np.sum(w, axis=1, keepdims=True)
    return nu * (np.sum(w[..., None] * vp[nbrs], axis=1) - np.sum(w, axis=1, keepdims=True) * v)


def force_versus_numpy(n: int) -> dict:
    rng = np.random.default_rng(2)
    x = rng.random((n, 2)).astype(np.float32)
    v = rng.normal(size=(n, 2)).astype(np.float32)
    tess = jaxgeom.delaunay(x)
    ell = np.float32(0.01)
    vj = jnp.asarray(v)
    ours = jaxgeom.viscous_force(tess, vj, nu=0.1, weights="kernel", length_scale=ell)
    nbrs = np.asarray(tess.neighbors)
    ref = numpy_viscous_force(x, v, nbrs, np.float32(0.1), ell)
    t_jax = best_of(lambda: jaxgeom.viscous_force(tess, vj, nu=0.1, weights="kernel", length_scale=ell))
    t_np = best_of(lambda: numpy_viscous_force(x, v, nbrs, np.float32(0.1), ell))
    out = {
        "n": n,
        "capacity_neighbors": tess.capacity.neighbors,
        "jax_seconds": t_jax,
        "numpy_seconds": t_np,
        "speedup": t_np / t_jax,
        "max_abs_difference": float(np.max(np.abs(np.asarray(ours) - ref))),
    }
    print(json.dumps(out))
    return out


# Child of `--against`: one config's seconds per step with whatever jaxgeom is on PYTHONPATH,
# using only the public API and its own Rastrigin, so that any commit of the library runs it.
AGAINST_CHILD = """
import json, sys, time
import numpy as np, jax, jax.numpy as jnp
import jaxgeom
def rastrigin(x):
    return 10.0 * x.shape[0] + jnp.sum(x * x - 10.0 * jnp.cos(2.0 * jnp.pi * x))
d, n, steps, observe, rebuild, repeats = json.loads(sys.argv[1])
observe = jaxgeom.OBSERVABLES if observe is None else tuple(observe)
x = np.random.default_rng(0).uniform(-5.12, 5.12, (n, d)).astype(np.float32)
state = jaxgeom.init_swarm(rastrigin, x, key=0)
params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
times = []
for _ in range(1 + repeats):
    start = time.perf_counter()
    final, _ = jaxgeom.simulate(rastrigin, state, params, n_steps=steps, rebuild_every=1, observe=observe,
                                rebuild=rebuild)
    jax.block_until_ready(final.positions)
    times.append((time.perf_counter() - start) / steps)
import scipy.spatial
from jaxgeom.tessellation._triangulators import QHULL_OPTIONS
points, bare = np.asarray(final.positions, np.float64), []
for _ in range(5):  # bare Qhull on the final walkers, as `qhull_alone` (unsorted: N < MORTON_MIN_POINTS)
    start = time.perf_counter()
    scipy.spatial.Delaunay(points, qhull_options=QHULL_OPTIONS)
    bare.append(time.perf_counter() - start)
row = {"seconds_per_step": times[1:], "bare_qhull_seconds": float(np.median(bare)), "jaxgeom": jaxgeom.__file__}
print(json.dumps(row))
"""

AGAINST_CONFIGS = [
    ("2D N=1e4 fitness observables", 2, 10_000, 20, list(OBS_FITNESS), "host"),
    ("2D N=1e4 every observable", 2, 10_000, 20, None, "host"),
    ("2D N=1e4 callback", 2, 10_000, 20, list(OBS_FITNESS), "callback"),
    ("3D N=1e4 fitness observables", 3, 10_000, 10, list(OBS_FITNESS), "host"),
]


def against(revs, rounds: int, repeats: int = 3, only: str = "2D") -> dict:
    """The N = 1e4 step configurations whose label holds `only`, for this working tree and
    each commit in `revs` (checked out into temporary git worktrees), each run in its own
    child process with that tree's jaxgeom; the trees alternate within each of `rounds`
    rounds, so that a drift of the machine's speed reaches all of them alike. Per tree and
    config: every timed run's seconds per step, their median, min and max, bare Qhull on each
    child's final walkers and the median step over the median of those, and the median's
    ratio to each tree's."""
    import tempfile

    root = Path(__file__).resolve().parent.parent
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"working tree": root}
        for rev in revs:
            trees[rev] = Path(tmp) / rev
            subprocess.run(
                ["git", "-C", str(root), "worktree", "add", "--detach", "-f", str(trees[rev]), rev],
                check=True,
                capture_output=True,
            )
        try:
            configs = [c for c in AGAINST_CONFIGS if only in c[0]]
            runs = {label: {tree: [] for tree in trees} for label, *_ in configs}
            bare = {label: {tree: [] for tree in trees} for label, *_ in configs}
            for _ in range(rounds):
                for label, d, n, steps, observe, rebuild in configs:
                    for tree, path in trees.items():
                        env = dict(os.environ, PYTHONPATH=str(path))
                        out = subprocess.run(
                            [sys.executable, "-c", AGAINST_CHILD, json.dumps([d, n, steps, observe, rebuild, repeats])],
                            env=env,
                            capture_output=True,
                            text=True,
                            check=True,
                            cwd=tmp,
                        )
                        row = json.loads(out.stdout.splitlines()[-1])
                        assert Path(row["jaxgeom"]).resolve().is_relative_to(path.resolve()), row["jaxgeom"]
                        runs[label][tree] += row["seconds_per_step"]
                        bare[label][tree].append(row["bare_qhull_seconds"])
                        print(
                            json.dumps(
                                {
                                    "config": label,
                                    "tree": tree,
                                    "ms": [round(1e3 * t, 2) for t in row["seconds_per_step"]],
                                    "bare_qhull_ms": round(1e3 * row["bare_qhull_seconds"], 2),
                                }
                            ),
                            flush=True,
                        )
        finally:
            for rev in revs:
                subprocess.run(
                    ["git", "-C", str(root), "worktree", "remove", "--force", str(trees[rev])], capture_output=True
                )
    return {
        label: {
            tree: {
                "median_ms": 1e3 * float(np.median(t)),
                "min_ms": 1e3 * min(t),
                "max_ms": 1e3 * max(t),
                "runs_ms": [1e3 * v for v in t],
                "bare_qhull_ms": [1e3 * v for v in bare[label][tree]],
                "step_over_bare_qhull": float(np.median(t) / np.median(bare[label][tree])),
                "speedup_over": {
                    other: float(np.median(runs[label][other]) / np.median(t)) for other in trees if other != tree
                },
            }
            for tree, t in runs[label].items()
        }
        for label in runs
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--steps", type=int, nargs="+", default=[40, 10], help="timed steps per size")
    parser.add_argument("--force-n", type=int, default=1_000_000)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument(
        "--triangulators",
        nargs="+",
        help="only the step matrix (MATRIX), with these backends "
        "side by side (e.g. qhull cdt shull auto), into results/dynamics_triangulators.json",
    )
    parser.add_argument(
        "--rebuild-modes",
        nargs="+",
        choices=("host", "callback", "device"),
        help="only simulate at --sizes/--steps in these rebuild modes, into results/dynamics_modes.json",
    )
    parser.add_argument("--budget", type=float, default=600.0, help="seconds for all of --rebuild-modes")
    parser.add_argument(
        "--against",
        nargs="+",
        metavar="REV",
        help="only the 2D N=1e4 step configurations, this working tree against these commits "
        "(each in a child process, alternating over --rounds), into results/dynamics_against.json",
    )
    parser.add_argument("--rounds", type=int, default=3, help="rounds of --against")
    parser.add_argument(
        "--only", default="2D", help="--against: the configurations whose label holds this (2D, 3D, callback, ...)"
    )
    parser.add_argument("--one", nargs=3, metavar=("N", "MODE", "STEPS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if len(args.steps) != len(args.sizes):  # each size its own step count (zip once dropped the extra sizes)
        parser.error(f"--steps gives {len(args.steps)} counts for {len(args.sizes)} --sizes; give one per size")
    if args.one:
        print(json.dumps(one_mode(int(args.one[0]), args.one[1], int(args.one[2]), repeats=2)), flush=True)
        return
    if args.against:
        result = {
            "machine": {
                "platform": platform.platform(),
                "cpus": os.cpu_count(),
                "jax": jax.__version__,
                "dtype": "float32",
                "date": time.strftime("%Y-%m-%d"),
            },
            "against": against(args.against, args.rounds, only=args.only),
        }
        out = args.out or Path(__file__).parent / "results" / "dynamics_against.json"
        out.write_text(json.dumps(result, indent=2))
        print(f"wrote {out}")
        return
    if args.rebuild_modes:
        result = {
            "machine": {
                "platform": platform.platform(),
                "cpus": os.cpu_count(),
                "jax": jax.__version__,
                "device": jax.devices()[0].device_kind,
                "dtype": "float32",
            },
            "modes": rebuild_modes(args.sizes, args.steps, args.rebuild_modes, args.budget),
        }
        out = args.out or Path(__file__).parent / "results" / "dynamics_modes.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(result, indent=2))
        print(f"wrote {out}")
        return
    if args.triangulators:
        configs = [c[:4] + (jaxgeom.OBSERVABLES if c[4] is None else c[4],) + c[5:] for c in MATRIX]
        result = {
            "machine": {
                "platform": platform.platform(),
                "cpus": jax.device_count("cpu"),
                "jax": jax.__version__,
                "dtype": "float32",
            },
            "matrix": triangulator_matrix(["qhull"] + [t for t in args.triangulators if t != "qhull"], configs),
        }
        out = args.out or Path(__file__).parent / "results" / "dynamics_triangulators.json"
        out.write_text(json.dumps(result, indent=2))
        print(f"wrote {out}")
        return
    args.out = args.out or Path(__file__).parent / "results" / "dynamics.json"
    result = {
        "machine": {
            "platform": platform.platform(),
            "cpus": jax.device_count("cpu"),
            "jax": jax.__version__,
            "dtype": "float32",
        },
        "throughput": [throughput(n, s) for n, s in zip(args.sizes, args.steps, strict=True)],
        "rebuild_strategy": rebuild_strategy(args.sizes[0], args.steps[0]),
        "viscous_force": force_versus_numpy(args.force_n),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
