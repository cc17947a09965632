"""Layer 2, the kernels: jittable functions of a `Tessellation` (volumes, metrics, curvature,
cells, edge weights, forces, spectral gap, heat method and geodesics, gradient and Hessian
estimates). Imports from `base` and `tessellation` only. The public names live in
`jaxgeom/__init__.py`."""
