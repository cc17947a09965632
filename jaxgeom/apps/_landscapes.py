"""Built-in fitness landscapes V: R^d -> R and exact sampling from exp(-beta V)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import scipy.special

from ..base._checks import check_choice, check_nonnegative


def double_well(x):
    """(x_0^2 - 1)^2 + (1 + x_0^2) sum_{k>0} x_k^2 / 2: two coupled wells at x_0 = +-1.

    The coupling makes the Hessian metric genuinely curved (a diagonal metric that
    depends on x_0 alone would be flat).
    """
    return (x[..., 0] ** 2 - 1.0) ** 2 + 0.5 * (1.0 + x[..., 0] ** 2) * jnp.sum(x[..., 1:] ** 2, axis=-1)


def quadratic(x):
    """Anisotropic bowl sum_k (k + 1) x_k^2 / 2."""
    scales = jnp.arange(1, x.shape[-1] + 1, dtype=x.dtype)
    return 0.5 * jnp.sum(scales * x**2, axis=-1)


def rosenbrock(x):
    return jnp.sum(100.0 * (x[..., 1:] - x[..., :-1] ** 2) ** 2 + (1.0 - x[..., :-1]) ** 2, axis=-1)


def rastrigin(x):
    return 10.0 * x.shape[-1] + jnp.sum(x**2 - 10.0 * jnp.cos(2.0 * jnp.pi * x), axis=-1)


LANDSCAPES: dict[str, tuple[Callable, float, float]] = {
    # name: (V, its minimum value, half-width of the sampling box)
    "double_well": (double_well, 0.0, 2.5),
    "quadratic": (quadratic, 0.0, 3.0),
    "rosenbrock": (rosenbrock, 0.0, 2.0),
    "rastrigin": (rastrigin, 0.0, 5.12),
}


def landscape(name: str) -> Callable:
    check_choice(name, "landscape", LANDSCAPES)
    return LANDSCAPES[name][0]


def sample_boltzmann(name, n: int, dim: int, *, beta: float = 2.0, seed: int = 0, box=None):
    """Samples of exp(-beta V) restricted to the landscape's box.

    Separable landscapes (quadratic, rastrigin) are sampled coordinate by coordinate and
    the double well through its structure (x_0 from its marginal, the others Gaussian given
    x_0), so the cost does not grow with the dimension; rosenbrock by rejection from the box.
    beta = 0 is the uniform distribution on the box.
    A callable V (a user's landscape, `box` = (lower, upper) required) is sampled by rejection
    from the box against the lowest V of a first batch of 2^16 uniform points: exact when that
    batch comes within ~1/beta of the minimum, which a narrow well in high dimension may not.

    **Returns:**

    `(points, box)`: (n, dim) float64 walkers and the sampling box `(lower, upper)`.
    """
    check_nonnegative(beta, "beta")
    rng = np.random.default_rng(seed)
    if callable(name):
        return _sample_by_rejection(name, n, dim, beta, rng, box)
    fitness = landscape(name)
    _, v_min, half = LANDSCAPES[name]
    box = (np.full(dim, -half), np.full(dim, half))
    if beta == 0:  # exp(-0 V) = 1: the uniform distribution on the box
        return rng.uniform(-half, half, (n, dim)), box
    if name == "quadratic":
        scales = np.sqrt(1.0 / (beta * np.arange(1, dim + 1)))
        return _truncated_normal(rng, np.broadcast_to(scales, (n, dim)), half), box
    if name == "rastrigin":
        return _rejection_1d(
            rng, lambda t: np.exp(-beta * (t**2 - 10.0 * np.cos(2 * np.pi * t) + 10.0)), n * dim, half, beta
        ).reshape(n, dim), box
    if name == "double_well" and dim > 1:
        return _double_well_sample(rng, n, dim, beta, half), box
    return _rejection(fitness, n, dim, beta, rng, (-half, half), v_min), box


def _sample_by_rejection(fitness, n: int, dim: int, beta: float, rng, box):
    if box is None:
        raise ValueError("sample_boltzmann of a callable V needs `box=(lower, upper)`.")
    lo, hi = (float(b) for b in box)
    batch = rng.uniform(lo, hi, size=(1 << 16, dim))
    v_min = float(np.nanmin(_values(fitness, batch)))
    return _rejection(fitness, n, dim, beta, rng, (lo, hi), v_min), (np.full(dim, lo), np.full(dim, hi))


def _values(fitness, points):
    return np.asarray(_batched(fitness)(points), dtype=float)


@functools.lru_cache(maxsize=16)
def _batched(fitness: Callable):
    """jit(vmap(fitness)), made once per landscape: a new jit per rejection round recompiled."""
    return jax.jit(jax.vmap(fitness))


def _rejection(fitness, n: int, dim: int, beta: float, rng, box, v_min: float):
    def accepted():
        trial = rng.uniform(box[0], box[1], size=(max(4 * n, 1024), dim))
        excess = np.maximum(_values(fitness, trial) - v_min, 0.0)
        return trial[rng.random(len(trial)) < np.exp(-beta * np.nan_to_num(excess, nan=np.inf))]

    return _collect(accepted, n, beta)


def _rejection_1d(rng, density, n: int, half: float, beta: float) -> np.ndarray:
    """n samples of an unnormalised 1D density on [-half, half] (max found on a fine grid)."""
    with np.errstate(all="ignore"):
        top = 1.05 * density(np.linspace(-half, half, 20001)).max()
    if not (np.isfinite(top) and top > 0):
        raise ValueError(
            f"the density exp(-beta V) with beta = {beta} is not a positive finite function on the "
            f"box [-{half}, {half}] (its maximum is {top}); give a finite beta > 0 (or 0 for uniform)."
        )

    def accepted():
        t = rng.uniform(-half, half, max(4 * n, 1024))
        return t[rng.random(t.size) * top < density(t)]

    return _collect(accepted, n, beta)


def _collect(accepted, n: int, beta: float, max_rounds: int = 200) -> np.ndarray:
    """The first n samples of rounds of `accepted()`, at most `max_rounds` of them (a density
    too narrow for its box would loop for ever)."""
    out, total = [], 0
    for _ in range(max_rounds):
        out.append(accepted())
        total += len(out[-1])
        if total >= n:
            return np.concatenate(out)[:n]
    raise ValueError(
        f"sampling exp(-{beta} V) by rejection accepted {total} of {n} walkers in {max_rounds} rounds; "
        "lower beta, shrink the box, or give the walkers yourself (--points)."
    )


def _truncated_normal(rng, scale, half: float) -> np.ndarray:
    """N(0, scale^2) restricted to [-half, half], by the inverse CDF in its symmetric form
    x = sqrt(2) scale erfinv((2u - 1) erf(half / (sqrt(2) scale))), which keeps its precision
    when scale >> half (a tiny beta: nearly uniform), where ndtri(ndtr(.)) rounds to 0."""
    reach = scipy.special.erf(half / (np.sqrt(2.0) * scale))
    return np.sqrt(2.0) * scale * scipy.special.erfinv((2.0 * rng.random(scale.shape) - 1.0) * reach)


def _double_well_sample(rng, n: int, dim: int, beta: float, half: float) -> np.ndarray:
    """x_0 from its marginal exp(-beta (x_0^2 - 1)^2) Z(x_0)^(d-1), Z the truncated Gaussian
    integral of each other coordinate; then x_k | x_0 ~ N(0, 1 / (beta (1 + x_0^2))) on the box."""

    def log_marginal(t):
        s = np.sqrt(beta * (1.0 + t**2))
        z = np.sqrt(2.0 * np.pi) / s * scipy.special.erf(half * s / np.sqrt(2.0))
        return -beta * (t**2 - 1.0) ** 2 + (dim - 1) * np.log(z)

    top = np.max(log_marginal(np.linspace(-half, half, 20001)))  # Z^(d-1) overflows from d ~ 500
    x0 = _rejection_1d(rng, lambda t: np.exp(log_marginal(t) - top), n, half, beta)
    scale = 1.0 / np.sqrt(beta * (1.0 + x0**2))
    rest = _truncated_normal(rng, np.broadcast_to(scale[:, None], (n, dim - 1)), half)
    return np.column_stack([x0, rest])
