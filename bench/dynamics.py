"""Swarm dynamics throughput, Qhull share, rebuild strategy, and the viscous force against numpy.

Run: python bench/dynamics.py [--sizes 10000 100000] [--out bench/results/dynamics.json]

All in float32 (the library default), 2D rastrigin swarm, default SwarmParams
(Langevin + kernel viscous force + cloning), in one run:

- steps per second at each N with rebuild every step and every 10 steps, with
  every observable and with only the fitness observables, and the share of the
  run's wall time spent inside Qhull (scipy's Delaunay constructor, clocked in
  the run); `qhull_seconds` is scipy.spatial.Delaunay alone on the final
  positions (best of 3); with rebuild every step, `rest_over_qhull` = (time per
  step - qhull_seconds) / qhull_seconds and `rest_over_qhull_in_run` the same
  with the Qhull time clocked inside the run (target <= 0.3);
- rebuild strategy at the smallest N: host rebuild between scan chunks against
  a `jax.pure_callback` inside the scan (both rebuild every step);
- `jaxgeom.viscous_force` alone at N = --force-n (1e6) against a vectorized numpy
  gather implementation of the same formula (target >= 5x).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.spatial

import jaxgeom
from jaxgeom._landscapes import rastrigin

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

    def __init__(self):
        self.seconds, self.calls, self._real = 0.0, 0, jaxgeom._delaunay.Delaunay

    def __enter__(self):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return self._real(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        jaxgeom._delaunay.Delaunay = timed
        return self

    def __exit__(self, *exc):
        jaxgeom._delaunay.Delaunay = self._real


def run(state, params, n_steps, rebuild_every, observe, rebuild="host"):
    """(seconds, final, history, Qhull seconds inside the run); the warm-up has the same
    n_steps, since a callback run compiles one scan over all of its steps."""
    kwargs = dict(n_steps=n_steps, rebuild_every=rebuild_every, observe=observe, rebuild=rebuild)
    jaxgeom.simulate(rastrigin, state, params, **kwargs)  # warm-up (compile)
    with QhullClock() as clock:
        start = time.perf_counter()
        final, history = jaxgeom.simulate(rastrigin, state, params, **kwargs)
        jax.block_until_ready(final.positions)
        seconds = time.perf_counter() - start
    return seconds, final, history, clock.seconds


def throughput(n: int, n_steps: int) -> dict:
    rng = np.random.default_rng(0)
    state = jaxgeom.init_swarm(rastrigin, rng.uniform(-5.12, 5.12, (n, 2)).astype(np.float32), key=0)
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    row = {"n": n, "n_steps": n_steps}
    for observe, label in ((jaxgeom.OBSERVABLES, "all_observables"), (OBS_FITNESS, "fitness_observables")):
        for every in (1, 10):
            seconds, final, history, qhull = run(state, params, n_steps, every, observe)
            row[f"{label}_rebuild_every_{every}"] = {
                "steps_per_second": n_steps / seconds, "seconds_per_step": seconds / n_steps,
                "seconds_rebuild": history["seconds_rebuild"], "seconds_steps": history["seconds_steps"],
                "seconds_qhull_in_run": qhull, "qhull_share": qhull / seconds,
                "n_reallocations": history["n_reallocations"]}
    x = np.asarray(final.positions, np.float64)
    row["qhull_seconds"] = best_of(lambda: scipy.spatial.Delaunay(x, qhull_options="Qbb Qc Qz Q12"))
    for label in ("all_observables", "fitness_observables"):
        timed = row[f"{label}_rebuild_every_1"]
        per_step = timed["seconds_per_step"]
        row[f"{label}_rest_over_qhull"] = (per_step - row["qhull_seconds"]) / row["qhull_seconds"]
        in_run = timed["seconds_qhull_in_run"] / n_steps
        row[f"{label}_rest_over_qhull_in_run"] = (per_step - in_run) / in_run
    print(json.dumps(row))
    return row


def rebuild_strategy(n: int, n_steps: int) -> dict:
    rng = np.random.default_rng(1)
    state = jaxgeom.init_swarm(rastrigin, rng.uniform(-5.12, 5.12, (n, 2)).astype(np.float32), key=0)
    params = jaxgeom.SwarmParams(dt=0.01, temperature=1.0, gamma=2.0, nu=0.1)
    out = {"n": n, "n_steps": n_steps}
    for rebuild in ("host", "callback"):
        seconds, _, _, qhull = run(state, params, n_steps, 1, OBS_FITNESS, rebuild)
        out[f"{rebuild}_seconds_per_step"] = seconds / n_steps
        out[f"{rebuild}_qhull_seconds_per_step"] = qhull / n_steps
    x = np.asarray(state.positions, np.float64)
    out["qhull_seconds"] = best_of(lambda: scipy.spatial.Delaunay(x, qhull_options="Qbb Qc Qz Q12"))
    print(json.dumps(out))
    return out


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
    ours = jaxgeom.viscous_force(tess, vj, nu=0.1, mode="kernel", length_scale=ell)
    nbrs = np.asarray(tess.neighbors)
    ref = numpy_viscous_force(x, v, nbrs, np.float32(0.1), ell)
    t_jax = best_of(lambda: jaxgeom.viscous_force(tess, vj, nu=0.1, mode="kernel", length_scale=ell))
    t_np = best_of(lambda: numpy_viscous_force(x, v, nbrs, np.float32(0.1), ell))
    out = {"n": n, "capacity_neighbors": tess.capacity.neighbors, "jax_seconds": t_jax, "numpy_seconds": t_np,
           "speedup": t_np / t_jax, "max_abs_difference": float(np.max(np.abs(np.asarray(ours) - ref)))}
    print(json.dumps(out))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--steps", type=int, nargs="+", default=[40, 10], help="timed steps per size")
    parser.add_argument("--force-n", type=int, default=1_000_000)
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "dynamics.json")
    args = parser.parse_args()
    result = {"machine": {"platform": platform.platform(), "cpus": jax.device_count("cpu"),
                          "jax": jax.__version__, "dtype": "float32"},
              "throughput": [throughput(n, s) for n, s in zip(args.sizes, args.steps)],
              "rebuild_strategy": rebuild_strategy(args.sizes[0], args.steps[0]),
              "viscous_force": force_versus_numpy(args.force_n)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
