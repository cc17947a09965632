"""Exact Euclidean Voronoi cell volumes from the Delaunay simplices alone."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._checks import takes_tessellation
from ._graph import Tessellation, simplex_coords
from ._simplex import dual_pieces, simplex_circumcenter


@takes_tessellation
@jax.jit
def voronoi_volumes(tess: Tessellation) -> Float[Array, " N"]:
    """Voronoi cell volume (area in 2D) of every walker.

    Circumcentric decomposition: each simplex is cut into signed orthoschemes
    (x_i, c(edge), c(triangle), ..., c(simplex)) spanned by the circumcentres of a
    flag of faces; the pieces of walker i, summed over its simplices, give its
    Voronoi cell exactly. Obtuse simplices contribute negative pieces, so no
    simplex needs to be well centred. Degenerate (zero-volume) simplices
    contribute nothing.

    **Arguments:**

    - `tess`: a Delaunay [`jaxgeom.Tessellation`][] (d = 2, 3 or 4).

    **Returns:**

    (N,) volumes in the dtype of `tess.points`. Unbounded cells (hull walkers of a
    non-periodic graph) are NaN; bounded cells reaching outside `box` keep their
    unclipped volume (their tier is 0). Periodic volumes sum to the box volume.
    """
    pieces = jax.vmap(dual_pieces)(simplex_coords(tess))
    pieces = jnp.where(tess.simplex_mask[:, None], pieces, 0.0)
    volumes = jax.ops.segment_sum(pieces.ravel(), tess.simplices.ravel(), num_segments=tess.n_points)
    return jnp.where(tess.hull, jnp.nan, volumes)


@takes_tessellation
@jax.jit
def circumcenters(tess: Tessellation) -> Float[Array, "S d"]:
    """Circumcentre of every simplex (the Voronoi vertices); padding rows are zero."""
    centers = jax.vmap(simplex_circumcenter)(simplex_coords(tess))
    return jnp.where(tess.simplex_mask[:, None], centers, 0.0)
