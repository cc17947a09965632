"""Voronoi facets: the (d-1)-volume of the face each walker shares with each neighbour, the
faces on the box walls, the cells' centroids and their vertex counts, in 2D and 3D.

Every cell from the Delaunay dual in O(simplices) (`_dual`: signed orthoschemes of each
simplex, no polytope per cell). With a (non-periodic) box:

- 3D: the dual's pieces that reach a wall are cut to the box (`_dualclip`), so the cost of
  the clipping follows the simplices at the boundary.
- 2D: the tier-0 cells, those that reach the box, are clipped from their half-planes (the
  neighbours' bisectors and the 4 walls, as in `_boxclip`): face f is the interval of its
  line inside every other half-plane, L_f its length, m_f its midpoint; centroid_i = x_i +
  sum_f c_f L_f m_f / (3 V_i) (a cone from x_i over a face has its centroid 2/3 of the way to
  the face's midpoint); a polygon has as many vertices as edges.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..tessellation._graph import Tessellation, takes_tessellation
from ._boxclip import ROUNDING_ULPS, cell_planes, line_interval, map_flagged_rows
from ._dual import dual_faces_2d, dual_faces_3d

FACET_CHUNK = 64  # cells per chunk of `lax.map` (bounds the O(F^d) temporaries)


class VoronoiFacets(eqx.Module):
    """What `voronoi_facets` returns.

    **Fields:**

    - `areas`: (N, K) the (d-1)-volume of the face walker i shares with neighbour slot k of
      `tess.neighbors` (a length in 2D, an area in 3D): 0 on padding and for neighbours whose
      shared face has zero measure, +inf for a face that is unbounded (no box).
    - `wall_areas`: (N, 2d) the face on each box wall, walls ordered x_1 = hi_1, ..., x_d =
      hi_d, x_1 = lo_1, ..., x_d = lo_d: > 0 for the cells at the box (the reference code's
      "wall neighbours"); all 0 without a box or on a torus.
    - `volumes`: (N,) the cells' volumes from the same faces, sum_f c_f a_f / d (equal to
      `voronoi_volumes` to rounding; NaN for an unbounded cell).
    - `centroids`: (N, d) the cells' centroids (NaN for an unbounded cell; in the box frame
      for a periodic graph, possibly outside the box by up to a cell's size).
    - `n_vertices`: (N,) the number of vertices of each cell (clipped to the box), -1 for an
      unbounded cell (and, 3D, for a walker with more incident simplices than 2K + 8, the table
      that counts its distinct circumcentres: `_dual`; boxed, for a walker whose row lies past
      the table of the faces' wall segments, which holds as many slots as a triangulation has
      directed edges: a graph with more edges than `delaunay` gives).
    """

    areas: Float[Array, "N K"]
    wall_areas: Float[Array, "N W"]
    volumes: Float[Array, " N"]
    centroids: Float[Array, "N d"]
    n_vertices: Int[Array, " N"]


def _polygon_faces(normals, offsets, active):
    """2D cell: per face (length, first moment about x_i of the face's cone times d + 1 = 3,
    unbounded), and the vertex count."""
    f = normals.shape[0]
    others = active[None, :] & ~jnp.eye(f, dtype=bool)
    size = jnp.max(jnp.where(active, offsets, 0.0))

    def face(n, c, usable):
        direction = jnp.stack([-n[1], n[0]])
        point = c * n
        lower, upper, empty, unbounded, _ = line_interval(point, direction, normals, offsets, usable, size)
        length = jnp.where(empty, 0.0, jnp.maximum(upper - lower, 0.0))
        middle = point + 0.5 * (lower + upper) * direction
        return length, middle, unbounded & ~empty

    length, middle, unbounded = jax.vmap(face)(normals, offsets, others)
    length = jnp.where(active, length, 0.0)
    unbounded = active & unbounded
    moment = jnp.sum((offsets * length)[:, None] * middle, axis=0)  # sum_f c_f L_f m_f; / (3 V) below
    edges = jnp.sum(length > ROUNDING_ULPS * jnp.finfo(length.dtype).eps * size)
    return length, moment, unbounded, edges


@takes_tessellation
@eqx.filter_jit
def voronoi_facets(tess: Tessellation) -> VoronoiFacets:
    """The Voronoi faces of every cell: the area shared with each neighbour, the areas on the
    box walls, the cell's centroid and its number of vertices (2D and 3D Delaunay graphs).

    **Arguments:**

    - `tess`: a 2D or 3D Delaunay [`jaxgeom.Tessellation`][]. With a (non-periodic) `box` the
      cells are clipped to it like `voronoi_volumes`; on a torus they are measured there.

    **Returns:** a [`jaxgeom.VoronoiFacets`][]. The divergence theorem ties the faces to the
    volumes: sum_j a_ij |x_j - x_i| / (2d) + sum_walls a_w h_w / d = V_i (h_w the walker's
    distance to the wall), which the tests check against `voronoi_volumes`.
    """
    if tess.simplices is None:
        raise ValueError("voronoi_facets needs a Delaunay graph (jaxgeom.delaunay): a k-NN graph has no Voronoi cells.")
    n, d = tess.points.shape
    if d not in (2, 3):
        raise ValueError(f"voronoi_facets measures faces in 2D and 3D; this graph has d = {d}.")
    return _facets_from_dual(tess)


def _facets_from_dual(tess: Tessellation) -> VoronoiFacets:
    """Every cell from the Delaunay dual (`_dual`, O(simplices)); with a (non-periodic) box, in
    3D the dual's pieces cut to it (`_dualclip`), in 2D the tier-0 cells (those reaching the
    box) clipped from their half-planes (intervals on lines), chunks past their count skipped
    as in `clip_to_box`. 2D cells beside a triangle
    within rounding of flat are unbounded-like (NaN), as in `voronoi_volumes`."""
    n, k = tess.neighbors.shape
    d = tess.dim
    boxed = tess.box is not None and not tess.periodic
    if d == 3:  # clipped to a box by the dual as well (`_dualclip`)
        areas, unbounded, volumes, moments, vertices, undecided, wall_areas = dual_faces_3d(tess)
        bounded = ~undecided if boxed else ~tess.hull & ~undecided
    else:
        areas, unbounded, volumes, moments, vertices, undecided = dual_faces_2d(tess)  # no ray on a torus or in a box
        bounded = ~tess.hull & ~undecided
        wall_areas = jnp.zeros((n, 2 * d), areas.dtype)
    if boxed and d == 2:

        def clipped(ids):
            normals, offsets, active = cell_planes(tess, ids)
            area, moment, _, count = jax.vmap(_polygon_faces)(normals, offsets, active)
            return area, jnp.sum(offsets * area, axis=1) / d, moment / (d + 1), count.astype(vertices.dtype)

        def empty(ids):
            return (
                jnp.zeros((len(ids), k + 2 * d), areas.dtype),
                jnp.zeros(len(ids), areas.dtype),
                jnp.zeros((len(ids), d), areas.dtype),
                jnp.zeros(len(ids), vertices.dtype),
            )

        rows, (c_area, c_volume, c_moment, c_count) = map_flagged_rows(tess.tier == 0, FACET_CHUNK, clipped, empty)
        areas = areas.at[rows].set(c_area[:, :k], mode="drop")
        wall_areas = wall_areas.at[rows].set(c_area[:, k:], mode="drop")
        volumes = volumes.at[rows].set(c_volume, mode="drop")
        moments = moments.at[rows].set(c_moment, mode="drop")
        vertices = vertices.at[rows].set(c_count, mode="drop")
        bounded = bounded | jnp.zeros(n, bool).at[rows].set(True, mode="drop")
    safe = jnp.where(bounded & (volumes > 0), volumes, 1.0)
    return VoronoiFacets(
        areas=jnp.where(unbounded, jnp.inf, jnp.where(tess.neighbor_mask, areas, 0.0)),
        wall_areas=wall_areas,
        volumes=jnp.where(bounded, volumes, jnp.nan),
        centroids=jnp.where(bounded[:, None], tess.points + moments / safe[:, None], jnp.nan),
        n_vertices=jnp.where(bounded, vertices, -1).astype(jnp.int32),
    )
