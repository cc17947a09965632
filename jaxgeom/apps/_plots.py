"""Diagnostic figures (matplotlib is imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

NEIGHBOUR_COUNTS = (6, 10, 16, 30)


ESTIMATION_KEYS = ("points", "valid", "values", "hessian_fd", "hessian_geometric", "eigenvalues_fd",
                   "eigenvalues_geometric", "metrics")


def _check_estimation_result(result) -> None:
    if not isinstance(result, dict):
        raise TypeError(f"`result` must be the dict of jaxgeom.compare_estimation_methods or "
                        f"validate_on_synthetic_function; got {type(result).__name__}.")
    comparison = result.get("comparison", result)
    missing = [key for key in ESTIMATION_KEYS if not isinstance(comparison, dict) or key not in comparison]
    if missing:
        raise ValueError(f"`result` lacks {missing}: pass the dict that jaxgeom.compare_estimation_methods or "
                         "jaxgeom.validate_on_synthetic_function returned.")


def plot_estimation_quality(result: dict, path, *, dpi: int = 100) -> Path:
    """The chapter's four-panel diagnostic of Hessian estimation, written to `path` (PNG).

    **Arguments:**

    - `result`: the dict of [`jaxgeom.compare_estimation_methods`][], or of
      [`jaxgeom.validate_on_synthetic_function`][] (then errors are against the
      analytic Hessian; otherwise against the geometric Hessian).
    - `dpi`: resolution of the PNG.

    Panels: FD vs geometric eigenvalues; spatial map of the per-walker relative
    error; median error against the number of k-NN neighbours (the fit redone on
    k-NN graphs); histogram of the per-walker errors.
    """
    _check_estimation_result(result)
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
    if medians:
        axes[1, 0].set_ylim(*_decade_limits(medians))
    axes[1, 1].hist(np.log10(error[ok] + 1e-16), bins=40)
    axes[1, 1].set(xlabel="log10 relative Hessian error", ylabel="walkers", title="error distribution")
    if truth is None:
        fig.suptitle("reference: the geometric Hessian C^-1 - eps_Sigma I, which measures walker spacing (~1/h^2), "
                     "not V;\nit matches H only for adaptive-gas equilibrium samples: for other samples large "
                     "errors are expected", fontsize=9)
    return save_figure(fig, path, dpi=dpi)


def _decade_limits(values) -> tuple[float, float]:
    """Log-axis limits on whole decades holding `values`, at least one decade apart, so that a
    flat series is drawn flat (matplotlib would stretch 0.99016..0.99029 over the axis)."""
    finite = np.asarray(values, float)
    finite = finite[np.isfinite(finite) & (finite > 0)]
    if not finite.size:
        return 0.1, 1.0
    low, high = np.floor(np.log10(finite.min())), np.ceil(np.log10(finite.max()))
    return 10.0 ** low, 10.0 ** max(high, low + 1)


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

    from ..geometry._estimation import estimate_hessian
    from ..tessellation._knn import knn_graph

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


def save_figure(fig, path, dpi: int = 100, layout: bool = True) -> Path:
    """Lay out (unless the figure has its own layout engine: `layout=False`), write (creating
    the folder) and close a figure; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if layout:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path


# observable: (panel title, y-axis label); energies are in the landscape's units
OBSERVABLE_LABELS = {
    "mean_fitness": ("mean fitness", "<V> over walkers"),
    "best_fitness": ("best fitness", "min V"),
    "velocity_variance": ("velocity variance per component", "tr Cov(v) / d"),
    "degree_weighted_variance": ("degree-weighted velocity variance", "tr Cov_w(v) / d, w: viscous degree"),
    "mean_ricci": ("mean Ricci scalar (Hessian metric)", "<R>_g, tier-2 walkers"),
    "volume_distortion": ("volume distortion", "Var(V_i / <V>), tier 2"),
    "mean_shape_distortion": ("mean shape ratio", "<r_in / r_circ>, tier 2 (1: round)"),
    "mean_expansion": ("expansion (volume-weighted)", "d ln(sum V_i)/dt, tier 2 at both steps"),
    "n_clones": ("clones per step", "walkers cloned"),
    "nu": ("viscous coupling", "nu"),
    "eps_sigma": ("metric floor", "eps_Sigma"),
    "spectral_gap": ("spectral gap (largest component)", "lambda_2 of the graph Laplacian"),
    "prism_fraction": ("prisms (no neighbour lost or gained)", "fraction, tier 2 at both steps"),
    "simple_scutoid_fraction": ("simple scutoids (<= 1 lost, <= 1 gained)", "fraction, tier 2 at both steps"),
    "complex_scutoid_fraction": ("complex scutoids (>= 2 lost or gained)", "fraction, tier 2 at both steps"),
    "mean_neighbor_change": ("neighbour change per walker", "<lost + gained>, tier 2 at both steps"),
}


def _landscape_grid(fitness, lo, hi, d: int):
    import jax
    import jax.numpy as jnp

    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 160), np.linspace(lo[1], hi[1], 160))
    plane = np.zeros((gx.size, d))
    plane[:, 0], plane[:, 1] = gx.ravel(), gy.ravel()
    return gx, gy, np.asarray(jax.vmap(fitness)(jnp.asarray(plane))).reshape(gx.shape)


def _contour_levels(values, n: int = 14):
    """Linear levels, or log-spaced ones above the minimum when most of the range lies in a
    thin layer near it (a valley such as Rosenbrock's is invisible with linear levels)."""
    low, high = float(np.nanmin(values)), float(np.nanmax(values))
    above = values - low
    if high > low and np.nanmedian(above) < 0.1 * (high - low):
        floor = max(np.nanpercentile(above, 1), 1e-6 * (high - low))
        return low + np.geomspace(floor, high - low, n)
    return np.linspace(low, high, n + 2)[1:-1]


def _frame(positions, box):
    """Limits of the first two coordinates that hold every walker, with a 5% margin, within
    the box (+ margin)."""
    lo, hi = positions[:, :2].min(axis=0), positions[:, :2].max(axis=0)
    pad = 0.05 * np.maximum(hi - lo, 1e-3)
    return np.maximum(lo - pad, box[0] - pad), np.minimum(hi + pad, box[1] + pad)


def _shared_ricci_norm(snapshots):
    """One symmetric-log colour scale for every panel: the uniform start has |R| orders of
    magnitude above a settled swarm, so linear scales per panel cannot be compared."""
    from matplotlib.colors import SymLogNorm

    pooled = np.concatenate([np.abs(s["ricci"][np.isfinite(s["ricci"])]) for s in snapshots
                             if s["ricci"] is not None] or [np.ones(1)])
    top = max(float(np.percentile(pooled, 99)), 1e-12)
    return SymLogNorm(linthresh=max(float(np.percentile(pooled, 25)), 1e-4 * top), vmin=-top, vmax=top, base=10)


def _symlog_ticks(norm):
    """0 and +-10^k for the decades between the linear threshold and the top (every second
    decade beyond four), so the colour bar's labels do not overlap."""
    decades = np.arange(np.ceil(np.log10(norm.linthresh)), np.floor(np.log10(norm.vmax)) + 1)
    decades = decades[:: 1 + (len(decades) > 4)]
    return np.concatenate([-(10.0 ** decades[::-1]), [0.0], 10.0 ** decades])


def plot_swarm_snapshots(fitness, snapshots: list, box, path) -> Path:
    """Walkers coloured by their Ricci scalar (one symmetric-log colour scale for every panel)
    over contours of V, one column per snapshot `{"step", "positions", "ricci"}` (ricci None on
    a k-NN graph: walkers coloured by V instead). The top row shares one frame that holds
    every walker, so the panels compare; the bottom row shares a frame zoomed on where the
    walkers of the later snapshots are (`zoom_frame`), drawn as a dashed box above and its
    width written. Beyond 2D the panels show the projection on (x_1, x_2) and the contours
    V(x_1, x_2, 0, ..., 0); the figure says so."""
    plt = pyplot()
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    d = snapshots[0]["positions"].shape[1]
    has_ricci = any(s["ricci"] is not None for s in snapshots)
    norm = _shared_ricci_norm(snapshots) if has_ricci else None
    fig, axes = plt.subplots(2, len(snapshots), figsize=(3.4 * len(snapshots) + 1.4, 7.2), squeeze=False,
                             layout="constrained")
    lo, hi = _frame(np.concatenate([snap["positions"] for snap in snapshots]), box)  # one frame: comparable
    later = snapshots[1:] or snapshots
    zoom_lo, zoom_hi = zoom_frame(np.concatenate([snap["positions"] for snap in later]))
    for row, (flo, fhi) in enumerate(((lo, hi), (zoom_lo, zoom_hi))):
        gx, gy, values = _landscape_grid(fitness, flo, fhi, d)
        for ax, snap in zip(axes[row], snapshots):
            mapped = _draw_snapshot(ax, fitness, snap, gx, gy, values, norm, has_ricci, size=4 if row else 3)
            ax.set(xlim=(flo[0], fhi[0]), ylim=(flo[1], fhi[1]), xlabel="x_1")
            ax.xaxis.set_major_locator(MaxNLocator(4))
            ax.yaxis.set_major_locator(MaxNLocator(5))
            if row == 0:
                ax.set_title(f"step {snap['step']}")
                ax.add_patch(Rectangle(zoom_lo, *(zoom_hi - zoom_lo), fill=False, ls="--", lw=1.0, ec="k"))
            else:
                ax.set_title(f"step {snap['step']}, zoomed", fontsize=9)
    axes[0, 0].set_ylabel("x_2")
    width = float(np.max(zoom_hi - zoom_lo))
    axes[1, 0].set_ylabel(f"x_2   (zoom: frame {width:.3g} wide)")
    label = "Ricci scalar R (symmetric log scale)" if has_ricci else "V(x)"
    bar = fig.colorbar(mapped, ax=axes.ravel().tolist(), label=label, fraction=0.03, pad=0.01)
    if has_ricci:
        bar.set_ticks(_symlog_ticks(norm))
    what = ("walkers coloured by the Ricci scalar of the Hessian metric g = H + eps_Sigma I (black: hull "
            "tiers, no R)" if has_ricci else "k-NN graph (no simplices, so no Ricci scalar): walkers coloured by V")
    where = (f"{d}D swarm projected on (x_1, x_2), contours of V(x_1, x_2, 0, ..., 0)" if d > 2
             else "contours of V")
    fig.suptitle(f"{what}\n{where}; top: one frame holding every walker; bottom: one frame {width:.3g} wide "
                 "zoomed on the later walkers (dashed box above)", fontsize=9)
    return save_figure(fig, path, dpi=72, layout=False)


def zoom_frame(positions, share: float = 0.97):
    """A square frame (lower, upper) of the first two coordinates about the median walker that
    holds `share` of the walkers, with a 10% margin: the bottom row of `plot_swarm_snapshots`."""
    xy = positions[:, :2]
    centre = np.median(xy, axis=0)
    radius = float(np.quantile(np.max(np.abs(xy - centre), axis=1), share))
    radius = 1.1 * max(radius, 1e-6 * max(float(np.max(np.abs(xy))), 1.0))
    return centre - radius, centre + radius


def _draw_snapshot(ax, fitness, snap, gx, gy, values, norm, has_ricci: bool, size: float):
    x = snap["positions"]
    ax.contour(gx, gy, values, levels=_contour_levels(values), colors="0.55", linewidths=0.5)
    if has_ricci:
        ok = np.isfinite(snap["ricci"]) if snap["ricci"] is not None else np.zeros(len(x), bool)
        ax.scatter(x[~ok, 0], x[~ok, 1], s=size / 3, c="k")
        return ax.scatter(x[ok, 0], x[ok, 1], s=size, c=snap["ricci"][ok], cmap="coolwarm", norm=norm)
    v = np.asarray(_fitness_at(fitness, x))
    return ax.scatter(x[:, 0], x[:, 1], s=size, c=v, cmap="viridis", vmin=0.0 if v.min() >= 0 else None)


def _fitness_at(fitness, x):
    import jax

    return jax.vmap(fitness)(x)


def _first_finite(values) -> float:
    values = np.asarray(values)
    return float(values[np.isfinite(values)][0])


def _constant(values) -> bool:
    finite = np.asarray(values)[np.isfinite(values)]
    return finite.size > 0 and np.ptp(finite) <= 1e-12 * max(np.abs(finite).max(), 1e-300)


def plot_observables(series: dict, gap_steps, gaps, path, gap_rounding=None) -> Path:
    """Every observable of a `jaxgeom.simulate` history against time, one panel each, with
    labelled axes. Constant series (nu, eps_Sigma without annealing) are named in the title
    instead of drawn; observables that are NaN throughout (the Voronoi ones on a k-NN graph)
    are listed; NaN entries (the expansion at step 0) are skipped, the line joins the rest.
    `gap_rounding` (bool per gap) marks the gaps below float64 resolution, drawn as x at 0."""
    plt = pyplot()
    names, constant, undefined = observable_panels(series, gaps)
    cols = 3
    rows = max(-(-len(names) // cols), 1)
    fig, axes = plt.subplots(rows, cols, figsize=(4.5 * cols, 2.9 * rows + 0.6), squeeze=False)
    t = np.asarray(series["time"])
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    for ax, name in zip(axes.ravel(), names):
        _plot_one(ax, name, series, t, np.asarray(gap_steps) * dt, gaps, gap_rounding)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    notes = []
    if constant:
        notes.append("constant: " + ", ".join(f"{n} = {_first_finite(series[n]):.4g}" for n in constant))
    if undefined:
        notes.append("undefined on this graph (no Voronoi cells): " + ", ".join(undefined))
    fig.suptitle("; ".join(n for n in notes if n) or "observables", fontsize=9)
    return save_figure(fig, path)


def observable_panels(series: dict, gaps) -> tuple[list, list, list]:
    """(drawn, constant, undefined): the observables `plot_observables` draws, those constant
    over the run and those NaN throughout."""
    names = [n for n in series if n not in ("time", "ricci_resolution")]
    constant = [n for n in names if _constant(series[n])]
    undefined = [n for n in names if not np.isfinite(series[n]).any()]
    drawn = [n for n in names if n not in constant and n not in undefined] + (["spectral_gap"] if len(gaps) else [])
    return drawn, constant, undefined


def _plot_one(ax, name, series, t, gap_times, gaps, gap_rounding=None):
    title, ylabel = OBSERVABLE_LABELS.get(name, (name, name))
    if name == "spectral_gap":
        rounding = np.zeros(len(gaps), bool) if gap_rounding is None else np.asarray(gap_rounding, bool)
        gaps = np.asarray(gaps)
        ax.plot(gap_times[~rounding], gaps[~rounding], "o-", ms=3)
        if rounding.any():
            ax.plot(gap_times[rounding], np.zeros(rounding.sum()), "rx", label="below float64 resolution")
            ax.legend(fontsize=7)
    else:
        y = np.asarray(series[name])
        ok = np.isfinite(y)
        ax.plot(t[ok], y[ok], lw=1)
        if (~ok).any():
            title += f" (NaN at {int((~ok).sum())} step{'s' if (~ok).sum() > 1 else ''}, skipped)"
    if name == "mean_ricci" and "ricci_resolution" in series:  # |R| below this is rounding
        floor = np.asarray(series["ricci_resolution"])
        ax.fill_between(t, -floor, floor, color="0.85", label="rounding floor (+-)")
        ax.legend(fontsize=7)
    ax.set_title(title, fontsize=10)
    ax.set(xlabel="time (steps x dt)", ylabel=ylabel)
