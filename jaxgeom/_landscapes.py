"""Built-in fitness landscapes V: R^d -> R and exact sampling from exp(-beta V)."""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

from ._checks import check_choice


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


def sample_boltzmann(name: str, n: int, dim: int, *, beta: float = 2.0, seed: int = 0):
    """Exact samples of exp(-beta V) restricted to the landscape's box, by rejection.

    **Returns:**

    `(points, box)`: (n, dim) float64 walkers and the sampling box `(lower, upper)`.
    """
    fitness = landscape(name)
    _, v_min, half = LANDSCAPES[name]
    rng = np.random.default_rng(seed)
    accepted, total = [], 0
    while total < n:
        trial = rng.uniform(-half, half, size=(max(4 * n, 1024), dim))
        keep = rng.random(len(trial)) < np.exp(-beta * (np.asarray(fitness(trial)) - v_min))
        accepted.append(trial[keep])
        total += int(keep.sum())
    box = (np.full(dim, -half), np.full(dim, half))
    return np.concatenate(accepted)[:n], box
