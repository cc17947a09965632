"""Exact Euclidean Voronoi cell volumes from the Delaunay simplices alone."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._simplex import dual_pieces, simplex_circumcenter
from ..tessellation._graph import Tessellation, simplex_coords, takes_tessellation
from ._boxclip import clip_to_box


@takes_tessellation
@functools.partial(jax.jit, static_argnames="clip")
def voronoi_volumes(tess: Tessellation, *, clip: bool = True) -> Float[Array, " N"]:
    """Voronoi cell volume (area in 2D) of every walker.

    Circumcentric decomposition: each simplex is cut into signed orthoschemes
    (x_i, c(edge), c(triangle), ..., c(simplex)) spanned by the circumcentres of a
    flag of faces; the pieces of walker i, summed over its simplices, give its
    Voronoi cell exactly. Obtuse simplices contribute negative pieces, so no
    simplex needs to be well centred. Degenerate (zero-volume) simplices
    contribute nothing.

    **Arguments:**

    - `tess`: a Delaunay [`jaxgeom.Tessellation`][] (d = 2, 3 or 4).
    - `clip`: with a `box` (not periodic, d = 2 or 3), the cells that reach the box
      (tier 0, hull walkers included) are clipped to it (`jaxgeom.geometry._boxclip`), so every
      walker has a finite cell and the volumes tile the box. Tier-1 and tier-2 cells lie
      inside the box and are unchanged, and the tiers keep their meaning (curvature and
      the cell proxies still read tier 2). `clip=False`: the unclipped cells.

    **Returns:**

    (N,) volumes in the dtype of `tess.points`. Without a box (or `clip=False`, or in
    4D), unbounded cells (hull walkers of a non-periodic graph) are NaN and bounded
    cells reaching outside the box keep their unclipped volume. Periodic volumes sum to
    the box volume.
    """
    pieces = jax.vmap(dual_pieces)(simplex_coords(tess))
    pieces = jnp.where(tess.simplex_mask[:, None], pieces, 0.0)
    volumes = jax.ops.segment_sum(pieces.ravel(), tess.simplices.ravel(), num_segments=tess.n_points)
    volumes = jnp.where(tess.hull, jnp.nan, volumes)
    if clip and tess.box is not None and not tess.periodic and tess.dim in (2, 3):
        return clip_to_box(tess, volumes)
    return volumes


@takes_tessellation
@jax.jit
def circumcenters(tess: Tessellation) -> Float[Array, "S d"]:
    """Circumcentre of every simplex (the Voronoi vertices); padding rows are zero."""
    centers = jax.vmap(simplex_circumcenter)(simplex_coords(tess))
    return jnp.where(tess.simplex_mask[:, None], centers, 0.0)
