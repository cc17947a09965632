"""Child process of tests/test_smallest_inputs.py: the smallest legal graphs through every public
kernel that accepts a graph, one JSON line per case (a line `start <case>` before each, so that
the parent names the case in flight when this process dies in native code).

    python tests/smallest_inputs_child.py [--kernels=all|none] CASE [CASE ...]

CASE: `delaunay:d:n:dtype:domain` (domain open, box or periodic) or `knn:d:k:dtype:domain`.
"""

import json
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
import jaxgeom  # noqa: E402


def kernels(t, v):
    """name -> thunk of every public kernel that takes the graph `t` (v: velocities)."""
    x = t.points
    bowl = lambda p: jnp.sum(p**2)  # noqa: E731
    metric = jaxgeom.hessian_metric(lambda p: jnp.sum(p**4) + jnp.sum(p**2), 0.1)
    vol = lambda: jaxgeom.voronoi_volumes(t)  # noqa: E731
    return {
        "neighbor_displacements": lambda: jaxgeom.neighbor_displacements(t),
        "simplex_vertices": lambda: jaxgeom.simplex_vertices(t),
        "circumcenters": lambda: jaxgeom.circumcenters(t),
        "voronoi_volumes": vol,
        "voronoi_facets": lambda: jaxgeom.voronoi_facets(t).areas,
        "angle_sums": lambda: jaxgeom.angle_sums(t),
        "deficit_angles": lambda: jaxgeom.deficit_angles(t),
        "ricci_scalar": lambda: jaxgeom.ricci_scalar(t),
        "ricci_scalar[metric]": lambda: jaxgeom.ricci_scalar(t, metric=metric),
        "ricci_resolution": lambda: jaxgeom.ricci_resolution(t),
        "shape_distortion": lambda: jaxgeom.shape_distortion(t),
        "vertex_distance_variance": lambda: jaxgeom.vertex_distance_variance(t),
        "volume_distortion": lambda: jaxgeom.volume_distortion(t),
        "raychaudhuri_expansion": lambda: jaxgeom.raychaudhuri_expansion(vol(), vol(), 0.1),
        "edge_lengths": lambda: jaxgeom.edge_lengths(t),
        "edge_lengths[metric]": lambda: jaxgeom.edge_lengths(t, metric=metric),
        "edge_weights": lambda: jaxgeom.edge_weights(t),
        "viscous_force": lambda: jaxgeom.viscous_force(t, v, nu=0.1),
        "emergent_metric": lambda: jaxgeom.emergent_metric(t),
        "metric_at_walkers": lambda: jaxgeom.metric_at_walkers(t, metric),
        "riemannian_volumes": lambda: jaxgeom.riemannian_volumes(t, metric=metric),
        "estimate_gradient": lambda: jaxgeom.estimate_gradient(t, jax.vmap(bowl)(x)),
        "estimate_hessian": lambda: jaxgeom.estimate_hessian(t, jax.vmap(bowl)(x)),
        "geometric_hessian": lambda: jaxgeom.geometric_hessian(t, 0.1),
        "geodesic_distances": lambda: jaxgeom.geodesic_distances(t, [0]),
        "ollivier_ricci": lambda: jaxgeom.ollivier_ricci(t).edge_curvature,
        "graph_laplacian": lambda: jaxgeom.graph_laplacian(t).weights,
        "spectral_gap": lambda: jaxgeom.spectral_gap(t, k=2),
        "scutoids": lambda: jaxgeom.scutoids(t, t).fractions(),
        "rebuild": lambda: jaxgeom.rebuild(t, x).neighbors,
    }


def graph(case):
    kind, d, size, dtype, domain = case.split(":")
    d, size = int(d), int(size)
    n = size if kind == "delaunay" else size + 1
    x = np.random.default_rng(d * 100 + n).uniform(0.05, 0.95, (n, d)).astype(dtype)
    box = None if domain == "open" else (np.zeros(d, dtype), np.ones(d, dtype))
    if kind == "delaunay":
        return jaxgeom.delaunay(x, box=box, periodic=domain == "periodic")
    return jaxgeom.knn_graph(x, size, box=box, periodic=domain == "periodic")


def outcome(thunk) -> tuple[str, float]:
    """('ok' or the class of a refusal: 'clear: Type' for a ValueError/TypeError, 'raw: Type: text'
    for anything else; seconds)."""
    began = time.perf_counter()
    try:
        jax.block_until_ready(thunk())
        verdict = "ok"
    except (ValueError, TypeError) as err:
        verdict = f"clear: {type(err).__name__}"
    except Exception as err:  # noqa: BLE001  (classified, reported by the parent)
        verdict = f"raw: {type(err).__name__}: {str(err)[:200]}"
    return verdict, round(time.perf_counter() - began, 2)


def main(cases):
    warnings.simplefilter("ignore")
    for case in cases:
        print("start", case, flush=True)
        built, _ = outcome(lambda: graph(case))
        result = {"case": case, "graph": built, "kernels": {}, "seconds": {}}
        if built == "ok" and KERNELS != "none":
            t = graph(case)
            v = jnp.asarray(np.random.default_rng(1).normal(size=t.points.shape), t.points.dtype)
            for name, thunk in kernels(t, v).items():
                result["kernels"][name], result["seconds"][name] = outcome(thunk)
        print(json.dumps(result), flush=True)


KERNELS = "all"  # or "none": the graph build alone

if __name__ == "__main__":
    if sys.argv[1].startswith("--kernels="):
        KERNELS = sys.argv.pop(1).split("=")[1]
    main(sys.argv[1:])
