"""Exact Euclidean Voronoi cell volumes from the Delaunay simplices alone."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._simplex import dual_pieces, simplex_circumcenter
from ..tessellation._graph import Tessellation, simplex_coords, takes_tessellation
from ._boxclip import clip_to_box
from ._dual import tier0_volumes_3d


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
      (tier 0, hull walkers included) are clipped to it (3D: the Delaunay dual's pieces cut to
      the box, `jaxgeom.geometry._dualclip`; 2D: `jaxgeom.geometry._boxclip`), so every
      walker has a finite cell and the volumes tile the box. Tier-1 and tier-2 cells lie
      inside the box and are unchanged, and the tiers keep their meaning (curvature and
      the cell proxies still read tier 2). `clip=False`: the unclipped cells.

    **Returns:**

    (N,) volumes in the dtype of `tess.points`. Without a box (or `clip=False`, or in
    4D), unbounded cells (hull walkers of a non-periodic graph) are NaN, and so are 2D cells
    beside a triangle within rounding of collinear (their sign is not decided); bounded
    cells reaching outside the box keep their unclipped volume. Periodic volumes sum to
    the box volume.
    """
    pieces = jax.vmap(dual_pieces)(simplex_coords(tess))
    pieces = jnp.where(tess.simplex_mask[:, None], pieces, 0.0)
    volumes = jax.ops.segment_sum(pieces.ravel(), tess.simplices.ravel(), num_segments=tess.n_points)
    volumes = jnp.where(tess.hull | _beside_flat_triangle(tess, pieces), jnp.nan, volumes)
    if clip and tess.box is not None and not tess.periodic and tess.dim == 3:
        return jnp.where(tess.tier == 0, tier0_volumes_3d(tess), volumes)
    if clip and tess.box is not None and not tess.periodic and tess.dim == 2:
        return clip_to_box(tess, volumes)
    return volumes


def _beside_flat_triangle(tess: Tessellation, pieces):
    """(N,) walkers of a 2D Delaunay triangle that `dual_pieces` found flat (within rounding of
    collinear). A flat triangle is never Delaunay inside the hull, so it is a thin one whose
    circumcentre, a real vertex of these walkers' cells (~1e13 away for walkers on a line
    with 1e-13 noise), rounding cannot place: their volumes would be anything, of either sign.
    From 3D on, flat simplices of cospherical walkers (a lattice's) add nothing and are kept."""
    if tess.dim != 2:
        return jnp.zeros(tess.n_points, bool)
    flat = tess.simplex_mask & jnp.all(pieces == 0, axis=1)
    hits = jax.ops.segment_max(
        jnp.repeat(flat, 3).astype(jnp.int32), tess.simplices.ravel(), num_segments=tess.n_points
    )
    return hits > 0


@takes_tessellation
@jax.jit
def circumcenters(tess: Tessellation) -> Float[Array, "S d"]:
    """Circumcentre of every simplex (the Voronoi vertices); padding rows are zero."""
    centers = jax.vmap(simplex_circumcenter)(simplex_coords(tess))
    return jnp.where(tess.simplex_mask[:, None], centers, 0.0)
