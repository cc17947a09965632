"""Cross-validation of fitness-derivative estimates: finite differences vs the geometric method."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..base._checks import check_choice, check_integer, check_nonnegative, warn_at_caller
from ..geometry._estimation import estimate_gradient, estimate_hessian, geometric_hessian
from ..tessellation._graph import Tessellation
from ..tessellation._knn import knn_graph
from ._landscapes import quadratic, rastrigin, rosenbrock

# The chapter's interpretation of the eigenvalue correlation rho.
EXCELLENT, GOOD = 0.8, 0.6
SYNTHETIC = {"quadratic": (quadratic, 2.0), "rosenbrock": (rosenbrock, 2.0), "rastrigin": (rastrigin, 5.12)}
# validate_on_synthetic_function: `passed` needs gradient RMSE / RMS |grad V| and the
# Hessian relative Frobenius error below these (quadratic: exact fit, to rounding).
PASS_THRESHOLDS = {"quadratic": (1e-8, 1e-8), "rosenbrock": (0.2, 0.3), "rastrigin": (0.5, 0.8)}


def compare_estimation_methods(
    tess: Tessellation, values, *, eps_sigma, compute_full_hessian: bool = True, eps_reg: float = 1e-5
) -> dict:
    """Finite-difference (least-squares) estimates against the geometric Hessian.

    **Arguments:**

    - `tess`, `values`: the graph and (N,) fitness values.
    - `eps_sigma`: the spectral floor of g = H + eps_Sigma I (user's model).
    - `compute_full_hessian`: full quadratic fit (else the diagonal estimate).

    **Returns:**

    A dict with `gradient` (N, d), `hessian_fd` (N, d, d) or (N, d),
    `hessian_geometric` (N, d, d), `eigenvalues_fd` and `eigenvalues_geometric`
    (N, d, ascending; the diagonal itself, sorted, when not full), `valid` (tier 2 with
    finite estimates), and `metrics`: `eigenvalue_correlation` (Pearson, over all
    eigenvalues of valid walkers), `frobenius_agreement` (mean over valid walkers of
    1 - |H_fd - H_geo|_F / (|H_fd|_F + |H_geo|_F); full Hessian only),
    `method_preference` ("excellent" rho > 0.8, "good" 0.6 < rho <= 0.8, "poor")
    and `n_valid`.

    What the geometric method can and cannot recover: H_geo = C^-1 - eps_Sigma I
    with C the neighbour covariance, so it measures the local *spacing* of the
    walkers (g ~ 1 / h^2), not the fitness. It equals the Hessian only when the
    sampling was designed to make the neighbour covariance proportional to H^-1
    (the adaptive gas at equilibrium, chapter Theorem 470); for walkers drawn from
    exp(-x^T A x / 2) or uniformly, neighbourhoods are locally isotropic and H_geo
    reflects density, not A (see bench/results/estimation.json for the measured
    agreement). The finite-difference fit needs no such assumption.
    """
    grad = estimate_gradient(tess, values)
    kind = "full" if compute_full_hessian else "diagonal"
    h_fd = estimate_hessian(tess, values, kind=kind)
    h_geo = geometric_hessian(tess, eps_sigma, eps_reg=eps_reg)
    finite = jnp.all(jnp.isfinite(h_fd.reshape(tess.n_points, -1)), axis=1) & jnp.all(jnp.isfinite(grad), axis=1)
    warn_if_undetermined(tess, np.asarray(finite), "compare_estimation_methods")
    valid = np.asarray(tess.interior & finite & jnp.all(jnp.isfinite(h_geo.reshape(tess.n_points, -1)), axis=1))
    eig_fd = (
        jnp.linalg.eigvalsh(jnp.where(valid[:, None, None], h_fd, 0.0))
        if compute_full_hessian
        else jnp.sort(h_fd, axis=1)
    )
    eig_geo = jnp.linalg.eigvalsh(jnp.where(valid[:, None, None], h_geo, 0.0))
    metrics = _agreement(
        np.asarray(eig_fd)[valid],
        np.asarray(eig_geo)[valid],
        np.asarray(h_fd)[valid] if compute_full_hessian else None,
        np.asarray(h_geo)[valid],
    )
    return {
        "gradient": grad,
        "hessian_fd": h_fd,
        "hessian_geometric": h_geo,
        "eigenvalues_fd": eig_fd,
        "eigenvalues_geometric": eig_geo,
        "valid": valid,
        "metrics": metrics,
        "points": np.asarray(tess.points),
        "values": np.asarray(values),
    }


def warn_if_undetermined(tess: Tessellation, determined: np.ndarray, caller: str) -> None:
    """A RuntimeWarning when the Hessian fit is NaN at most walkers, with the fix."""
    n, d = tess.n_points, tess.dim
    if determined.sum() >= 0.5 * n:
        return
    needed = (d + 1) * (d + 2) // 2
    fix = (
        f"build the k-NN graph with k >= {2 * needed} (knn_graph(points, k), or analyze's --k)"
        if tess.simplices is None
        else "use a k-NN graph with more neighbours"
    )
    warn_at_caller(
        f"{caller}: the Hessian fit is undetermined (NaN) at {n - int(determined.sum())} of {n} walkers: "
        f"a quadratic fit in d = {d} has (d + 1)(d + 2)/2 = {needed} coefficients and each walker has "
        f"{tess.neighbors.shape[1]} neighbour slots; {fix}.",
        RuntimeWarning,
    )


def _agreement(eig_fd, eig_geo, h_fd, h_geo) -> dict:
    if len(eig_fd) < 2:
        rho = float("nan")
    else:
        rho = float(np.corrcoef(eig_fd.ravel(), eig_geo.ravel())[0, 1])
    out: dict[str, Any] = {"eigenvalue_correlation": rho, "n_valid": int(len(eig_fd))}
    if h_fd is not None and len(h_fd):
        diff = np.linalg.norm(h_fd - h_geo, axis=(1, 2))
        total = np.linalg.norm(h_fd, axis=(1, 2)) + np.linalg.norm(h_geo, axis=(1, 2))
        out["frobenius_agreement"] = float(np.mean(1.0 - diff / np.where(total > 0, total, 1.0)))
    out["method_preference"] = "excellent" if rho > EXCELLENT else "good" if rho > GOOD else "poor"
    return out


def validate_on_synthetic_function(
    name: str, *, n_walkers: int = 100, dim: int = 2, eps_sigma: float = 0.1, seed: int = 0, k: int | None = None
) -> dict:
    """Estimation errors against analytic derivatives (jax autodiff) on a synthetic function.

    Walkers are uniform in the function's box ([-2, 2]^d, Rastrigin [-5.12, 5.12]^d),
    with a k-NN graph (k = 10 as in the chapter's table, at least the d(d+3)/2 + 2
    a quadratic fit needs). Interior walkers (all coordinates within 80% of the box)
    are scored.

    **Returns:**

    dict: `gradient_rmse`, `gradient_relative_rmse` (over the RMS of |grad V|),
    `hessian_frobenius_error` (median over walkers of |H_est - H|_F / |H|_F),
    `fd_geometric_correlation`, `n_scored`, `thresholds` and `passed`: both relative
    errors below `PASS_THRESHOLDS[name]` (quadratic: the fit is exact, 1e-8).
    """
    check_choice(name, "name", SYNTHETIC)
    check_integer(n_walkers, "n_walkers", 4)
    check_integer(dim, "dim", 1)
    check_integer(seed, "seed")
    if k is not None:
        check_integer(k, "k", 1)
    check_nonnegative(eps_sigma, "eps_sigma")
    fitness, half = SYNTHETIC[name]
    k = max(10, dim * (dim + 3) // 2 + 2) if k is None else k
    x = np.random.default_rng(seed).uniform(-half, half, size=(n_walkers, dim))
    tess = knn_graph(x, k)
    xj = jnp.asarray(x, tess.points.dtype)
    values = jax.vmap(fitness)(xj)
    true_grad, true_hess = np.asarray(jax.vmap(jax.grad(fitness))(xj)), np.asarray(jax.vmap(jax.hessian(fitness))(xj))
    comparison = compare_estimation_methods(tess, values, eps_sigma=eps_sigma)
    scored = np.all(np.abs(x) < 0.8 * half, axis=1) & np.all(np.isfinite(np.asarray(comparison["gradient"])), axis=1)
    grad_err = np.asarray(comparison["gradient"])[scored] - true_grad[scored]
    hess_err = np.linalg.norm(np.asarray(comparison["hessian_fd"])[scored] - true_hess[scored], axis=(1, 2))
    rmse = float(np.sqrt(np.mean(np.sum(grad_err**2, axis=1))))
    scale = float(np.sqrt(np.mean(np.sum(true_grad[scored] ** 2, axis=1))))
    rel_grad = rmse / scale if scale > 0 else rmse
    rel_hess = float(np.median(hess_err / np.linalg.norm(true_hess[scored], axis=(1, 2))))
    g_tol, h_tol = PASS_THRESHOLDS[name]
    return {
        "function": name,
        "n_walkers": n_walkers,
        "dim": dim,
        "k": k,
        "n_scored": int(scored.sum()),
        "gradient_rmse": rmse,
        "gradient_relative_rmse": rel_grad,
        "hessian_frobenius_error": rel_hess,
        "fd_geometric_correlation": comparison["metrics"]["eigenvalue_correlation"],
        "thresholds": {"gradient_relative_rmse": g_tol, "hessian_frobenius_error": h_tol},
        "passed": bool(rel_grad < g_tol and rel_hess < h_tol),
        "comparison": comparison,
        "true_hessian": true_hess,
        "scored": scored,
    }
