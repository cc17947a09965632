"""One-line definitions, with units, of every row `jaxgeom simulate` and `jaxgeom analyze` print
(shown with --explain; tests/apps/test_cli.py checks that each printed row has one)."""

from __future__ import annotations

UNITS = (
    "Units: [x] the walkers' coordinates, [V] the landscape's values, [t] the time of --dt, [g] a length "
    "measured in the metric in use ([x] without one; [V]^(1/2) for the Hessian metric), [1] none."
)

KERNEL_GRAPH = (
    "the Delaunay (or k-NN) graph with kernel weights exp(-|x_j - x_i|^2 / 2 l^2), l = 3 x the mean "
    "nearest-neighbour distance, edges lighter than 1e-8 x the heaviest dropped"
)

SIMULATE_ROWS = {
    "mean_fitness": "mean of V over the living walkers [V]",
    "best_fitness": "lowest V among the living walkers [V]",
    "velocity_variance": "tr Cov(v) / d over the walkers: the kinetic temperature, T at equilibrium [x^2/t^2]",
    "degree_weighted_variance": "the same, each walker weighted by the sum of its viscous edge weights [x^2/t^2]",
    "mean_ricci": "Regge Ricci scalar (deficit angles) in the Hessian metric, Riemannian-volume mean over tier-2 "
    "walkers [1/g^2]",
    "ricci_resolution": "the smallest |mean_ricci| the float type resolves: below it mean_ricci is rounding [1/g^2]",
    "volume_distortion": "Var(V_i / <V_i>) of the tier-2 Voronoi cell volumes: 0 for equal cells [1]",
    "mean_shape_distortion": "mean over tier-2 cells of inradius / circumradius about the walker: 1 regular, "
    "towards 0 elongated [1]",
    "mean_expansion": "Raychaudhuri expansion d ln(sum V_i) / dt over the walkers tier 2 at both steps; NaN at "
    "step 0, which has no step before [1/t]",
    "n_clones": "walkers that cloned in the step leading to the state [count]",
    "nu": "the viscous coupling in force at the step [1/t]",
    "eps_sigma": "the Hessian-metric floor in force (raised x10 where adapt_eps_sigma finds cond(g) > 1e6) [V/x^2]",
    "mean_metric_curvature": "exact Ricci scalar of the Hessian metric (metric_curvature), Riemannian-volume mean "
    "over tier-2 walkers [1/g^2]",
    "prism_fraction": "share of the walkers tier 2 at both steps whose cell kept its neighbours [1]",
    "simple_scutoid_fraction": "share whose cell lost at most one neighbour and gained at most one, not none [1]",
    "complex_scutoid_fraction": "share whose cell lost or gained two neighbours or more [1]",
    "mean_neighbor_change": "mean number of neighbours lost plus gained over the step [count]",
    "spectral_gap": "second-smallest eigenvalue of the normalized Laplacian of the largest connected component "
    f"of {KERNEL_GRAPH}; measured every --gap-every steps; 'rounding' below 2 n eps [1]",
    "kernel_graph_components": f"connected components of {KERNEL_GRAPH} (the Delaunay graph itself is "
    "connected); at the spectral gap's steps [count]",
}

STAT_SUFFIXES = {
    "mean": "mean",
    "median": "median",
    "std": "standard deviation",
    "min": "minimum",
    "max": "maximum",
    "count": "number of finite values (0: none, so no statistics)",
}

ANALYZE_STATS = {  # analyze rows `<base>_<suffix>` with a suffix of STAT_SUFFIXES
    "tier2": "Voronoi volumes of the tier-2 cells [x^d]",
    "tier2_condition": "condition number lambda_max / lambda_min of the metric at tier-2 walkers [1]",
    "tier2_ricci": "Regge Ricci scalar at tier-2 walkers [1/g^2]",
    "tier2_exact_ricci": "exact Ricci scalar of the Hessian metric at tier-2 walkers [1/g^2]",
    "tier2_walker_curvature": "Ollivier-Ricci curvature per tier-2 walker, the mean over its edges [1]",
    "tier2_shape_distortion": "inradius / circumradius of the tier-2 cells [1]",
    "tier2_vertex_distance_variance": "variance of the distances from a tier-2 walker to its cell's vertices [x^2]",
    "tier2_gradient_norm": "|grad V| estimated by local least squares at walkers with a fit [V/x]",
    "tier2_hessian_min_eigenvalue": "smallest eigenvalue of the estimated Hessian of V [V/x^2]",
    "tier2_hessian_max_eigenvalue": "largest eigenvalue of the estimated Hessian of V [V/x^2]",
    "tier2_hessian_error_vs_exact": "relative error |H_fd - H|_F / |H|_F of the estimated Hessian against the "
    "landscape's exact one [1]",
}

ANALYZE_ROWS = {
    "swarm": {
        "source": "where the walkers come from (a .npy file, or a sample of exp(-beta V))",
        "n_walkers": "walkers N [count]",
        "dim": "dimension d [count]",
        "graph": "the neighbour graph built",
        "periodic": "whether the box wraps (a torus)",
        "landscape": "the landscape V, or none",
        "k": "neighbours per walker of the k-NN graph [count]",
        "box_lower": "the box's lower corner [x]",
        "box_upper": "the box's upper corner [x]",
    },
    "graph": {
        "tier0": "walkers whose cell is unbounded or reaches the box [count]",
        "tier1": "neighbours of tier 0 [count]",
        "tier2": "interior walkers, over which means are taken [count]",
        "degree_mean": "mean neighbours per walker [count]",
        "degree_min": "fewest neighbours [count]",
        "degree_max": "most neighbours [count]",
        "capacity_neighbors": "width of the padded neighbour rows [count]",
        "capacity_simplices": "rows of the padded simplex table [count]",
        "n_simplices": "Delaunay simplices [count]",
        "overflow": "whether a capacity was too small (the graph would be incomplete)",
    },
    "volumes": {
        "tier2_total": "summed volume of the tier-2 cells [x^d]",
        "n_unbounded": "cells without a finite volume (unbounded, no box) [count]",
        "total_in_box": "summed volume of all cells clipped to the box: the box's volume [x^d]",
    },
    "metric": {
        "kind": "the metric of curvature and Riemannian volumes: none, hessian or emergent",
        "landscape": "the landscape whose Hessian makes the metric",
        "eps_sigma": "the metric's floor [V/x^2]",
        "tier2_min_eigenvalue": "smallest metric eigenvalue at a tier-2 walker [V/x^2 or 1/x^2]",
    },
    "curvature": {
        "tier2_volume_weighted_ricci": "Regge Ricci scalar, Riemannian-volume mean over tier-2 walkers [1/g^2]",
        "tier2_volume_weighted_ricci_resolution": "the smallest |mean| the float type resolves [1/g^2]",
        "precision": "the float type of the computation",
        "tier2_ricci_resolution_median": "median per-walker resolution of the Regge scalar [1/g^2]",
        "mean_abs_deficit": "mean |deficit angle| over the hinges with a non-zero deficit [rad]",
    },
    "metric_curvature": {
        "method": "the exact form used: hessian (S from D^3 V), christoffel, or hessian-stochastic",
        "probes": "probe pairs of the stochastic form (None: exact) [count]",
        "tier2_walkers_used": "tier-2 walkers with a finite exact scalar and a positive definite metric [count]",
        "floor_active_walkers": "walkers where the metric's floor changes Hess V + eps_Sigma I [count]",
        "not_positive_definite_walkers": "walkers where the metric is not positive definite [count]",
        "flagged_nan_walkers": "walkers whose exact scalar is NaN (flagged, never averaged) [count]",
        "weights": "the measure of the means",
        "standard_error_of_the_mean": "of the stochastic form's mean [1/g^2]",
        "tier2_riemannian_mean_exact_ricci": "exact Ricci scalar, Riemannian-volume mean over tier-2 walkers [1/g^2]",
        "regge_same_walkers": "Regge scalar's mean over the walkers where both are finite, same weights [1/g^2]",
        "exact_same_walkers": "exact scalar's mean over those walkers [1/g^2]",
        "regge_vs_exact": "whether the two means estimate the same quantity here (comparable / not comparable)",
        "regge_vs_exact_why": "the criterion behind regge_vs_exact: the floor's kink, and how much the exact "
        "scalar changes between neighbouring cells against its mean",
    },
    "ollivier_ricci": {
        "k": "neighbours of the k-NN graph the curvature is computed on [count]",
        "alpha": "laziness of the random walk's measures [1]",
        "measure": "the walk's measure on the neighbours",
        "cost": "the transport's ground cost",
        "edges": "undirected edges [count]",
        "undirected_degree_max": "most undirected edges at a walker [count]",
        "isolated_walkers": "walkers without an edge [count]",
        "not_converged_walkers": "walkers whose transport did not converge [count]",
        "overflow": "whether a capacity was too small",
        "mean_edge_curvature": "kappa = 1 - W1 / d, mean over edges [1]",
        "tier2_mean_orc_scalar_estimate": "2 n^2 kappa / ((1 - alpha) E|w|^2) averaged: see scalar_estimate_note "
        "[1/g^2]",
        "scalar_estimate_note": "why that estimate is not the scalar curvature at the k-NN scale",
    },
    "cells": {
        "volume_distortion": "Var(V_i / <V_i>) of the tier-2 cell volumes [1]",
        "volume_distortion_riemannian": "the same of V_i sqrt(det g_i) [1]",
        "raychaudhuri": "the expansion needs two snapshots",
    },
    "graph_proxies": {
        "kernel_graph_components": f"connected components of {KERNEL_GRAPH} (--length-scale sets l) [count]",
        "walkers_outside_largest_component": "walkers in the smaller components [count]",
        "spectral_gap_largest_component": "second-smallest eigenvalue of the normalized Laplacian of the largest "
        "component; '< level (float64 rounding)' below 2 n eps [1]",
        "best_walker": "index of the lowest-V walker, the geodesics' source",
        "best_fitness": "its V [V]",
        "central_walker": "index of the walker nearest the centroid, the geodesics' source",
        "geodesic_method": "heat (Delaunay) or dijkstra (graph distance, k-NN)",
        "best_walker_geodesic_eccentricity": "largest geodesic distance from the source [g]",
        "best_walker_mean_geodesic_distance": "mean geodesic distance from the source [g]",
        "central_walker_geodesic_eccentricity": "largest geodesic distance from the source [g]",
        "central_walker_mean_geodesic_distance": "mean geodesic distance from the source [g]",
        "unreachable_walkers": "walkers with no path from the source [count]",
    },
    "estimation": {
        "walkers_with_hessian": "walkers whose least-squares fit is determined [count]",
        "walkers": "walkers [count]",
        "agreement_eigenvalue_correlation": "correlation of the eigenvalues of the least-squares Hessian and the "
        "geometric one [1]",
        "agreement_n_valid": "walkers compared [count]",
        "agreement_frobenius_agreement": "mean of 1 - |H_fd - H_geo|_F / (|H_fd|_F + |H_geo|_F): 1 for equal [1]",
        "agreement_method_preference": "the chapter's reading of the correlation (excellent > 0.8 > good > 0.6)",
        "geometric_reference": "what the geometric Hessian measures",
    },
}


def simulate_definition(name: str) -> str | None:
    return SIMULATE_ROWS.get(name)


def analyze_definition(section: str, key: str) -> str | None:
    """The definition of row `key` of section `section`, or None."""
    if key in ANALYZE_ROWS.get(section, {}):
        return ANALYZE_ROWS[section][key]
    if key == "skipped":
        return "why the section is not computed here"
    base, _, suffix = key.rpartition("_")
    if suffix in STAT_SUFFIXES and base in ANALYZE_STATS:
        return f"{STAT_SUFFIXES[suffix]} of the {ANALYZE_STATS[base]}"
    if section == "timings_s":
        what = key.removesuffix("_first_call")
        return f"seconds of {what}" + (", its first call (compilation included)" if key != what else "") + " [s]"
    if section == "figures":
        return "the figure written"
    return None
