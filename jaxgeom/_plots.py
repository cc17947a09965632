"""Diagnostic figures (matplotlib is imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

NEIGHBOUR_COUNTS = (6, 10, 16, 30)


def plot_estimation_quality(result: dict, path) -> Path:
    """The chapter's four-panel diagnostic of Hessian estimation, written to `path` (PNG).

    **Arguments:**

    - `result`: the dict of [`jaxgeom.compare_estimation_methods`][], or of
      [`jaxgeom.validate_on_synthetic_function`][] (then errors are against the
      analytic Hessian; otherwise against the geometric Hessian).

    Panels: FD vs geometric eigenvalues; spatial map of the per-walker relative
    error; median error against the number of k-NN neighbours (the fit redone on
    k-NN graphs); histogram of the per-walker errors.
    """
    plt = pyplot()
    comparison = result.get("comparison", result)
    truth = result.get("true_hessian")
    points, valid = comparison["points"], comparison["valid"]
    h_fd = np.asarray(comparison["hessian_fd"])
    reference = truth if truth is not None else np.asarray(comparison["hessian_geometric"])
    label = "analytic" if truth is not None else "geometric"
    error = _relative_error(h_fd, reference)
    fig, axes = plt.subplots(2, 2, figsize=(11, 9))
    e_fd, e_geo = np.asarray(comparison["eigenvalues_fd"])[valid], np.asarray(comparison["eigenvalues_geometric"])[valid]
    axes[0, 0].scatter(e_geo.ravel(), e_fd.ravel(), s=3, alpha=0.5)
    rho = comparison["metrics"]["eigenvalue_correlation"]
    axes[0, 0].set(xlabel="geometric eigenvalue", ylabel="finite-difference eigenvalue", title=f"eigenvalues, rho = {rho:.2f}")
    ok = valid & np.isfinite(error)
    sc = axes[0, 1].scatter(points[ok, 0], points[ok, 1], c=np.log10(error[ok] + 1e-16), s=4, cmap="magma")
    fig.colorbar(sc, ax=axes[0, 1], label=f"log10 relative error vs {label}")
    axes[0, 1].set(title="spatial quality map (first two coordinates)")
    ks, medians = _error_by_neighbour_count(points, comparison["values"], reference, valid)
    axes[1, 0].loglog(ks, medians, "o-")
    axes[1, 0].set(xlabel="k (k-NN neighbours)", ylabel=f"median relative error vs {label}", title="convergence with neighbours")
    axes[1, 1].hist(np.log10(error[ok] + 1e-16), bins=40)
    axes[1, 1].set(xlabel="log10 relative Hessian error", ylabel="walkers", title="error distribution")
    if truth is None:
        fig.suptitle("reference: the geometric Hessian C^-1 - eps_Sigma I, which measures walker spacing (~1/h^2), "
                     "not V;\nit matches H only for adaptive-gas equilibrium samples: for other samples large "
                     "errors are expected", fontsize=9)
    return save_figure(fig, path)


def _relative_error(estimate, reference):
    if estimate.ndim == 2:  # a diagonal estimate
        reference = np.diagonal(reference, axis1=1, axis2=2)
        return np.linalg.norm(estimate - reference, axis=1) / np.maximum(np.linalg.norm(reference, axis=1), 1e-300)
    diff = np.linalg.norm(estimate - reference, axis=(1, 2))
    return diff / np.maximum(np.linalg.norm(reference, axis=(1, 2)), 1e-300)


def _error_by_neighbour_count(points, values, reference, valid):
    """Median error of the k-NN fit for each k in NEIGHBOUR_COUNTS. One graph at the largest k,
    nearest first; the smaller graphs keep its first k columns (the rest at the sentinel N), so
    every fit has one shape and compiles once."""
    import equinox as eqx
    import jax.numpy as jnp

    from ._estimation import estimate_hessian
    from ._knn import knn_graph

    n, d = points.shape
    ks = [k for k in NEIGHBOUR_COUNTS if d * (d + 3) // 2 <= k < n]
    if not ks:
        return ks, []
    full = knn_graph(points, ks[-1])
    medians = []
    for k in ks:
        nbrs = jnp.where(jnp.arange(ks[-1]) < k, full.neighbors, n)
        est = np.asarray(estimate_hessian(eqx.tree_at(lambda t: t.neighbors, full, nbrs), values))
        err = _relative_error(est, reference)[valid]
        medians.append(float(np.nanmedian(err)))
    return ks, medians


def pyplot():
    """matplotlib.pyplot on the non-interactive Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 100) -> Path:
    """Lay out, write (creating the folder) and close a figure; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


def _landscape_grid(fitness, lo, hi, d: int):
    import jax
    import jax.numpy as jnp

    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 120), np.linspace(lo[1], hi[1], 120))
    plane = np.zeros((gx.size, d))
    plane[:, 0], plane[:, 1] = gx.ravel(), gy.ravel()
    return gx, gy, np.asarray(jax.vmap(fitness)(jnp.asarray(plane))).reshape(gx.shape)


def plot_swarm_snapshots(fitness, snapshots: list, box, path) -> Path:
    """Walkers coloured by their Ricci scalar over the contours of V (first two coordinates,
    other coordinates 0), one panel per snapshot `{"step", "positions", "ricci"}`, each
    zoomed to the swarm (the central 98% of walkers) within `box`."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(snapshots), figsize=(4.4 * len(snapshots), 4.2), squeeze=False)
    for ax, snap in zip(axes[0], snapshots):
        x, ricci = snap["positions"], snap["ricci"]
        lo = np.maximum(np.percentile(x[:, :2], 1, axis=0), box[0])
        hi = np.minimum(np.percentile(x[:, :2], 99, axis=0), box[1])
        pad = 0.1 * np.max(hi - lo) + 1e-3
        lo, hi = lo - pad, hi + pad
        gx, gy, values = _landscape_grid(fitness, lo, hi, x.shape[1])
        ax.contour(gx, gy, values, levels=15, colors="0.6", linewidths=0.6)
        ok = np.isfinite(ricci) if ricci is not None else np.zeros(len(x), bool)
        ax.scatter(x[~ok, 0], x[~ok, 1], s=2, c="0.7")
        if ok.any():
            scale = np.percentile(np.abs(ricci[ok]), 90)
            sc = ax.scatter(x[ok, 0], x[ok, 1], s=3, c=ricci[ok], cmap="coolwarm", vmin=-scale, vmax=scale)
            fig.colorbar(sc, ax=ax, label="Ricci scalar (Hessian metric)")
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), title=f"step {snap['step']}")
    return save_figure(fig, path, dpi=72)


def plot_observables(series: dict, gap_steps, gaps, path) -> Path:
    """Every observable of a `jaxgeom.simulate` history against time, one panel each."""
    plt = pyplot()
    names = [n for n in series if n not in ("time", "ricci_resolution")] + (["spectral_gap"] if len(gaps) else [])
    cols = 3
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 2.8 * rows), squeeze=False)
    t = series["time"]
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    for ax, name in zip(axes.ravel(), names):
        if name == "spectral_gap":
            ax.plot(np.asarray(gap_steps) * dt, gaps, "o-")
        else:
            ax.plot(t, series[name], lw=1)
        if name == "mean_ricci" and "ricci_resolution" in series:  # |R| below this is rounding
            floor = np.asarray(series["ricci_resolution"])
            ax.fill_between(t, -floor, floor, color="0.85", label="resolution (+-)")
            ax.legend(fontsize=7)
        ax.set(title=name, xlabel="time")
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    return save_figure(fig, path)
