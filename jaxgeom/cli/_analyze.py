"""`jaxgeom analyze`: tessellate a swarm and report its geometry (a recorded trajectory's
observables with --trajectory: `_trajectory.py`).

The report is a list of sections (`REPORT_SECTIONS`); each takes the analysis
context and returns a flat dict of numbers. New proxies add a section.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

import jaxgeom

from ..apps._landscapes import LANDSCAPES, sample_boltzmann
from ..apps._plots import relative_error, save_figure, subplots
from ..geometry._metric_curvature import DEFAULT_PROBES, EXACT_HESSIAN_MAX_DIM
from ..geometry._spectral import bulk_spectral_gap, gap_rounding_level
from ..swarm._observables import riemannian_log_weights, weighted_mean_from_logs
from ..tessellation._graph import Tessellation
from ._legend import UNITS, analyze_definition
from ._simulate import HelpFormatter, load_landscape
from ._trajectory import add_trajectory_arguments, refuse_mixed_options, trajectory_main


@dataclasses.dataclass
class Analysis:
    """What every report section can read; `timings` collects seconds per stage."""

    args: argparse.Namespace
    points: np.ndarray
    box: tuple | None
    source: str
    fitness: Callable | None = None
    tess: Tessellation | None = None
    timings: dict = dataclasses.field(default_factory=dict)
    cache: dict = dataclasses.field(default_factory=dict)


def timed(analysis: Analysis, label: str, fn: Callable, *args, **kwargs):
    """Run fn, block on its JAX outputs, and record the wall time under `label`."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kwargs))
    analysis.timings[label] = time.perf_counter() - start
    return out


def timed_warm(analysis: Analysis, label: str, fn: Callable, *args, **kwargs):
    """Time a first call (with compilation) as `label_first_call`, then a warm call as `label`."""
    timed(analysis, f"{label}_first_call", fn, *args, **kwargs)
    return timed(analysis, label, fn, *args, **kwargs)


def _stats(values: np.ndarray, prefix: str) -> dict:
    v = values[np.isfinite(values)]
    if not v.size:
        return {f"{prefix}_count": 0}
    return {
        f"{prefix}_mean": float(v.mean()),
        f"{prefix}_median": float(np.median(v)),
        f"{prefix}_std": float(v.std()),
        f"{prefix}_min": float(v.min()),
        f"{prefix}_max": float(v.max()),
    }


def section_swarm(a: Analysis) -> dict:
    n, d = a.points.shape
    out: dict[str, Any] = {
        "source": a.source,
        "n_walkers": n,
        "dim": d,
        "graph": a.args.graph,
        "periodic": a.args.periodic,
        "landscape": a.args.landscape or NO_LANDSCAPE,
    }
    if a.args.graph == "knn":
        out["k"] = a.args.k
    if a.box is not None:
        out["box_lower"], out["box_upper"] = np.asarray(a.box[0]).tolist(), np.asarray(a.box[1]).tolist()
    return out


def section_graph(a: Analysis) -> dict:
    tess = a.tess
    degree = np.asarray(tess.degree)
    tiers = np.bincount(np.asarray(tess.tier), minlength=3)
    out: dict[str, Any] = {f"tier{t}": int(tiers[t]) for t in range(3)}
    out.update(degree_mean=float(degree.mean()), degree_min=int(degree.min()), degree_max=int(degree.max()))
    out.update(capacity_neighbors=tess.capacity.neighbors, capacity_simplices=tess.capacity.simplices)
    if tess.simplices is not None:
        out["n_simplices"] = int(tess.simplex_mask.sum())
    out["overflow"] = bool(tess.overflow)
    return out


def needs_simplices(section: Callable[[Analysis], dict]) -> Callable[[Analysis], dict]:
    """Report sections that need Delaunay simplices are skipped, with a note, on k-NN graphs."""

    def guarded(a: Analysis) -> dict:
        if a.tess.simplices is None:
            return {"skipped": "needs a Delaunay graph (--graph delaunay)"}
        return section(a)

    return guarded


@needs_simplices
def section_volumes(a: Analysis) -> dict:
    vol = np.asarray(timed_warm(a, "voronoi_volumes", jaxgeom.voronoi_volumes, a.tess))
    a.cache["volumes"] = vol
    interior = np.asarray(a.tess.interior)
    out: dict[str, Any] = {"tier2_total": float(vol[interior].sum()), "n_unbounded": int(np.isnan(vol).sum())}
    if a.tess.box is not None:  # cells clipped to the box: they tile it
        out["total_in_box"] = float(np.sum(vol))
    out.update(_stats(vol[interior], "tier2"))
    return out


def analysis_metric(a: Analysis):
    """The metric chosen by --metric: None, the landscape's Hessian metric, or the emergent metric."""
    if "metric" not in a.cache:
        kind = a.args.metric
        if kind == "hessian":
            assert a.fitness is not None  # --metric hessian without a landscape: refused by resolve_options
            a.cache["metric"] = jaxgeom.hessian_metric(a.fitness, a.args.eps_sigma, floor=ANALYSIS_FLOOR)
        elif kind == "emergent":
            a.cache["metric"] = timed_warm(a, "emergent_metric", jaxgeom.emergent_metric, a.tess)
        else:
            a.cache["metric"] = None
    return a.cache["metric"]


def section_metric(a: Analysis) -> dict:
    out: dict[str, Any] = {"kind": a.args.metric}
    if a.args.metric == "hessian":  # only with a landscape (`resolve_options`)
        out.update(landscape=a.args.landscape, eps_sigma=a.args.eps_sigma)
    g = jaxgeom.metric_at_walkers(a.tess, analysis_metric(a))
    if g is not None:
        lam = np.linalg.eigvalsh(np.asarray(g)[np.asarray(a.tess.interior)])
        out.update(_stats(lam[:, -1] / lam[:, 0], "tier2_condition"))
        out["tier2_min_eigenvalue"] = float(lam[:, 0].min()) if len(lam) else np.nan  # no tier-2 walker
    return out


@needs_simplices
def section_curvature(a: Analysis) -> dict:
    metric, vol = analysis_metric(a), a.cache.get("volumes")
    riem = np.asarray(
        timed_warm(a, "riemannian_volumes", jaxgeom.riemannian_volumes, a.tess, metric=metric, volumes=vol)
    )
    ricci = np.asarray(timed_warm(a, "ricci_scalar", jaxgeom.ricci_scalar, a.tess, metric=metric, volumes=vol))
    resolution = np.asarray(jaxgeom.ricci_resolution(a.tess, metric=metric, volumes=vol))
    a.cache.update(ricci=ricci, riemannian_volumes=riem)
    interior = np.asarray(a.tess.interior)
    out: dict[str, Any] = {
        "tier2_volume_weighted_ricci": float(jaxgeom.riemannian_mean(ricci, riem, interior)),
        "tier2_volume_weighted_ricci_resolution": float(jaxgeom.riemannian_mean(resolution, riem, interior)),
        "precision": str(a.tess.points.dtype),
    }
    out.update(_stats(ricci[interior], "tier2_ricci"))
    out["tier2_ricci_resolution_median"] = float(np.nanmedian(resolution[interior])) if interior.any() else np.nan
    if a.tess.dim in (2, 3):
        delta = np.asarray(timed_warm(a, "deficit_angles", jaxgeom.deficit_angles, a.tess, metric=metric))
        out["mean_abs_deficit"] = float(np.abs(delta[delta != 0]).mean()) if np.any(delta != 0) else 0.0
    return out


def section_metric_curvature(a: Analysis) -> dict:
    """The exact Ricci scalar of the Hessian metric (`metric_curvature`), any graph and any d:
    its region average over tier-2 walkers in the Riemannian measure, beside the Regge proxy's
    (same walkers, same weights) where the graph is Delaunay."""
    if a.args.metric != "hessian":
        why = (
            "the Euclidean metric is flat (S = 0)"
            if a.args.metric == "none"
            else ("the emergent metric is known only at the walkers, and curvature needs its derivatives")
        )
        return {"skipped": f"needs the Hessian metric of a landscape (--metric hessian): {why}"}
    d = a.points.shape[1]
    probes = None if d <= EXACT_HESSIAN_MAX_DIM else DEFAULT_PROBES
    key = jax.random.key(a.args.seed) if probes else None
    s, info = timed_warm(
        a,
        "metric_curvature",
        jaxgeom.metric_curvature,
        analysis_metric(a),
        a.points,
        probes=probes,
        key=key,
        with_info=True,
    )
    g = jaxgeom.metric_at_walkers(a.tess, analysis_metric(a))
    log_w, ok = riemannian_log_weights(a.tess, g)
    ok = np.asarray(ok & a.tess.interior)
    values, se = np.asarray(s), np.asarray(info.standard_error)
    usable = ok & np.isfinite(values)
    out: dict[str, Any] = {
        "method": info.method,
        "probes": probes,
        "tier2_walkers_used": int(usable.sum()),
        "floor_active_walkers": int(np.asarray(info.floor_active).sum()),
        "not_positive_definite_walkers": int(np.asarray(info.not_positive_definite).sum()),
        "flagged_nan_walkers": int(np.isnan(values).sum()),
        "weights": "Voronoi volume x sqrt(det g)" if a.tess.simplices is not None else "r_k^d x sqrt(det g) (k-NN)",
    }
    out["tier2_riemannian_mean_exact_ricci"] = float(weighted_mean_from_logs(s, log_w, usable))
    if probes:  # sqrt(sum w^2 se^2) / sum w
        log_used = np.asarray(log_w)[usable]
        w = np.exp(log_used - log_used.max()) if log_used.size else log_used
        out["standard_error_of_the_mean"] = (
            float(np.sqrt(np.sum((w * se[usable]) ** 2)) / w.sum()) if w.size else np.nan
        )
    if "ricci" in a.cache:  # the Regge proxy on the same walkers with the same weights
        both = usable & np.isfinite(a.cache["ricci"])
        out["regge_same_walkers"] = float(weighted_mean_from_logs(a.cache["ricci"], log_w, both))
        out["exact_same_walkers"] = float(weighted_mean_from_logs(s, log_w, both))
        comparable, why = regge_comparison(
            a.tess,
            values,
            np.asarray(log_w),
            both,
            np.asarray(info.floor_active),
            ANALYSIS_FLOOR,
            out["regge_same_walkers"],
            out["exact_same_walkers"],
        )
        out["regge_vs_exact"] = "comparable" if comparable else "not comparable"
        out["regge_vs_exact_why"] = why
    out.update(_stats(values[ok], "tier2_exact_ricci"))
    return out


ANALYSIS_FLOOR = "clip"  # the Hessian metric's floor in `analyze` (jaxgeom.hessian_metric's default)
RESOLVED_SPREAD = 0.25  # regge_comparison: the largest neighbour spread of S, against its mean, called resolved


def regge_comparison(
    tess,
    exact: np.ndarray,
    log_w: np.ndarray,
    used: np.ndarray,
    floor_active: np.ndarray,
    floor: str,
    regge_mean: float,
    exact_mean: float,
) -> tuple[bool, str]:
    """(comparable, why): whether the Regge and the exact region averages over the walkers `used`
    estimate the same quantity, so that their difference measures the Regge proxy's error.

    Not where the "clip" floor is active at some of the walkers but not all: g = clip(Hess V) +
    eps_Sigma I is then only C^0 across the surface where an eigenvalue of Hess V crosses 0,
    and its curvature includes a part concentrated on that surface, which the deficit angles
    of the cells straddling it measure and the pointwise exact scalar omits. Not where the
    sample does not resolve the exact scalar: its Riemann sum over the cells is then not yet
    the region's average (the measure: the volume-weighted mean over the walkers of half the
    mean |S_j - S_i| over their neighbours, against the larger |mean|; resolved below
    `RESOLVED_SPREAD`)."""
    if not used.any():
        return False, "no tier-2 walker has both values"
    share = float(floor_active[used].mean())
    if floor == "clip" and 0.0 < share < 1.0:
        return False, (
            f"the clip floor is active at {share:.0%} of these walkers: g has a kink where an eigenvalue "
            "of Hess V crosses 0, whose curvature the deficit angles include and the pointwise exact "
            "scalar omits"
        )
    neighbors, mask = np.asarray(tess.neighbors), np.asarray(tess.neighbor_mask)
    safe = np.minimum(neighbors, len(exact) - 1)
    other = np.where(mask & np.isfinite(exact)[safe], exact[safe], np.nan)
    with np.errstate(invalid="ignore"):
        jump = 0.5 * np.nanmean(np.abs(other - exact[:, None]), axis=1)
    ok = used & np.isfinite(jump)
    weights = np.exp(log_w[ok] - log_w[ok].max()) if ok.any() else np.zeros(0)
    spread = float(np.sum(weights * jump[ok]) / np.sum(weights)) if ok.any() else float("nan")
    scale = max(abs(regge_mean), abs(exact_mean))
    if not spread <= RESOLVED_SPREAD * scale and not (spread == 0.0 and scale == 0.0):
        return False, (
            f"unresolved by the sample: the exact scalar changes by {spread:.3g} between neighbouring "
            f"cells against means of {scale:.3g}; more walkers resolve it"
        )
    floor_note = "the floor is inactive" if share == 0.0 else "the floor is active at every one of these walkers"
    return True, (
        f"{floor_note}, and the exact scalar changes by {spread:.3g} between neighbouring cells against "
        f"means of {scale:.3g}: both estimate the region's average"
    )


def section_ollivier_ricci(a: Analysis) -> dict:
    """Ollivier-Ricci curvature of every edge of the (undirected) k-NN graph, any d: exact transport,
    alpha = 0.5, uniform measure, ground cost = shortest path of <= 3 edges in the analysis metric.
    Delaunay graphs have the Regge curvature (section `curvature`)."""
    if a.tess.simplices is not None:
        return {
            "skipped": "reported for k-NN graphs (--graph knn); a Delaunay graph has the Regge curvature "
            "(section curvature); jaxgeom.ollivier_ricci computes it on either"
        }
    tess = a.tess
    if tess.neighbors.shape[1] > ORC_K:  # the analysis k (a Hessian fit's) would cost O(k^3) per edge
        periodic = bool(getattr(a.args, "periodic", False))
        box = a.box if periodic or getattr(a.args, "box", None) is not None else None
        tess = timed(a, "knn_graph_orc", jaxgeom.knn_graph, a.points, ORC_K, box=box, periodic=periodic)
    orc = timed(a, "ollivier_ricci", jaxgeom.ollivier_ricci, tess, alpha=0.5, metric=analysis_metric(a))
    edges = np.asarray(orc.edge_mask)
    kappa = np.asarray(orc.edge_curvature)[edges]
    tier2 = np.asarray(orc.interior & ~orc.isolated)
    out: dict[str, Any] = {
        "k": tess.neighbors.shape[1],
        "alpha": 0.5,
        "measure": "uniform",
        "cost": "graph (<= 3 edges, metric lengths)",
        "edges": int(edges.sum()) // 2,
        "undirected_degree_max": int(edges.sum(axis=1).max()),
        "isolated_walkers": int(np.asarray(orc.isolated).sum()),
        "not_converged_walkers": int(np.asarray(orc.not_converged).sum()),
        "overflow": bool(orc.overflow),
        "mean_edge_curvature": float(kappa.mean()) if kappa.size else float("nan"),
    }
    out.update(_stats(np.asarray(orc.walker_curvature)[tier2], "tier2_walker_curvature"))
    out["tier2_mean_orc_scalar_estimate"] = float(orc.mean_scalar_curvature)
    out["scalar_estimate_note"] = ORC_SCALE_NOTE
    return out


ORC_K = 10  # the k-NN graph of the Ollivier-Ricci section (a larger analysis k is rebuilt at this k)
ORC_SCALE_NOTE = (
    "2 n^2 kappa / ((1 - alpha) E|w|^2) (Ollivier's expansion) holds at a mesoscopic scale; at the "
    "k-NN scale the discrete measures dominate kappa and the estimate does not converge to the "
    "scalar curvature (bench/README.md, 'Ollivier-Ricci curvature')"
)


@needs_simplices
def section_cells(a: Analysis) -> dict:
    shape = np.asarray(timed_warm(a, "shape_distortion", jaxgeom.shape_distortion, a.tess))
    a.cache["shape"] = shape
    spread = np.asarray(jaxgeom.vertex_distance_variance(a.tess))
    interior = np.asarray(a.tess.interior)
    out: dict[str, Any] = {
        "volume_distortion": float(timed_warm(a, "volume_distortion", jaxgeom.volume_distortion, a.tess))
    }
    if "riemannian_volumes" in a.cache:
        out["volume_distortion_riemannian"] = float(jaxgeom.volume_distortion(a.tess, a.cache["riemannian_volumes"]))
    out.update(_stats(shape[interior], "tier2_shape_distortion"))
    out.update(_stats(spread[interior], "tier2_vertex_distance_variance"))
    out["raychaudhuri"] = "needs two snapshots: use jaxgeom.raychaudhuri_expansion on a time series"
    return out


def section_graph_proxies(a: Analysis) -> dict:
    """The spectral gap of the normalized Laplacian of the kernel-weighted graph's largest connected
    component, its components (`jaxgeom.simulate`'s reading: two blobs are two components, and
    the gap of the whole graph would be 0 by construction; a gap below float64 resolution is
    shown as such), and geodesics from the best (lowest-V) walker (the heat method on Delaunay
    graphs, Dijkstra's graph distance on k-NN graphs)."""
    gap, components, outside = timed(a, "spectral_gap", bulk_spectral_gap, a.tess, length_scale=a.args.length_scale)
    level = gap_rounding_level(a.tess.n_points - outside)
    out: dict[str, Any] = {
        "kernel_graph_components": components,
        "walkers_outside_largest_component": outside,
        "spectral_gap_largest_component": gap if not gap < level else f"< {level:.1e} (float64 rounding)",
    }
    if a.fitness is not None:  # from the best (lowest-V) walker
        fitness = np.asarray(jax.vmap(a.fitness)(np.asarray(a.points)))
        source, role = int(np.argmin(fitness)), "best_walker"
        out.update(best_walker=source, best_fitness=float(fitness[source]))
    else:  # no landscape: from the walker nearest the centroid
        source, role = int(np.argmin(np.sum((a.points - a.points.mean(axis=0)) ** 2, axis=1))), "central_walker"
        out.update(central_walker=source)
    metric = analysis_metric(a)
    method = "heat" if a.tess.simplices is not None else "dijkstra"  # a k-NN graph has no simplices
    dist = np.asarray(
        timed(a, "geodesic_distances", jaxgeom.geodesic_distances, a.tess, source, metric=metric, method=method)
    )[0]
    reachable = np.isfinite(dist)
    out.update(
        {
            "geodesic_method": method,
            f"{role}_geodesic_eccentricity": float(dist[reachable].max()),
            f"{role}_mean_geodesic_distance": float(dist[reachable].mean()),
            "unreachable_walkers": int((~reachable).sum()),
        }
    )
    return out


def section_estimation(a: Analysis) -> dict:
    """Gradient and Hessian of the fitness field estimated from its values at the walkers: the
    Hessian's error against the landscape's exact one (autodiff), and its agreement with the
    geometric (emergent-metric) Hessian."""

    if a.fitness is None:
        return {"skipped": f"needs fitness values: {NO_LANDSCAPE}"}
    values = np.asarray(jax.vmap(a.fitness)(np.asarray(a.points)))
    result = timed(
        a, "compare_estimation_methods", jaxgeom.compare_estimation_methods, a.tess, values, eps_sigma=a.args.eps_sigma
    )
    exact = np.asarray(jax.vmap(jax.hessian(a.fitness))(np.asarray(a.points)))  # the landscape's own Hessian
    a.cache["estimation"] = {"comparison": result, "true_hessian": exact}
    valid = result["valid"]
    out: dict[str, Any] = {"walkers_with_hessian": int(valid.sum()), "walkers": len(valid)}
    out |= _stats(np.linalg.norm(np.asarray(result["gradient"])[valid], axis=1), "tier2_gradient_norm")
    eig = np.asarray(result["eigenvalues_fd"])[valid]
    out.update(_stats(eig[:, 0], "tier2_hessian_min_eigenvalue"))
    out.update(_stats(eig[:, -1], "tier2_hessian_max_eigenvalue"))
    out.update(
        _stats(relative_error(np.asarray(result["hessian_fd"])[valid], exact[valid]), "tier2_hessian_error_vs_exact")
    )  # the figure's per-walker error
    out.update({f"agreement_{k}": v for k, v in result["metrics"].items()})
    out["geometric_reference"] = GEOMETRIC_REFERENCE_NOTE
    return out


GEOMETRIC_REFERENCE_NOTE = (
    "the geometric Hessian C^-1 - eps_Sigma I measures walker spacing (~1/h^2), not V: it "
    "matches H only for adaptive-gas equilibrium samples; for a Boltzmann or uniform sample "
    "'poor' agreement and relative errors near 1 are expected"
)


REPORT_SECTIONS: list[tuple[str, Callable[[Analysis], dict]]] = [
    ("swarm", section_swarm),
    ("graph", section_graph),
    ("volumes", section_volumes),
    ("metric", section_metric),
    ("curvature", section_curvature),
    ("metric_curvature", section_metric_curvature),
    ("ollivier_ricci", section_ollivier_ricci),
    ("cells", section_cells),
    ("graph_proxies", section_graph_proxies),
    ("estimation", section_estimation),
]


def write_maps(a: Analysis, path: Path) -> None:
    """PNG: walkers coloured by the Ricci scalar and by the shape distortion (first two
    coordinates; the title says so beyond 2D), with labelled axes and colour bars. Where the
    Ricci scalar is 0 at every walker (the Euclidean metric is flat) its panel gives way to
    the cells' volumes, and the title says why."""
    fig, axes = subplots(1, 2, figsize=(12, 5.5))
    pts = a.points
    metric = a.args.metric + (f" of {a.args.landscape}" if a.args.metric == "hessian" else "")
    ricci = a.cache["ricci"]
    flat = not np.any(ricci[np.isfinite(ricci)])
    first = (
        ("volumes", "Voronoi cell volume (log10)", "cividis", np.log10)
        if flat
        else ("ricci", f"Ricci scalar R (metric: {metric})", "coolwarm", None)
    )
    for ax, (key, title, cmap, transform) in zip(
        axes, [first, ("shape", "shape distortion r_in / r_circ (1: round)", "viridis", None)], strict=True
    ):
        values = a.cache[key] if transform is None else transform(a.cache[key])
        ok = np.isfinite(values)
        ax.scatter(pts[~ok, 0], pts[~ok, 1], s=3, c="k", label="no value (hull tiers)")
        lo, hi = np.percentile(values[ok], [2, 98]) if ok.any() else (0, 1)
        if key == "ricci":
            lo, hi = -max(abs(lo), abs(hi)), max(abs(lo), abs(hi))
        sc = ax.scatter(pts[ok, 0], pts[ok, 1], s=4, c=np.clip(values[ok], lo, hi), cmap=cmap, vmin=lo, vmax=hi)
        fig.colorbar(sc, ax=ax, label=title.split(" (")[0] + " (2-98% range)")
        ax.set(title=title, xlabel="x_1", ylabel="x_2", aspect="equal")
        ax.legend(loc="upper right", fontsize=7)
    d = pts.shape[1]
    where = f"{d}D walkers projected on (x_1, x_2)" if d > 2 else "2D walkers"
    why = f"; no Ricci panel: R = 0 at every walker (metric {metric}: flat)" if flat else ""
    fig.suptitle(f"{a.source}: {where}; landscape: {a.args.landscape or 'none'}{why}", fontsize=9)
    save_figure(fig, path, dpi=110)


NO_LANDSCAPE = "none (--points without --landscape: landscape-free geometry only)"


def resolve_options(args) -> None:
    """Fill the options whose default depends on others: the landscape (double_well for a
    sampled swarm, none for --points), the metric (hessian with a landscape, else none) and
    k (enough neighbours for a quadratic fit in d dimensions)."""
    if args.landscape is None and args.points is None:
        args.landscape = "double_well"
    if args.metric is None:
        args.metric = "hessian" if args.landscape else "none"
    if args.metric == "hessian" and not args.landscape:
        raise ValueError(
            "--metric hessian is the Hessian metric of a landscape: give --landscape with --points, "
            "or choose --metric none / emergent."
        )
    if args.dim < 1:
        raise ValueError(f"--dim must be >= 1; got {args.dim}.")
    if args.box is not None:
        lower, upper = args.box
        if not (np.isfinite(lower) and np.isfinite(upper) and lower < upper):
            raise ValueError(f"--box LOWER UPPER must be finite with LOWER < UPPER; got {lower} {upper}.")
        if args.points is None:
            raise ValueError(
                "--box applies to walkers given with --points; a sampled swarm lives in its landscape's "
                "box (a .py landscape sets it with BOX = (lower, upper)), which --periodic wraps."
            )
    if args.graph == "delaunay" and args.points is None:
        check_delaunay_dim(args.dim, "--dim")


def check_delaunay_dim(d: int, what: str) -> None:
    if not 2 <= d <= 4:
        raise ValueError(
            f"{what} {d} needs --graph knn (Delaunay tessellations exist for d = 2, 3, 4; "
            "k-NN graphs in any dimension)."
        )


def default_k(d: int) -> int:
    """k-NN neighbours for `analyze`: the (d + 1)(d + 2)/2 coefficients of a quadratic fit (the
    Hessian estimate) plus d, at least 12 (d = 10: 76 neighbours; every walker's fit is then
    determined on the 1-ring of a Boltzmann sample, where k = 12 left 4687 of 5000 NaN)."""
    return max(12, (d + 1) * (d + 2) // 2 + d)


def load_swarm(args, fitness, bounds) -> tuple[np.ndarray, tuple | None, str]:
    if args.points is None:
        name = args.landscape if args.landscape in LANDSCAPES else fitness
        pts, box = sample_boltzmann(name, args.n, args.dim, beta=args.beta, seed=args.seed, box=bounds)
        return pts, box, f"exp(-{args.beta} V), V = {args.landscape}, seed {args.seed}"
    pts = load_points(args.points)
    box = None
    if args.box is not None:
        box = (np.full(pts.shape[1], args.box[0]), np.full(pts.shape[1], args.box[1]))
    elif args.periodic:
        pad = 0.5 * (np.prod(np.ptp(pts, axis=0)) / len(pts)) ** (1 / pts.shape[1])
        box = (pts.min(axis=0) - pad, pts.max(axis=0) + pad)
    return pts, box, str(args.points)


def load_points(path: Path) -> np.ndarray:
    """An (N, d) float array from a .npy file, or a ValueError saying what the file is not."""
    try:
        pts = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as err:
        raise ValueError(
            f"--points must be a .npy file written by numpy.save; {path} is not one (for a text "
            f"file: numpy.save('points.npy', numpy.loadtxt(...))). numpy said: {err}"
        ) from None
    if not isinstance(pts, np.ndarray) or pts.ndim != 2 or not np.issubdtype(pts.dtype, np.floating):
        shape = getattr(pts, "shape", None)
        raise ValueError(
            f"--points must hold an (N, d) float array; {path} holds shape {shape}, "
            f"dtype {getattr(pts, 'dtype', None)}."
        )
    return pts


def analysis_graph(a: Analysis):
    use_box = a.box if (a.args.periodic or a.args.box is not None) else None
    if a.args.graph == "knn":
        return timed(a, "knn_graph", jaxgeom.knn_graph, a.points, a.args.k, box=use_box, periodic=a.args.periodic)
    return timed(a, "delaunay", jaxgeom.delaunay, a.points, box=use_box, periodic=a.args.periodic)


def run_analysis(args) -> dict:
    start = time.perf_counter()
    resolve_options(args)
    fitness, bounds = load_landscape(args.landscape, args.dim) if args.landscape else (None, None)
    points, box, source = load_swarm(args, fitness, bounds)
    if args.graph == "delaunay" and args.points is not None:  # a sample's --dim: `resolve_options`
        check_delaunay_dim(points.shape[1], "--points of dimension")
    if args.k is None:
        args.k = default_k(points.shape[1])
    a = Analysis(args=args, points=points, box=box, source=source, fitness=fitness)
    a.timings["load"] = time.perf_counter() - start
    a.tess = analysis_graph(a)
    report = {name: section(a) for name, section in REPORT_SECTIONS}
    report["timings_s"] = {k: round(v, 6) for k, v in a.timings.items()}
    if args.out is not None:
        report["figures"] = write_figures(a, args.out)
    return report


def write_figures(a: Analysis, out: Path) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    figures = {}
    if "ricci" in a.cache and "shape" in a.cache:
        write_maps(a, out / "proxies.png")
        figures["proxies"] = str(out / "proxies.png")
    if "estimation" in a.cache:
        figures["estimation"] = str(jaxgeom.plot_estimation_quality(a.cache["estimation"], out / "estimation.png"))
    return figures


def format_report(report: dict, explain: bool = False) -> str:
    """The report as `[section]` blocks of `key value` rows; with `explain`, each row's
    definition and unit under it."""
    lines = []
    for name, values in report.items():
        lines.append(f"[{name}]")
        for key, value in values.items():
            shown = f"{value:.6g}" if isinstance(value, float) else str(value)
            lines.append(f"  {key:<38} {shown}")
            if explain:
                lines.append(f"      {analyze_definition(name, key)}")
    lines.append(UNITS if explain else "--explain defines every row and its unit.")
    return "\n".join(lines)


def add_analyze_parser(sub) -> argparse.ArgumentParser:
    an = sub.add_parser(
        "analyze",
        help="tessellate a swarm and report its geometry",
        description=__doc__.split("\n\n")[0],
        formatter_class=HelpFormatter,
    )
    an.add_argument("--points", type=Path, help="(N, d) .npy file; None: sample exp(-beta V) of --landscape")
    an.add_argument(
        "--landscape",
        default=None,
        help=f"one of {', '.join(sorted(LANDSCAPES))}, or a .py file defining V(x) (and optionally "
        "BOX = (lower, upper)): the sampled density, the Hessian metric, the fitness values "
        "(None: double_well for a sampled swarm; with --points no landscape, so only "
        "landscape-free geometry is reported)",
    )
    an.add_argument(
        "--beta", type=float, default=2.0, help="inverse temperature of the default sample (0: uniform on the box)"
    )
    an.add_argument("--dim", type=int, default=2, help="dimension of the sampled walkers")
    an.add_argument("--n", type=int, default=5000, help="walkers sampled")
    an.add_argument("--seed", type=int, default=0, help="seed of the sample")
    an.add_argument("--graph", choices=["delaunay", "knn"], default="delaunay", help="neighbour graph")
    an.add_argument(
        "--k",
        type=int,
        default=None,
        help="neighbours per walker with --graph knn (None: max(12, (d + 1)(d + 2)/2 + d), what a "
        "quadratic fit of the Hessian needs plus d)",
    )
    an.add_argument("--periodic", action="store_true", help="wrap the box (the sampling box by default)")
    an.add_argument(
        "--box",
        type=float,
        nargs=2,
        metavar=("LOWER", "UPPER"),
        help="domain bounds for every axis of --points (a sampled swarm uses its landscape's box)",
    )
    an.add_argument(
        "--metric",
        choices=["none", "hessian", "emergent"],
        default=None,
        help="metric for curvature and Riemannian volumes (hessian: of the landscape; None: hessian "
        "when there is a landscape, else none)",
    )
    an.add_argument("--eps-sigma", type=float, default=0.1, help="spectral floor of the Hessian metric")
    an.add_argument(
        "--length-scale",
        type=float,
        default=None,
        help="width l of the kernel weights exp(-|x_j - x_i|^2 / 2 l^2) of the spectral gap's graph "
        "(None: the adaptive rule, 3 x the nearest-neighbour distance); edges lighter than "
        "1e-8 of the heaviest split it into components",
    )
    an.add_argument("--explain", action="store_true", help="define every row of the report, with its unit")
    an.add_argument(
        "--out",
        type=Path,
        help="directory for summary.json and proxies.png (with --trajectory: "
        "observables.json, observables.h5md, observables.png, swarm.png)",
    )
    add_trajectory_arguments(an)
    ANALYZE_DEFAULTS.update({action.dest: action.default for action in an._actions})
    return an


ANALYZE_DEFAULTS: dict = {}  # each option's default: an option of the other mode given is refused


def analyze_main(args) -> int:
    try:
        refuse_mixed_options(args, ANALYZE_DEFAULTS)
    except ValueError as err:
        print(f"jaxgeom analyze: error: {err}", file=sys.stderr)
        return 2
    if args.trajectory is not None:
        return trajectory_main(args)
    try:
        report = run_analysis(args)
    except (ValueError, TypeError, OSError) as err:
        print(f"jaxgeom analyze: error: {err}", file=sys.stderr)
        return 2
    print(format_report(report, args.explain))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "summary.json").write_text(json.dumps(report, indent=2))
        print(f"wrote {args.out / 'summary.json'}")
    return 0
