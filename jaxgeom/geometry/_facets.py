"""Voronoi facets: the (d-1)-volume of the face each walker shares with each neighbour, the
faces on the box walls, the cells' centroids and their vertex counts, in 2D and 3D.

Every cell from the Delaunay dual in O(simplices) (`_dual`: signed orthoschemes of each
simplex, no polytope per cell). With a (non-periodic) box the tier-0 cells, those that reach
it, are clipped from their half-spaces: the polytope {y : n_f . (y - x_i) <= c_f} of the
neighbours' bisectors and the 2d walls, as in `_boxclip`, measured by intervals on lines:

- 2D: face f is the interval of its line inside every other half-plane; L_f its length, m_f
  its midpoint.
- 3D: face f has area A_f = 1/2 sum_g h_fg L_fg over the lines (plane f) ∩ (plane g), h_fg the
  signed distance of line fg from the foot p_f of x_i on plane f, L_fg the length of its part
  inside every other half-space, m_fg that part's midpoint.

First moments follow from the same signed decomposition (a cone from x_i over a face has its
centroid d / (d + 1) of the way to the face's centroid; a triangle (p_f, edge) has its centroid
at (p_f + 2 m_fg) / 3), so centroid_i = x_i + sum_f c_f M_f / ((d + 1) V_i). Vertices: a polygon
has as many as edges; a clipped polyhedron E - F + 2 (Euler). A clipped cell costs O(F^d),
F = K + 2d (~1 ms per 3D cell at K = 40 on 2 cores); the dual, ~60 us per 3D cell at N = 1e4
(bench/cells_3d.py).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..tessellation._graph import Tessellation, takes_tessellation
from ._boxclip import ROUNDING_ULPS, cell_planes, line_interval, map_flagged_rows, plane_line
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
      that counts its distinct circumcentres: `_dual`).
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


def _polyhedron_faces(normals, offsets, active):
    """3D cell: per face (area, the face's first moment about x_i, unbounded), and the vertex
    count E - F + 2."""
    f = normals.shape[0]
    eye = jnp.eye(f, dtype=bool)
    size = jnp.max(jnp.where(active, offsets, 0.0))
    tol = ROUNDING_ULPS * jnp.finfo(offsets.dtype).eps * size

    def face(nf, cf, row):
        foot = cf * nf

        def edge(ng, cg, g):
            ok, point, direction, height, usable = plane_line(nf, cf, ng, cg, g, row, active)
            lower, upper, empty, unbounded, contains = line_interval(point, direction, normals, offsets, usable, size)
            first = ~jnp.any(usable & contains & (jnp.arange(f) < g))
            counted = ok & first & ~empty
            length = jnp.where(counted, jnp.maximum(upper - lower, 0.0), 0.0)
            middle = point + 0.5 * (lower + upper) * direction
            area = 0.5 * height * length
            return area, area * (foot + 2.0 * middle) / 3.0, counted & unbounded, length > tol

        area, moment, unbounded, real = jax.vmap(edge)(normals, offsets, jnp.arange(f))
        return jnp.sum(area), jnp.sum(moment, axis=0), jnp.any(unbounded), jnp.sum(real)

    area, moment, unbounded, edges = jax.vmap(face)(normals, offsets, eye)
    area = jnp.where(active, area, 0.0)
    unbounded = active & unbounded
    real_face = active & (area > tol * size)
    faces = jnp.sum(real_face)
    # edges on faces of positive area only: a zero-area plane through an edge (a lattice's
    # diagonal contact between hull walkers) would count it a third time
    vertices = jnp.sum(jnp.where(real_face, edges, 0)) // 2 - faces + 2
    moment = jnp.sum(offsets[:, None] * jnp.where(active[:, None], moment, 0.0), axis=0)
    return area, moment, unbounded, vertices


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
        raise ValueError("voronoi_facets needs a Delaunay graph (jaxgeom.delaunay): a k-NN graph has no Voronoi "
                         "cells.")
    n, d = tess.points.shape
    if d not in (2, 3):
        raise ValueError(f"voronoi_facets measures faces in 2D and 3D; this graph has d = {d}.")
    return _facets_from_dual(tess)


def _facets_from_dual(tess: Tessellation) -> VoronoiFacets:
    """Every cell from the Delaunay dual (`_dual`, O(simplices)); with a (non-periodic) box, the
    tier-0 cells (those reaching the box) clipped to it from their half-spaces (intervals on
    lines), chunks past their count skipped as in `clip_to_box`. 2D cells beside a triangle
    within rounding of flat are unbounded-like (NaN), as in `voronoi_volumes`."""
    n, k = tess.neighbors.shape
    d = tess.dim
    dual = dual_faces_2d if d == 2 else dual_faces_3d
    areas, unbounded, volumes, moments, vertices, undecided = dual(tess)  # no ray on a torus or in a box
    bounded = ~tess.hull & ~undecided
    wall_areas = jnp.zeros((n, 2 * d), areas.dtype)
    measure = _polygon_faces if d == 2 else _polyhedron_faces
    if tess.box is not None and not tess.periodic:
        def clipped(ids):
            normals, offsets, active = cell_planes(tess, ids)
            area, moment, _, count = jax.vmap(measure)(normals, offsets, active)
            return area, jnp.sum(offsets * area, axis=1) / d, moment / (d + 1), count.astype(vertices.dtype)

        def empty(ids):
            return (jnp.zeros((len(ids), k + 2 * d), areas.dtype), jnp.zeros(len(ids), areas.dtype),
                    jnp.zeros((len(ids), d), areas.dtype), jnp.zeros(len(ids), vertices.dtype))

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
