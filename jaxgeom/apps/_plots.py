"""Diagnostic figures (matplotlib is imported lazily)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

NEIGHBOUR_COUNTS = (6, 10, 16, 30)


ESTIMATION_KEYS = (
    "points",
    "valid",
    "values",
    "hessian_fd",
    "hessian_geometric",
    "eigenvalues_fd",
    "eigenvalues_geometric",
    "metrics",
)


def _check_estimation_result(result) -> None:
    if not isinstance(result, dict):
        raise TypeError(
            f"`result` must be the dict of jaxgeom.compare_estimation_methods or "
            f"validate_on_synthetic_function; got {type(result).__name__}."
        )
    comparison = result.get("comparison", result)
    missing = [key for key in ESTIMATION_KEYS if not isinstance(comparison, dict) or key not in comparison]
    if missing:
        raise ValueError(
            f"`result` lacks {missing}: pass the dict that jaxgeom.compare_estimation_methods or "
            "jaxgeom.validate_on_synthetic_function returned."
        )


def plot_estimation_quality(result: dict, path, *, dpi: int = 100) -> Path:
    """The chapter's four-panel diagnostic of Hessian estimation, written to `path` (PNG).

    **Arguments:**

    - `result`: the dict of [`jaxgeom.compare_estimation_methods`][], or of
      [`jaxgeom.validate_on_synthetic_function`][], or `{"comparison": <the former>,
      "true_hessian": (N, d, d)}` for any landscape whose Hessian is known. With a true Hessian
      the errors are against it (exact); otherwise against the geometric Hessian, which
      measures the walkers' spacing, not V (the figure says so).
    - `dpi`: resolution of the PNG.

    Panels: least-squares (FD) eigenvalues against the reference's, on axes holding the
    central 98% of both (the points beyond are counted in the title); the spatial map of
    the per-walker relative error; with a true Hessian, the median error of the k-NN fit on
    random subsets of the walkers against their number (the fit converges as the spacing
    h ~ N^(-1/d) shrinks), otherwise against the number of neighbours k; the histogram of
    the per-walker errors.
    """
    _check_estimation_result(result)
    comparison = result.get("comparison", result)
    truth = result.get("true_hessian")
    points, valid = comparison["points"], comparison["valid"]
    h_fd = np.asarray(comparison["hessian_fd"])
    reference = np.asarray(truth) if truth is not None else np.asarray(comparison["hessian_geometric"])
    label = "exact" if truth is not None else "geometric"
    error = relative_error(h_fd, reference)
    fig, axes = subplots(2, 2, figsize=(11, 9))
    e_fd = np.asarray(comparison["eigenvalues_fd"])[valid]
    e_ref = (
        np.linalg.eigvalsh(reference[valid])
        if truth is not None
        else np.asarray(comparison["eigenvalues_geometric"])[valid]
    )
    _eigenvalue_panel(axes[0, 0], e_ref.ravel(), e_fd.ravel(), label)
    ok = valid & np.isfinite(error)
    sc = axes[0, 1].scatter(points[ok, 0], points[ok, 1], c=np.log10(error[ok] + 1e-16), s=4, cmap="magma")
    fig.colorbar(sc, ax=axes[0, 1], label=f"log10 relative error vs {label}")
    axes[0, 1].set(title="spatial quality map (first two coordinates)", xlabel="x_1", ylabel="x_2")
    if truth is not None:
        sizes, medians = _error_by_walker_count(points, comparison["values"], reference)
        axes[1, 0].loglog(sizes, medians, "o-", label="k-NN fit on random subsets")
        if len(sizes) > 1:
            d = points.shape[1]
            slope = medians[-1] * (np.asarray(sizes, float) / sizes[-1]) ** (-1.0 / d)
            axes[1, 0].loglog(sizes, slope, "k--", lw=0.8, label=f"~ h ~ N^(-1/{d})")
        axes[1, 0].legend(fontsize=8)
        axes[1, 0].set(
            xlabel="walkers N",
            ylabel="median relative error vs exact",
            title=f"convergence with walkers (k = {subset_neighbours(points.shape[1])})",
        )
    else:
        sizes, medians = _error_by_neighbour_count(points, comparison["values"], reference, valid)
        axes[1, 0].loglog(sizes, medians, "o-")
        axes[1, 0].set(
            xlabel="k (k-NN neighbours)", ylabel=f"median relative error vs {label}", title="error against neighbours"
        )
    if medians:
        axes[1, 0].set_ylim(*_decade_limits(medians))
    else:
        axes[1, 0].text(
            0.5,
            0.5,
            f"too few walkers ({len(points)}) to refit on subsets",
            ha="center",
            transform=axes[1, 0].transAxes,
        )
    axes[1, 1].hist(np.log10(error[ok] + 1e-16), bins=40)
    axes[1, 1].set(
        xlabel=f"log10 relative Hessian error vs {label}",
        ylabel="walkers",
        title=f"error distribution (median {np.median(error[ok]) if ok.any() else np.nan:.2g})",
    )
    if truth is None:
        fig.suptitle(
            "reference: the geometric Hessian C^-1 - eps_Sigma I, which measures walker spacing (~1/h^2), "
            "not V;\nit matches H only for adaptive-gas equilibrium samples: for other samples large "
            "errors are expected",
            fontsize=9,
        )
    else:
        fig.suptitle(
            "least-squares Hessian estimated from the fitness values at the walkers, against the "
            "landscape's exact Hessian (autodiff)",
            fontsize=10,
        )
    return save_figure(fig, path, dpi=dpi)


def subset_neighbours(d: int) -> int:
    """Neighbours of the convergence panel's k-NN fits: twice a quadratic fit's coefficients."""
    return max(12, (d + 1) * (d + 2))


def _eigenvalue_panel(ax, reference, estimate, label: str) -> None:
    """FD eigenvalues against the reference's with the diagonal, on axes holding the central
    98% of both: a few outliers (a geometric eigenvalue of 8e5) would flatten the rest."""
    finite = np.isfinite(reference) & np.isfinite(estimate)
    reference, estimate = reference[finite], estimate[finite]
    both = np.concatenate([reference, estimate]) if reference.size else np.zeros(1)
    low, high = np.percentile(both, [1, 99])
    pad = 0.05 * max(high - low, 1e-12)
    low, high = low - pad, high + pad
    outside = int(np.sum((reference < low) | (reference > high) | (estimate < low) | (estimate > high)))
    ax.scatter(reference, estimate, s=3, alpha=0.5)
    ax.plot([low, high], [low, high], "k--", lw=0.8, label="equal")
    rho = float(np.corrcoef(reference, estimate)[0, 1]) if reference.size > 1 else float("nan")
    ax.set(
        xlim=(low, high),
        ylim=(low, high),
        xlabel=f"{label} eigenvalue",
        ylabel="least-squares eigenvalue",
        title=f"eigenvalues, rho = {rho:.2f} ({outside} beyond the axes)",
    )
    ax.legend(fontsize=8, loc="upper left")


def _error_by_walker_count(points, values, reference):
    """Median relative error of the k-NN least-squares Hessian on random subsets of N/8, N/4,
    N/2 and all walkers (those of at least 5 k walkers), against the reference at
    those walkers; the fit's error shrinks with the spacing."""
    from ..geometry._estimation import estimate_hessian
    from ..tessellation._knn import knn_graph

    n, d = points.shape
    k = subset_neighbours(d)
    rng = np.random.default_rng(0)
    sizes = [n // 2**j for j in (3, 2, 1, 0) if n // 2**j >= 5 * k]
    medians = []
    for size in sizes:
        pick = np.sort(rng.choice(n, size, replace=False))
        est = np.asarray(estimate_hessian(knn_graph(points[pick], k), np.asarray(values)[pick]))
        medians.append(float(np.nanmedian(relative_error(est, reference[pick]))))
    return sizes, medians


def _decade_limits(values) -> tuple[float, float]:
    """Log-axis limits on whole decades holding `values`, at least one decade apart, so that a
    flat series is drawn flat (matplotlib would stretch 0.99016..0.99029 over the axis)."""
    finite = np.asarray(values, float)
    finite = finite[np.isfinite(finite) & (finite > 0)]
    if not finite.size:
        return 0.1, 1.0
    low, high = np.floor(np.log10(finite.min())), np.ceil(np.log10(finite.max()))
    return 10.0**low, 10.0 ** max(high, low + 1)


def relative_error(estimate, reference):
    """Per walker |estimate - reference|_F / |reference|_F (a diagonal estimate against the diagonal)."""
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
        err = relative_error(est, reference)[valid]
        medians.append(float(np.nanmedian(err)))
    return ks, medians


def subplots(rows: int, cols: int, *, figsize, layout=None, **kwargs):
    """A figure and its axes, made without pyplot: no backend is chosen or changed (a notebook
    keeps its inline figures) and nothing is left open in pyplot's list of figures."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout=layout)
    return fig, fig.subplots(rows, cols, **kwargs)


def save_figure(fig, path, dpi: int = 100, layout: bool = True) -> Path:
    """Lay out (unless the figure has its own layout engine: `layout=False`), and write (creating
    the folder) a figure; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if layout:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
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
    "spectral_gap": ("spectral gap (kernel graph, largest component)", "lambda_2 of the normalized Laplacian"),
    "prism_fraction": ("prisms (no neighbour lost or gained)", "fraction, tier 2 at both steps"),
    "simple_scutoid_fraction": ("simple scutoids (<= 1 lost, <= 1 gained)", "fraction, tier 2 at both steps"),
    "complex_scutoid_fraction": ("complex scutoids (>= 2 lost or gained)", "fraction, tier 2 at both steps"),
    "mean_neighbor_change": ("neighbour change per walker", "<lost + gained>, tier 2 at both steps"),
}


def _landscape_grid(fitness, lo, hi, d: int):
    import jax
    import jax.numpy as jnp

    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 160), np.linspace(lo[1], hi[1], 160))
    if fitness is None:  # a recorded trajectory without a landscape: no contours
        return gx, gy, None
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
    """One symmetric-log colour scale for every panel, spanning the values of the snapshots
    after the first: the uniform start has |R| orders of magnitude above a settled swarm and
    would leave it grey; the start's larger values saturate (the colour bar's arrows)."""
    from matplotlib.colors import SymLogNorm

    later = [s for s in snapshots[1:] if s["ricci"] is not None and np.isfinite(s["ricci"]).any()] or snapshots
    pooled = np.concatenate(
        [np.abs(s["ricci"][np.isfinite(s["ricci"])]) for s in later if s["ricci"] is not None] or [np.ones(1)]
    )
    top = max(float(np.percentile(pooled, 99)), 1e-12)
    return SymLogNorm(linthresh=max(float(np.percentile(pooled, 25)), 1e-4 * top), vmin=-top, vmax=top, base=10)


def _symlog_ticks(norm):
    """0 and +-10^k for the decades between the linear threshold and the top (every second
    decade beyond four), so the colour bar's labels do not overlap."""
    decades = np.arange(np.ceil(np.log10(norm.linthresh)), np.floor(np.log10(norm.vmax)) + 1)
    decades = decades[:: 1 + (len(decades) > 4)]
    return np.concatenate([-(10.0 ** decades[::-1]), [0.0], 10.0**decades])


def plot_swarm_snapshots(fitness, snapshots: list, box, path, colour: tuple[str, str] | None = None) -> Path:
    """Three rows, one column per snapshot `{"step", "positions", "ricci"}` (ricci None on a
    k-NN graph: walkers coloured by V instead), one symmetric-log colour scale for every panel:

    - top: every walker, in one frame shared by the columns, over light contours of V; a
      dashed square marks the middle row's frame;
    - middle: zoomed on the snapshot's most populated cluster (`cluster_frame`), walkers drawn
      large enough that each one's colour shows;
    - bottom: the distribution of the colour's values over the walkers that have one, bars in
      the same colours, with its median and the count of walkers without a value (hull tiers).

    Beyond 2D the panels show the projection on (x_1, x_2) and the contours V(x_1, x_2, 0, ...,
    0); the figure says so. `colour` = (label, description): the snapshots carry their own
    per-walker "values" (a recorded trajectory's fitness or cell volumes), on a linear scale;
    `fitness` None: no contours."""
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    d = snapshots[0]["positions"].shape[1]
    has_ricci = colour is None and any(s["ricci"] is not None for s in snapshots)
    colours = [
        np.asarray(snap["values"], np.float64) if colour else _colour_values(fitness, snap, has_ricci)
        for snap in snapshots
    ]
    norm = _shared_ricci_norm(snapshots) if has_ricci else _value_norm(colours[1:] or colours)
    cmap = "coolwarm" if has_ricci else "viridis"
    n = len(snapshots)
    fig, axes = subplots(
        3,
        n,
        figsize=(3.7 * n + 1.2, 11.0),
        squeeze=False,
        layout="constrained",
        gridspec_kw={"height_ratios": [1.0, 1.0, 0.7]},
    )
    lo, hi = _frame(np.concatenate([snap["positions"] for snap in snapshots]), box)
    gx, gy, values = _landscape_grid(fitness, lo, hi, d)
    for col, (snap, c) in enumerate(zip(snapshots, colours, strict=True)):
        x = snap["positions"]
        zoom_lo, zoom_hi = cluster_frame(x, max_width=0.25 * float(np.max(hi - lo)))
        top, mid, bottom = axes[:, col]
        mapped = _draw_walkers(top, x, c, gx, gy, values, norm, cmap, size=3.0)
        top.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), title=f"step {snap['step']}", xlabel="x_1")
        top.add_patch(Rectangle(zoom_lo, *(zoom_hi - zoom_lo), fill=False, ls="--", lw=1.0, ec="k"))
        zx, zy, zvalues = _landscape_grid(fitness, zoom_lo, zoom_hi, d)
        inside = np.all((x[:, :2] >= zoom_lo) & (x[:, :2] <= zoom_hi), axis=1)
        _draw_walkers(mid, x, c, zx, zy, zvalues, norm, cmap, size=float(np.clip(3000.0 / max(inside.sum(), 1), 6, 40)))
        width = float(np.max(zoom_hi - zoom_lo))
        mid.set(xlim=(zoom_lo[0], zoom_hi[0]), ylim=(zoom_lo[1], zoom_hi[1]), xlabel="x_1")
        mid.set_title(f"zoom: {inside.sum()} walkers in a {width:.3g}-wide square", fontsize=9)
        for ax in (top, mid):
            ax.xaxis.set_major_locator(MaxNLocator(4))
            ax.yaxis.set_major_locator(MaxNLocator(5))
            ax.set_aspect("equal", adjustable="box")
        _draw_histogram(bottom, c, norm, cmap, has_ricci, colour[0] if colour else None)
    axes[0, 0].set_ylabel("x_2")
    axes[1, 0].set_ylabel("x_2")
    axes[2, 0].set_ylabel("share of the walkers with a value")
    label = "Ricci scalar R (symmetric log scale)" if has_ricci else (colour[0] if colour else "V(x)")
    bar = fig.colorbar(mapped, ax=axes[:2].ravel().tolist(), label=label, fraction=0.03, pad=0.01, extend="both")
    if has_ricci:
        bar.set_ticks(_symlog_ticks(norm))
    what = (
        "walkers coloured by the Ricci scalar of the Hessian metric g = H + eps_Sigma I (black: hull tiers, no R)"
        if has_ricci
        else colour[1]
        if colour
        else "k-NN graph (no simplices, so no Ricci scalar): walkers coloured by V"
    )
    where = (f"{d}D swarm projected on (x_1, x_2)" if d > 2 else "") + (
        "" if fitness is None else (", contours of V(x_1, x_2, 0, ..., 0)" if d > 2 else "contours of V")
    )
    where = where or "no landscape (no contours)"
    fig.suptitle(
        f"{what}; {where}\ntop: every walker, one frame; middle: the most populated cluster (dashed "
        "square above); bottom: the distribution of the colour over the walkers",
        fontsize=10,
    )
    return save_figure(fig, path, dpi=100, layout=False)


def cluster_frame(positions, max_width: float):
    """A square frame (lower, upper) of the first two coordinates on the most populated cluster:
    the largest group of walkers linked by steps shorter than 3x the median nearest-neighbour
    distance, with the walkers within 1.5x its extent (its sparser outskirts), framed about its
    median to hold 97% of them with a 10% margin, and at most
    `max_width` wide (a swarm spread over its box: a window about its median)."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    xy = np.asarray(positions, np.float64)[:, :2]
    tree = cKDTree(xy)
    spacing = float(np.median(tree.query(xy, k=2)[0][:, 1])) if len(xy) > 1 else 1.0
    links = tree.sparse_distance_matrix(tree, 3.0 * max(spacing, 1e-12), output_type="coo_matrix")
    _, labels = connected_components(links, directed=False)
    cluster = xy[labels == np.argmax(np.bincount(labels))]
    centre = np.median(cluster, axis=0)
    reach = np.max(np.abs(xy - centre), axis=1)
    near = reach[reach <= 1.5 * np.max(np.abs(cluster - centre))]  # with its sparser outskirts
    radius = float(np.quantile(near, 0.97))
    radius = min(1.1 * max(radius, 5.0 * spacing, 1e-9), 0.5 * max_width)
    return centre - radius, centre + radius


def _colour_values(fitness, snap, has_ricci: bool) -> np.ndarray:
    if has_ricci:
        ricci = snap["ricci"]
        return np.full(len(snap["positions"]), np.nan) if ricci is None else np.asarray(ricci, np.float64)
    return np.asarray(_fitness_at(fitness, snap["positions"]), np.float64)


def _value_norm(colours):
    """A linear scale over the 1st-99th percentiles of the values (of the snapshots after the
    first, as the Ricci scale)."""
    from matplotlib.colors import Normalize

    pooled = np.concatenate([c[np.isfinite(c)] for c in colours] or [np.zeros(1)])
    low, high = np.percentile(pooled, [1, 99]) if pooled.size else (0.0, 1.0)
    return Normalize(vmin=float(low), vmax=float(max(high, low + 1e-12)))


def _draw_walkers(ax, x, c, gx, gy, values, norm, cmap: str, size: float):
    """Light contours of V, walkers without a value in black, the others coloured."""
    if values is not None:
        ax.contour(gx, gy, values, levels=_contour_levels(values, 10), colors="0.78", linewidths=0.4, zorder=0)
    ok = np.isfinite(c)
    ax.scatter(x[~ok, 0], x[~ok, 1], s=size / 3, c="k", lw=0, zorder=1)
    return ax.scatter(x[ok, 0], x[ok, 1], s=size, c=c[ok], cmap=cmap, norm=norm, lw=0, zorder=2)


def _draw_histogram(ax, c, norm, cmap: str, symlog: bool, label: str | None = None):
    """The share of the walkers with a value in each of 40 bins spread evenly in the colour
    scale, each bar in its bin's colour (values off the scale in the end bars); the median dashed."""
    import matplotlib

    ok = c[np.isfinite(c)]
    edges = np.asarray(norm.inverse(np.linspace(0.0, 1.0, 41)), np.float64)
    counts, _ = np.histogram(np.clip(ok, edges[0], edges[-1]), bins=edges)
    share = counts / max(ok.size, 1)
    centres = np.asarray(norm.inverse(np.linspace(0.0, 1.0, 81)[1::2]), np.float64)
    ax.bar(
        edges[:-1],
        share,
        width=np.diff(edges),
        align="edge",
        color=matplotlib.colormaps[cmap](norm(centres)),
        edgecolor="none",
    )
    if symlog:
        ax.set_xscale("symlog", linthresh=norm.linthresh)
        ax.set_xticks(_symlog_ticks(norm))
    ax.set_xlim(edges[0], edges[-1])
    if ok.size:
        median = float(np.median(ok))
        ax.axvline(median, color="k", ls="--", lw=0.8)
        beyond = int(np.sum((ok < edges[0]) | (ok > edges[-1])))
        ax.set_title(
            f"median {median:.3g}; {int(c.size - ok.size)} without a value, {beyond} off the scale", fontsize=9
        )
    ax.set_xlabel(label or ("Ricci scalar R" if symlog else "V"))


def _fitness_at(fitness, x):
    import jax

    return jax.vmap(fitness)(x)


def _first_finite(values) -> float:
    values = np.asarray(values)
    return float(values[np.isfinite(values)][0])


def _constant(values) -> bool:
    finite = np.asarray(values)[np.isfinite(values)]
    return bool(finite.size > 0 and np.ptp(finite) <= 1e-12 * max(np.abs(finite).max(), 1e-300))


def plot_observables(
    series: dict, gap_steps, gaps, path, gap_rounding=None, gap_times=None, time_label: str = "time (steps x dt)"
) -> Path:
    """Every observable of a `jaxgeom.simulate` history against time, one panel each, with
    labelled axes. Constant series (nu, eps_Sigma without annealing) are named in the title
    instead of drawn; observables that are NaN throughout (the Voronoi ones on a k-NN graph)
    are listed; NaN entries (the expansion at step 0) are skipped, the line joins the rest.
    `gap_rounding` (bool per gap) marks the gaps below float64 resolution, drawn as x at 0.
    `gap_times`: the gaps' times (default: their steps x the series' time step)."""
    names, constant, undefined = observable_panels(series, gaps)
    cols = 3
    rows = max(-(-len(names) // cols), 1)
    fig, axes = subplots(rows, cols, figsize=(4.5 * cols, 2.9 * rows + 0.6), squeeze=False)
    t = np.asarray(series["time"])
    dt = t[1] - t[0] if len(t) > 1 else 1.0
    gap_times = np.asarray(gap_steps) * dt if gap_times is None else np.asarray(gap_times)
    for ax, name in zip(axes.ravel(), names, strict=False):  # the grid has spare panels
        _plot_one(ax, name, series, t, gap_times, gaps, gap_rounding, time_label)
    for ax in axes.ravel()[len(names) :]:
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


def _plot_one(ax, name, series, t, gap_times, gaps, gap_rounding=None, time_label="time (steps x dt)"):
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
    ax.set(xlabel=time_label, ylabel=ylabel)
