"""Voronoi facets: the (d-1)-volume of the face each walker shares with each neighbour, the
faces on the box walls, the cells' centroids and their vertex counts, in 2D and 3D.

3D: from the Delaunay dual in O(simplices) (`_dual`: signed orthoschemes of each simplex,
no polytope per cell), and with a (non-periodic) box the tier-0 cells, those that reach it,
clipped from their half-spaces as below. 2D, and 3D's clipped cells: each cell is the
polytope {y : n_f . (y - x_i) <= c_f} of its neighbours' bisectors and, with a box, of the 2d
walls, as in `_boxclip`; a face's measure comes from intervals on lines, as the volume does
there (no polygon is built):

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

from ..tessellation._graph import Tessellation, neighbor_displacements, takes_tessellation
from ._boxclip import ROUNDING_ULPS, cell_planes, line_interval, plane_line
from ._dual import dual_faces_3d

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


def _cell_planes(tess: Tessellation, rows):
    """Half-spaces (normals (M, F, d), offsets (M, F), active (M, F)) of the cells of `rows` in
    their own frames: the K bisectors, then 2d walls (inactive without a box or on a torus)."""
    n, d = tess.points.shape
    dx = neighbor_displacements(tess)[rows]
    real = tess.neighbors[rows] < n
    r_sq = jnp.sum(jnp.where(real[..., None], dx, 1.0) ** 2, axis=-1)
    r = jnp.sqrt(r_sq)
    normals = jnp.where(real[..., None], dx / r[..., None], 0.0)
    x = tess.points[rows]
    eye = jnp.eye(d, dtype=x.dtype)
    walls = jnp.broadcast_to(jnp.concatenate([eye, -eye]), (len(rows), 2 * d, d))
    if tess.box is None or tess.periodic:
        wall_offsets = jnp.ones((len(rows), 2 * d), x.dtype)
        wall_active = jnp.zeros((len(rows), 2 * d), bool)
    else:
        box = tess.box.astype(x.dtype)
        wall_offsets = jnp.concatenate([box[1] - x, x - box[0]], axis=1)
        wall_active = jnp.ones((len(rows), 2 * d), bool)
    return (jnp.concatenate([normals, walls], axis=1), jnp.concatenate([0.5 * r, wall_offsets], axis=1),
            jnp.concatenate([real, wall_active], axis=1))


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
    if d == 3:
        return _facets_3d(tess)
    n_chunks = -(-n // FACET_CHUNK)
    rows = jnp.minimum(jnp.arange(n_chunks * FACET_CHUNK, dtype=jnp.int32), n - 1).reshape(n_chunks, FACET_CHUNK)
    measured = jax.lax.map(lambda ids: jax.vmap(_polygon_faces)(*_cell_planes(tess, ids)), rows)
    area, moment, unbounded, vertices = (a.reshape((n_chunks * FACET_CHUNK,) + a.shape[2:])[:n] for a in measured)
    k = tess.neighbors.shape[1]
    _, offsets, _ = _cell_planes(tess, jnp.arange(n, dtype=jnp.int32))
    bounded = ~jnp.any(unbounded, axis=1)
    volumes = jnp.sum(offsets * jnp.where(unbounded, 0.0, area), axis=1) / d
    safe = jnp.where(bounded & (volumes > 0), volumes, 1.0)
    centroids = tess.points + moment / ((d + 1) * safe[:, None])
    return VoronoiFacets(
        areas=jnp.where(unbounded[:, :k], jnp.inf, area[:, :k]),
        wall_areas=area[:, k:],
        volumes=jnp.where(bounded, volumes, jnp.nan),
        centroids=jnp.where(bounded[:, None], centroids, jnp.nan),
        n_vertices=jnp.where(bounded, vertices, -1).astype(jnp.int32),
    )


def _facets_3d(tess: Tessellation) -> VoronoiFacets:
    """3D: every cell from the Delaunay dual (`_dual`, O(simplices)); with a (non-periodic) box,
    the tier-0 cells (those reaching the box) clipped to it from their half-spaces (intervals on
    lines, `_polyhedron_faces`), chunks past their count skipped as in `clip_to_box`."""
    n, k = tess.neighbors.shape
    areas, unbounded, volumes, moments, vertices, _ = dual_faces_3d(tess)
    if tess.periodic:
        unbounded = jnp.zeros_like(unbounded)
    bounded = ~tess.hull
    wall_areas = jnp.zeros((n, 6), areas.dtype)
    if tess.box is not None and not tess.periodic:
        n_chunks = -(-n // FACET_CHUNK)
        rows = jnp.nonzero(tess.tier == 0, size=n_chunks * FACET_CHUNK, fill_value=n)[0].astype(jnp.int32)

        def chunk(ids):
            def clipped():
                normals, offsets, active = cell_planes(tess, ids)
                area, moment, _, count = jax.vmap(_polyhedron_faces)(normals, offsets, active)
                return area, jnp.sum(offsets * area, axis=1) / 3.0, moment / 4.0, count.astype(vertices.dtype)

            empty = (jnp.zeros((len(ids), k + 6), areas.dtype), jnp.zeros(len(ids), areas.dtype),
                     jnp.zeros((len(ids), 3), areas.dtype), jnp.zeros(len(ids), vertices.dtype))
            return jax.lax.cond(ids[0] < n, clipped, lambda: empty)

        c_area, c_volume, c_moment, c_count = (a.reshape((-1,) + a.shape[2:]) for a in
                                               jax.lax.map(chunk, rows.reshape(n_chunks, FACET_CHUNK)))
        areas = areas.at[rows].set(c_area[:, :k], mode="drop")
        wall_areas = wall_areas.at[rows].set(c_area[:, k:], mode="drop")
        volumes = volumes.at[rows].set(c_volume, mode="drop")
        moments = moments.at[rows].set(c_moment, mode="drop")
        vertices = vertices.at[rows].set(c_count.astype(vertices.dtype), mode="drop")
        unbounded = jnp.zeros_like(unbounded)
        bounded = jnp.ones(n, bool)
    safe = jnp.where(bounded & (volumes > 0), volumes, 1.0)
    return VoronoiFacets(
        areas=jnp.where(unbounded, jnp.inf, jnp.where(tess.neighbor_mask, areas, 0.0)),
        wall_areas=wall_areas,
        volumes=jnp.where(bounded, volumes, jnp.nan),
        centroids=jnp.where(bounded[:, None], tess.points + moments / safe[:, None], jnp.nan),
        n_vertices=jnp.where(bounded, vertices, -1).astype(jnp.int32),
    )
