"""A hostile-input campaign: each case in its own process (memory cap, time limit), classified.

Every case is a snippet run after a common preamble (a 200-walker 2D graph `T`, its volumes
`VOL`, a bowl `V`, a swarm `S`, `P = SwarmParams()`), or a `jaxgeom` command line. A case
declares what it should give:

- "error": a ValueError/TypeError (or the library's own errors) whose message names the
  argument with backticks or a --flag: a *clear error*; a returned value is *accepted
  silently*; another exception, or one whose text comes from JAX or numpy, is a *raw
  traceback*.
- "value": a result (NaN allowed) or, for the CLI, exit status 0: *handled*.
- "either": a result or a clear refusal (nearly degenerate input that may or may not be
  resolvable), both fine.
- "warn": a result together with a warning that names `metric_defects` (a callable metric
  that is NaN or indefinite at the walkers): *handled*; without the warning, *silent NaN*.

Outcomes also count *hang* (over the time limit) and *out of memory* (killed under the cap).
Writes bench/results/hostile_inputs.json; `--list` prints the cases.

    python bench/hostile_inputs.py [--jobs 2] [--timeout 180]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

PREAMBLE = """
import warnings; warnings.simplefilter("ignore")
import numpy as np, jax, jax.numpy as jnp, jaxgeom as jg
from jaxgeom.apps._landscapes import rastrigin, sample_boltzmann
jax.config.update("jax_enable_x64", True)
rng = np.random.default_rng(0)
X = rng.random((200, 2)); T = jg.delaunay(X); VOL = np.asarray(jg.voronoi_volumes(T)); N = 200
V = lambda p: jnp.sum(p ** 2)
S = jg.init_swarm(V, rng.random((40, 2))); P = jg.SwarmParams()
L = jg.simulation_loss(V, S, n_steps=2, params=P)
R = lambda p: 100.0 * (p[1] - p[0] ** 2) ** 2 + (1.0 - p[0]) ** 2 + jnp.sum(p[2:] ** 2)  # Rosenbrock (+ a bowl)
PD = jg.SwarmParams(dt=0.05, gamma=0.5, temperature=1.0, nu=0.3, weights="metric_full", anisotropic=True)
SD = lambda d=2, graph="delaunay": jg.init_swarm(R, rng.uniform(-2, 2, (80, d)), graph=graph)  # diverges under PD
"""


E, OK, EITHER, WARN = "error", "value", "either", "warn"  # either: a result, or a clear refusal
CASES: list[tuple[str, str, str]] = [
    # (label, snippet or "cli: args", expectation)
    ("positions NaN", "jg.delaunay(np.r_[X[:-1], [[np.nan, 0.0]]])", E),
    ("positions inf", "jg.delaunay(np.r_[X[:-1], [[np.inf, 0.0]]])", E),
    ("positions 1-D", "jg.delaunay(X[:, 0])", E),
    ("positions strings", "jg.delaunay([['a', 'b']] * 10)", E),
    ("positions int", "jg.delaunay(rng.integers(0, 100, (50, 2)))", E),
    ("positions complex", "jg.delaunay(X + 0j)", E),
    ("too few points", "jg.delaunay(X[:3])", E),
    ("duplicates", "jg.delaunay(np.r_[X, X[:5]])", E),
    ("collinear", "jg.delaunay(np.c_[X[:, 0], 2 * X[:, 0]])", E),
    (
        "near collinear 1e-13",
        "s = np.linspace(0, 1, 40); v = np.asarray(jg.voronoi_volumes(jg.delaunay("
        "np.c_[s, 2 * s + 1e-13 * rng.standard_normal(40)]))); assert not np.any(v[np.isfinite(v)] < 0)",
        EITHER,
    ),
    (
        "near collinear 1e-12 volumes",
        "s = np.linspace(0, 1, 40); v = np.asarray(jg.voronoi_volumes(jg.delaunay("
        "np.c_[s, 2 * s + 1e-12 * rng.standard_normal(40)]))); assert np.all(v[np.isfinite(v)] > 0)",
        OK,
    ),
    ("coplanar 3D", "jg.delaunay(np.c_[X, X[:, 0] + X[:, 1]])", E),
    ("dimension 5 Delaunay", "jg.delaunay(rng.random((100, 5)))", E),
    ("unknown triangulator", "jg.delaunay(X, triangulator='fast')", E),
    ("box reversed", "jg.delaunay(X, box=([1, 1], [0, 0]))", E),
    ("walkers outside box", "jg.delaunay(X, box=([0.5, 0.5], [1, 1]))", E),
    ("float32 offset 1e6", "jg.delaunay((X + 1e6).astype(np.float32))", E),
    ("float32 offset 1e3", "jg.delaunay((rng.random((5000, 2)) + 1e3).astype(np.float32))", E),
    ("float32 centred", "jg.voronoi_volumes(jg.delaunay(X.astype(np.float32)))", OK),
    ("metric wrong shape", "jg.ricci_scalar(T, metric=np.ones((5, 2, 2)))", E),
    ("metric indefinite", "jg.ricci_scalar(T, metric=np.broadcast_to(np.diag([1.0, -1.0]), (N, 2, 2)))", E),
    ("metric string", "jg.ricci_scalar(T, metric='euclidean')", E),
    (
        "metric 1e200 I",
        "v = np.asarray(jg.riemannian_volumes(T, metric=np.broadcast_to(1e200 * np.eye(2), (N, 2, 2))));"
        " assert np.isfinite(v).sum() > 100",
        OK,
    ),
    ("metric 1e-200 I", "jg.ricci_scalar(T, metric=np.broadcast_to(1e-200 * np.eye(2), (N, 2, 2)))", OK),
    ("metric callable float()", "jg.ricci_scalar(T, metric=lambda p: float(p[0]) * jnp.eye(2))", E),
    ("zero metric eps 0", "jg.ricci_scalar(T, metric=jg.hessian_metric(lambda p: jnp.sum(p), 0.0))", OK),
    ("hessian_metric(5)", "jg.hessian_metric(5, 0.1)", E),
    ("hessian_metric eps -1", "jg.hessian_metric(V, -1.0)", E),
    ("unknown mode", "jg.edge_lengths(T, mode='diag')", E),
    ("unknown weights", "jg.viscous_force(T, np.zeros((N, 2)), nu=0.1, weights='gauss')", E),
    ("nu negative", "jg.viscous_force(T, np.zeros((N, 2)), nu=-1.0)", E),
    ("velocities wrong shape", "jg.viscous_force(T, np.zeros((N, 3)), nu=0.1)", E),
    ("volume_weights complex", "jg.viscous_force(T, np.zeros((N, 2)), nu=0.1, volume_weights=VOL + 0j)", E),
    ("volumes short", "jg.volume_distortion(T, VOL[:5])", E),
    ("volumes string", "jg.volume_distortion(T, 'abc')", E),
    ("volumes list", "jg.volume_distortion(T, list(VOL))", OK),
    ("volumes complex", "jg.volume_distortion(T, VOL + 0j)", E),
    ("volumes negative", "jg.volume_distortion(T, -VOL)", E),
    ("ricci volumes short", "jg.ricci_scalar(T, volumes=VOL[:5])", E),
    ("ricci volumes complex", "jg.ricci_scalar(T, volumes=VOL + 0j)", E),
    ("riemannian_volumes list short", "jg.riemannian_volumes(T, volumes=list(VOL[:5]))", E),
    ("riemannian_volumes negative", "jg.riemannian_volumes(T, volumes=-VOL)", E),
    ("riemannian_mean float mask", "jg.riemannian_mean(VOL, VOL, mask=np.ones(N))", E),
    ("riemannian_mean short mask", "jg.riemannian_mean(VOL, VOL, mask=np.ones(5, bool))", E),
    ("riemannian_mean negative weights", "jg.riemannian_mean(VOL, -VOL)", E),
    ("riemannian_mean complex", "jg.riemannian_mean(VOL + 0j, VOL)", E),
    ("riemannian_mean string", "jg.riemannian_mean(VOL, 'abc')", E),
    ("raychaudhuri (N, 2)", "jg.raychaudhuri_expansion(np.ones((N, 2)), np.ones((N, 2)), 0.1)", E),
    ("raychaudhuri complex", "jg.raychaudhuri_expansion(VOL + 0j, VOL, 0.1)", E),
    ("raychaudhuri float valid", "jg.raychaudhuri_expansion(VOL, VOL, 0.1, valid=np.ones(N))", E),
    ("raychaudhuri dt 0", "jg.raychaudhuri_expansion(VOL, VOL, 0.0)", E),
    ("mean_curvature list with NaN", "assert float(jg.mean_curvature_estimate([1.0, 2.0, np.nan])) == -1.5", OK),
    ("mean_curvature complex", "jg.mean_curvature_estimate(np.array([1.0, 2.0]) + 0j)", E),
    (
        "heat on clipped Rastrigin metric 2D",
        "x = rng.uniform(-5.12, 5.12, (300, 2)); d = np.asarray(jg.geodesic_distances("
        "jg.delaunay(x), 0, jg.hessian_metric(rastrigin, 0.1))); assert np.isfinite(d).all()",
        OK,
    ),
    (
        "heat on clipped Rastrigin metric 3D",
        "x = rng.uniform(-5.12, 5.12, (400, 3)); d = np.asarray(jg.geodesic_distances("
        "jg.delaunay(x), 0, jg.hessian_metric(rastrigin, 0.1))); assert np.isfinite(d).all()",
        OK,
    ),
    ("geodesic sources out of range", "jg.geodesic_distances(T, 500)", E),
    ("geodesic unknown method", "jg.geodesic_distances(T, 0, method='astar')", E),
    ("geodesic t negative", "jg.geodesic_distances(T, 0, t=-1.0)", E),
    ("geometric_hessian eps -1", "jg.geometric_hessian(T, -1.0)", E),
    ("geometric_hessian eps NaN", "jg.geometric_hessian(T, np.nan)", E),
    ("compare eps -1", "jg.compare_estimation_methods(T, VOL, eps_sigma=-1.0)", E),
    ("validate n_walkers 100.5", "jg.validate_on_synthetic_function('quadratic', n_walkers=100.5)", E),
    ("validate eps NaN", "jg.validate_on_synthetic_function('quadratic', eps_sigma=np.nan)", E),
    ("validate unknown name", "jg.validate_on_synthetic_function('himmelblau')", E),
    ("plot_estimation_quality({})", "jg.plot_estimation_quality({}, '/tmp/unused.png')", E),
    ("spectral_gap tol -1", "jg.spectral_gap(T, method='lobpcg', tol=-1.0)", E),
    ("spectral_gap tol NaN", "jg.spectral_gap(T, method='lobpcg', tol=np.nan)", E),
    ("spectral_gap maxiter -3", "jg.spectral_gap(T, method='lobpcg', maxiter=-3)", E),
    ("spectral_gap k 0", "jg.spectral_gap(T, k=0)", E),
    ("batch_mesh('cpu')", "jg.batch_mesh('cpu')", E),
    ("batch_mesh([d, d])", "jg.batch_mesh([jax.devices()[0]] * 2)", E),
    ("shard_batch string mesh", "jg.shard_batch(jg.stack_swarms([S, S]), 'cpu')", E),
    ("shard_batch walker mesh", "jg.shard_batch(jg.stack_swarms([S, S]), jg.walker_mesh())", E),
    ("init_swarm int fitness", "jg.init_swarm(lambda p: 1, X)", E),
    ("init_swarm complex fitness", "jg.init_swarm(lambda p: jnp.sum(p) + 1j, X)", E),
    ("init_swarm vector fitness", "jg.init_swarm(lambda p: p, X)", E),
    ("init_swarm numpy fitness", "jg.init_swarm(lambda p: float(np.sum(p)), X)", E),
    ("init_swarm swapped arguments", "jg.init_swarm(X, V)", E),
    ("simulate untraceable fitness", "jg.simulate(lambda p: float(np.sum(p)), S, P, n_steps=1)", E),
    ("simulate observe as a string", "jg.simulate(V, S, P, n_steps=1, observe='mean_fitness')", OK),
    ("simulate unknown observable", "jg.simulate(V, S, P, n_steps=1, observe=('fitness',))", E),
    ("simulate spectral_gap_every -2", "jg.simulate(V, S, P, n_steps=1, spectral_gap_every=-2)", E),
    ("simulate n_steps 0", "jg.simulate(V, S, P, n_steps=0)", E),
    (
        "simulate zero metric weights",
        "jg.simulate(lambda p: jnp.sum(p), jg.init_swarm(lambda p: jnp.sum(p), X), "
        "jg.SwarmParams(eps_sigma=0.0, weights='metric_full'), n_steps=3, observe=('mean_fitness',))",
        E,
    ),
    ("SwarmParams dt -1", "jg.SwarmParams(dt=-1.0)", E),
    ("SwarmParams nu NaN", "jg.SwarmParams(nu=np.nan)", E),
    ("SwarmParams unknown weights", "jg.SwarmParams(weights='gauss')", E),
    ("simulation_loss key 'abc'", "jg.simulation_loss(V, S, n_steps=2, params=P, key='abc')", E),
    ("simulation_loss string bounds", "jg.simulation_loss(V, S, n_steps=2, params=P, bounds={'nu': ('a', 'b')})", E),
    ("simulation_loss unknown objective", "jg.simulation_loss(V, S, 'fastest', n_steps=2, params=P)", E),
    ("loss theta wrong length", "L(jnp.zeros(5))", E),
    ("tune rtol -1", "jg.tune(L, rtol=-1.0)", E),
    ("tune rtol NaN", "jg.tune(L, rtol=np.nan)", E),
    ("tune lbfgsb reversed bounds", "jg.tune(L, solver='lbfgsb', bounds={'nu': (1.0, 0.1)})", E),
    ("tune max_steps 0", "jg.tune(L, max_steps=0)", E),
    ("tune unknown solver", "jg.tune(L, solver='adam')", E),
    (
        "sample_boltzmann beta 0",
        "x, _ = sample_boltzmann('double_well', 1000, 2, beta=0.0); assert np.isfinite(x).all()",
        OK,
    ),
    ("sample_boltzmann beta 1e300", "sample_boltzmann('double_well', 10, 2, beta=1e300)", E),
    ("sample_boltzmann d 1000", "sample_boltzmann('double_well', 100, 1000, beta=1e-3)", OK),
    ("cli: analyze --n 300 --dim 4", "cli: analyze --n 300 --dim 4", OK),
    ("cli: analyze --beta 0", "cli: analyze --beta 0 --n 300", OK),
    ("cli: analyze --beta 0 quadratic", "cli: analyze --beta 0 --landscape quadratic --n 300", OK),
    ("cli: analyze --beta 0 rastrigin", "cli: analyze --beta 0 --landscape rastrigin --n 300", OK),
    ("cli: analyze --box 1 0", "cli: analyze --n 100 --box 1 0", E),
    ("cli: analyze --box nan 1", "cli: analyze --n 100 --box nan 1", E),
    ("cli: analyze --periodic --box 0 1", "cli: analyze --n 100 --periodic --box 0 1", E),
    ("cli: analyze --dim 0", "cli: analyze --dim 0", E),
    ("cli: analyze --dim -1", "cli: analyze --dim -1", E),
    ("cli: analyze --n 2", "cli: analyze --n 2", E),
    ("cli: analyze --eps-sigma -1", "cli: analyze --eps-sigma -1", E),
    ("cli: simulate --dt 0", "cli: simulate --dt 0 --steps 2", E),
    ("cli: simulate --dim 5", "cli: simulate --dim 5 --steps 2", E),
    ("cli: simulate --triangulator fast", "cli: simulate --triangulator fast --steps 2", E),
    ("cli: tune --tune speed", "cli: tune --tune speed", E),
    # issue 47: diverging swarms under every driver (the rebuilds meet inf coordinates), NaN metrics
    (
        "cli: tune rosenbrock 2D",
        "cli: tune --tune nu eps_sigma --dim 2 --weights metric_full --landscape rosenbrock "
        "--max-steps 3 --no-progress",
        E,
    ),
    (
        "cli: tune rosenbrock 3D",
        "cli: tune --tune nu eps_sigma --dim 3 --weights metric_full --landscape rosenbrock "
        "--max-steps 3 --no-progress",
        E,
    ),
    (
        "cli: simulate rosenbrock dt 0.05",
        "cli: simulate --landscape rosenbrock --weights metric_full --dt 0.05 --n 200 --steps 30 --anisotropic",
        E,
    ),
    ("diverging swarm host", "jg.simulate(R, SD(), PD, n_steps=30)", E),
    (
        "diverging swarm callback",
        "_, h = jax.jit(lambda s: jg.simulate(R, s, PD, n_steps=30, rebuild='callback'))(SD()); "
        "assert int(h['diverged_step']) >= 0",
        OK,
    ),
    (
        "diverging swarm callback k-NN",
        "_, h = jax.jit(lambda s: jg.simulate(R, s, PD, n_steps=30, rebuild='callback'))("
        "SD(graph='knn')); assert int(h['diverged_step']) >= 0",
        OK,
    ),
    (
        "diverging swarm callback 3D",
        "_, h = jax.jit(lambda s: jg.simulate(R, s, PD, n_steps=30, rebuild='callback'))("
        "SD(3)); assert int(h['diverged_step']) >= 0",
        OK,
    ),
    (
        "diverging swarm device",
        "_, h = jax.jit(lambda s: jg.simulate(R, s, PD, n_steps=30, rebuild='device'))(SD()); "
        "assert int(h['diverged_step']) >= 0",
        OK,
    ),
    (
        "diverging swarm vmapped seeds",
        "loss = jg.simulation_loss(R, SD(), n_steps=30, params=PD, n_seeds=4); "
        "assert np.isposinf(float(jax.jit(lambda t: loss(t))(loss.to_theta()))); "
        "assert 'diverged by step' in loss.divergence(loss.to_theta())",
        OK,
    ),
    ("diverging swarm tune", "jg.tune(jg.simulation_loss(R, SD(), n_steps=30, params=PD, n_seeds=2), max_steps=2)", E),
    ("delaunay coordinate 1e200", "jg.delaunay(np.r_[X[:-1], [[1e200, 0.0]]])", E),
    ("metric array NaN", "jg.ricci_scalar(T, metric=np.full((N, 2, 2), np.nan))", E),
    (
        "metric array one NaN row",
        "g = np.broadcast_to(np.eye(2), (N, 2, 2)).copy(); g[7] = np.nan; jg.ricci_scalar(T, metric=g)",
        E,
    ),
    (
        "metric_defects NaN callable",
        "assert np.asarray(jg.metric_defects(T, lambda p: jnp.full((2, 2), jnp.nan))).all()",
        OK,
    ),
    ("ricci NaN callable", "jg.ricci_scalar(T, metric=lambda p: jnp.full((2, 2), jnp.nan))", WARN),
    ("ricci indefinite callable", "jg.ricci_scalar(T, metric=lambda p: jnp.diag(jnp.array([1.0, -1.0])))", WARN),
    (
        "viscous_force NaN callable",
        "jg.viscous_force(T, np.ones((N, 2)), nu=0.1, weights='metric_full', "
        "metric=lambda p: jnp.full((2, 2), jnp.nan))",
        WARN,
    ),
    (
        "viscous_force indefinite callable",
        "jg.viscous_force(T, np.ones((N, 2)), nu=0.1, weights='metric_full', "
        "metric=lambda p: jnp.diag(jnp.array([1.0, -1.0])))",
        WARN,
    ),
    ("edge_lengths NaN callable", "jg.edge_lengths(T, metric=lambda p: jnp.full((2, 2), jnp.nan))", WARN),
    (
        "simulation_loss numpy objective",
        "jg.simulation_loss(V, S, lambda h: float(np.asarray(h['mean_fitness'])[-1]), n_steps=2, params=P)",
        E,
    ),
]
LANDSCAPE_FILES = {  # analyze --landscape FILE.py: each must be refused clearly
    "vector": "import jax.numpy as jnp\ndef V(x):\n    return 2.0 * x\n",
    "raises": "def V(x):\n    raise RuntimeError('boom')\n",
    "numpy": "import numpy as np\ndef V(x):\n    return float(np.sum(np.asarray(x) ** 2))\n",
    "int": "import jax.numpy as jnp\ndef V(x):\n    return jnp.sum(x ** 2).astype(int)\n",
}
CLEAR_TYPES = (
    "ValueError",
    "TypeError",
    "CoincidentPointsError",
    "CapacityError",
    "SimulationDiverged",
    "TuningFailed",
    "FloatingPointError",
)
MEMORY_CAP = 8 << 30


def run_case(label: str, code: str, expect: str, timeout: float, workdir: Path) -> dict:
    if code.startswith("cli: "):
        cmd = [sys.executable, "-m", "jaxgeom.cli", *code[5:].split(), "--precision", "float64"]
        if code.split()[1] == "simulate":
            cmd += ["--no-progress", "--gap-every", "0"]
    else:
        body = (
            PREAMBLE + f"try:\n    out = {code}\n"
            if "assert" not in code and ";" not in code
            else PREAMBLE + "try:\n    " + code.replace("; ", "\n    ") + "\n    out = None\n"
        )
        if expect == WARN:  # the warnings the preamble silences, recorded for this call
            body = body.replace(
                "try:\n",
                "W = warnings.catch_warnings(record=True); caught = W.__enter__(); "
                "warnings.simplefilter('always')\ntry:\n",
                1,
            )
        body += (
            "except Exception as err:\n    import sys; print('EXC', type(err).__name__, '|', str(err)[:400]);"
            " sys.exit(3)\nprint('OK', repr(out)[:200])\n"
        )
        if expect == WARN:
            body += "print('WARNED' if any('metric_defects' in str(w.message) for w in caught) else 'NO WARNING')\n"
        cmd = [sys.executable, "-c", body]
    began = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd,
            capture_output=True,
            text=True,
            timeout=timeout,
            cwd=workdir,
            preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP)),
        )
    except subprocess.TimeoutExpired:
        return {"label": label, "expect": expect, "outcome": "hang", "seconds": timeout}
    seconds = round(time.perf_counter() - began, 1)
    text = proc.stdout + proc.stderr
    return {
        "label": label,
        "expect": expect,
        "outcome": classify(code, expect, proc.returncode, text),
        "seconds": seconds,
        "tail": text.strip().splitlines()[-1][:300] if text.strip() else "",
    }


def classify(code: str, expect: str, status: int, text: str) -> str:
    if status in (-9, 137) or "MemoryError" in text or "RESOURCE_EXHAUSTED" in text:
        return "out of memory"
    if code.startswith("cli: "):
        clear = status == 2 and "error:" in text and "Traceback" not in text
        if expect == OK:
            return (
                "handled" if status == 0 and "Traceback" not in text else ("clear error" if clear else "raw traceback")
            )
        return "clear error" if clear else ("accepted silently" if status == 0 else "raw traceback")
    if status == 0 and expect == WARN:
        return "handled" if "WARNED" in text else "silent NaN"
    if status == 0:
        return "handled" if expect in (OK, EITHER) else "accepted silently"
    line = next((l for l in text.splitlines() if l.startswith("EXC ")), "")
    kind, _, message = line[4:].partition(" | ")
    named = any(w in message for w in ("`", "--", "must", "valid values", "Likely cause", "eps_sigma"))
    clear = kind.strip() in CLEAR_TYPES and named
    if expect in (OK, WARN):
        return "raw traceback" if not clear else "clear error"
    return "clear error" if clear else "raw traceback"  # an error, or a clear refusal of EITHER


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=240.0)
    parser.add_argument("--list", action="store_true")
    parser.add_argument(
        "--only",
        nargs="+",
        metavar="TEXT",
        help="rerun the cases whose label contains one of these, replacing them in --out",
    )
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "hostile_inputs.json")
    args = parser.parse_args()
    workdir = Path("/tmp/jaxgeom_hostile")
    workdir.mkdir(exist_ok=True)
    cases = list(CASES)
    for name, body in LANDSCAPE_FILES.items():
        (workdir / f"landscape_{name}.py").write_text(body)  # not numpy.py: it would shadow numpy
        cases.append((f"cli: analyze --landscape {name}", f"cli: analyze --n 100 --landscape landscape_{name}.py", E))
    if args.list:
        print("\n".join(f"{expect:5} {label}" for label, _, expect in cases))
        return
    if args.only:
        cases = [c for c in cases if any(text in c[0] for text in args.only)]
    with ThreadPoolExecutor(args.jobs) as pool:
        results = list(pool.map(lambda c: run_case(*c, args.timeout, workdir), cases))
    if args.only:  # merged into the last full campaign
        rerun = {r["label"]: r for r in results}
        results = [rerun.get(r["label"], r) for r in json.loads(args.out.read_text())["results"]]
    counts = {}
    for r in results:
        counts[r["outcome"]] = counts.get(r["outcome"], 0) + 1
        if r["outcome"] not in ("handled", "clear error") or (r["expect"] in (OK, WARN) and r["outcome"] != "handled"):
            print(f"{r['outcome']:18} {r['label']}: {r.get('tail', '')}")
    print(json.dumps(counts))
    args.out.write_text(
        json.dumps(
            {
                "cases": len(results),
                "counts": counts,
                "results": results,
                "python": sys.version.split()[0],
                "cpus": os.cpu_count(),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
