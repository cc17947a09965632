"""Layer 1, points -> `Tessellation`: the graph pytree (`_graph`), the host builders (Qhull
Delaunay in `_delaunay` with `_planar` and `_contacts`, k-NN in `_knn`) and the device rebuild
(`_cellgrid`, `_cellclip`). Imports from `base` only. The public names live in
`jaxgeom/__init__.py`."""
