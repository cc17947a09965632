"""Tuning through whole simulations (jaxgeom.simulation_loss / jaxgeom.tune), measured.

Run: python bench/tuning.py [--part memory time noise solvers] [--precision float64]
         [--out bench/results/tuning.json]

- memory: XLA's buffer plan (`compiled.memory_analysis()`: temporaries + arguments +
  outputs) of loss + gradient, rebuild="callback", N = 1e3 and 1e4, 100 and 1000 steps,
  with the nested sqrt(T) checkpointing (the default) and without; plus the measured peak
  RSS of a process that runs loss + gradient at N = 1e3 (checkpointed).
- time: one loss + gradient against the forward loss alone (N = 1e3, 100 steps), medians
  of 3 after compilation, checkpointed and not.
- noise: the seed-to-seed spread of the per-seed gradient (16 seeds) of the built-in
  objectives in d/dlog(nu) and d/dlog(eps_Sigma), for the Hessian floor "clip" and
  "softabs", in the precision given (run once per precision).
- solvers: the recovery problem of tests/swarm/test_tuning.py (nu* = 0.3 from 0.05) with BFGS,
  NonlinearCG and L-BFGS-B: iterations, loss evaluations' wall time, the value found.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import jax

PRECISION = (
    "float64" if "--precision" in sys.argv and sys.argv[sys.argv.index("--precision") + 1] == "float64" else None
)
if PRECISION:
    jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from tqdm.auto import tqdm  # noqa: E402

import jaxgeom  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent))
from device_rebuild import median_seconds  # noqa: E402


def V(x):
    return jnp.sum(x**2 - 2.0 * jnp.cos(3.0 * x))


def swarm(n: int, seed: int = 0):
    x0 = np.random.default_rng(seed).uniform(-3, 3, (n, 2))
    return jaxgeom.init_swarm(V, x0, key=seed)


def physics(**extra):
    return jaxgeom.SwarmParams(
        **{
            "dt": 0.05,
            "temperature": 0.5,
            "gamma": 0.5,
            "nu": 0.3,
            "eps_sigma": 0.1,
            "weights": "metric_full",
            "cloning": False,
            **extra,
        }
    )


def mean_fitness_loss(n: int, n_steps: int, checkpoint: bool = True):
    return jaxgeom.simulation_loss(
        V, swarm(n), "mean_fitness", n_steps=n_steps, params=physics(), checkpoint=checkpoint
    )


def memory_plan(n: int, n_steps: int, checkpoint: bool) -> dict:
    loss = mean_fitness_loss(n, n_steps, checkpoint)
    arrays, static = eqx.partition(loss, eqx.is_array)
    both = jax.jit(lambda a, t: jax.value_and_grad(eqx.combine(a, static))(t))
    compiled = both.lower(arrays, loss.to_theta()).compile()
    plan = compiled.memory_analysis()
    total = plan.temp_size_in_bytes + plan.argument_size_in_bytes + plan.output_size_in_bytes
    return {
        "n": n,
        "n_steps": n_steps,
        "checkpoint": checkpoint,
        "temp_bytes": int(plan.temp_size_in_bytes),
        "total_bytes": int(total),
    }


def peak_rss_child(n: int, n_steps: int) -> float:
    """Peak resident memory (MB) of a fresh process that runs one loss + gradient."""
    code = (
        f"import sys; sys.argv = ['x', '--precision', '{PRECISION or 'float32'}']; "
        "import resource, jax, equinox as eqx; sys.path.insert(0, 'bench'); import tuning; "
        f"l = tuning.mean_fitness_loss({n}, {n_steps}); "
        "jax.block_until_ready(eqx.filter_jit(lambda l, t: jax.value_and_grad(l)(t))(l, l.to_theta())); "
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


def part_memory() -> dict:
    plans = [memory_plan(n, t, c) for n in (1000, 10000) for t in (100, 1000) for c in (True, False)]
    rss = {f"n1000_steps{t}": peak_rss_child(1000, t) for t in (100, 1000)}
    ratios = {}
    for n in (1000, 10000):
        for c in (True, False):
            pick = {p["n_steps"]: p["total_bytes"] for p in plans if p["n"] == n and p["checkpoint"] == c}
            ratios[f"n{n}_{'checkpointed' if c else 'plain'}_1000_over_100"] = pick[1000] / pick[100]
    return {"plans": plans, "ratios": ratios, "peak_rss_mb_checkpointed": rss}


def part_time(n: int = 1000, n_steps: int = 100) -> dict:
    rows = []
    for checkpoint in (True, False):
        loss = mean_fitness_loss(n, n_steps, checkpoint)
        theta = loss.to_theta()
        forward = eqx.filter_jit(lambda l, t: l(t))
        both = eqx.filter_jit(lambda l, t: jax.value_and_grad(l)(t))
        jax.block_until_ready(forward(loss, theta))
        jax.block_until_ready(both(loss, theta))
        f, f_runs = median_seconds(lambda: forward(loss, theta))
        g, g_runs = median_seconds(lambda: both(loss, theta))
        rows.append(
            {
                "n": n,
                "n_steps": n_steps,
                "checkpoint": checkpoint,
                "forward_seconds": f,
                "loss_and_grad_seconds": g,
                "ratio": g / f,
                "forward_runs": f_runs,
                "grad_runs": g_runs,
            }
        )
    return {"rows": rows}


def part_noise(n: int = 200, n_seeds: int = 16) -> dict:
    rows = []
    state = swarm(n)
    late_vv = lambda h: jnp.mean(h["velocity_variance"][len(h["velocity_variance"]) // 2 :])  # noqa: E731
    objectives = {
        "mean_fitness": ("mean_fitness", None),
        "velocity_variance (late mean)": (late_vv, ("velocity_variance",)),
    }
    for floor in ("clip", "softabs"):
        for n_steps in (20, 60):
            params = physics(nu=0.05, eps_sigma=0.2, anisotropic=True, floor=floor)
            for name, (objective, observe) in objectives.items():
                loss = jaxgeom.simulation_loss(
                    V, state, objective, n_steps=n_steps, params=params, n_seeds=n_seeds, observe=observe
                )
                jac = np.asarray(eqx.filter_jit(lambda l, t: jax.jacrev(l.per_seed)(t))(loss, loss.to_theta()))
                mean, std = jac.mean(axis=0), jac.std(axis=0, ddof=1)
                rows.append(
                    {
                        "floor": floor,
                        "n_steps": n_steps,
                        "objective": name,
                        "n_seeds": n_seeds,
                        "grad_mean": {"log_nu": mean[0], "log_eps_sigma": mean[1]},
                        "grad_std": {"log_nu": std[0], "log_eps_sigma": std[1]},
                        "sign_agreement_eps": float(np.mean(np.sign(jac[:, 1]) == np.sign(mean[1]))),
                        "t_statistic_eps": float(mean[1] / (std[1] / np.sqrt(n_seeds))),
                    }
                )
                print(json.dumps(rows[-1], default=float), flush=True)
    return {"rows": rows}


def part_solvers() -> dict:
    state, params = swarm(200), physics()
    record = jaxgeom.simulation_loss(
        V,
        state,
        lambda h: h["velocity_variance"][-1],
        n_steps=60,
        params=params,
        tuned=("nu",),
        n_seeds=4,
        observe=("velocity_variance",),
    )
    _, history = eqx.filter_jit(lambda l, t: l.histories(t))(record, record.to_theta())
    target = float(np.mean(np.asarray(history["velocity_variance"])[:, 30:]))
    loss = jaxgeom.simulation_loss(
        V, state, "match", n_steps=60, params=params, tuned=("nu",), n_seeds=4, targets={"velocity_variance": target}
    )
    rows = []
    for solver in ("bfgs", "nonlinear_cg", "lbfgsb"):
        result = jaxgeom.tune(loss, {"nu": 0.05}, solver=solver, max_steps=30)
        rows.append(
            {
                "solver": solver,
                "nu_found": result.values["nu"],
                "nu_true": 0.3,
                "relative_error": abs(result.values["nu"] / 0.3 - 1),
                "iterations": len(result.iterations) - 1,
                "solver_steps": result.n_steps,
                "seconds": result.seconds,
                "loss": result.loss,
                "message": result.message,
            }
        )
        print(json.dumps(rows[-1], default=float), flush=True)
    return {"rows": rows}


PARTS = {"memory": part_memory, "time": part_time, "noise": part_noise, "solvers": part_solvers}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", nargs="+", choices=sorted(PARTS), default=sorted(PARTS))
    parser.add_argument("--precision", choices=["float32", "float64"], default="float32")
    parser.add_argument("--out", type=Path, default=Path("bench/results/tuning.json"))
    args = parser.parse_args()
    results = json.loads(args.out.read_text()) if args.out.exists() else {}
    for part in tqdm(args.part, desc="tuning bench parts", disable=None):
        began = time.perf_counter()
        results[f"{part}_{args.precision}"] = dict(
            PARTS[part](),
            seconds=time.perf_counter() - began,
            machine=f"{platform.machine()} CPU x{jax.device_count()}",
            backend=jax.default_backend(),
            jax=jax.__version__,
            date=time.strftime("%Y-%m-%d"),
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=1, default=float))
        tqdm.write(f"{part}: done in {time.perf_counter() - began:.0f} s")


if __name__ == "__main__":
    main()
