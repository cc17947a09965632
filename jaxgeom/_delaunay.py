"""Host-side Delaunay builder: scipy Qhull plus index bookkeeping in numpy.

Geometry derived from the simplices (tiers from circumcentres, volumes, angles) is
computed in JAX; the one geometric test done here is the periodic skin check,
which decides whether Qhull must be run again.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import Delaunay, QhullError

from ._checks import check_full_rank, check_min_points, host_box, host_points
from ._graph import Capacity, Tessellation, bucket_neighbors, bucket_simplices, neighbor_any, simplex_vertices
from ._simplex import simplex_circumcenter

QHULL_OPTIONS = "Qbb Qc Qz Q12"
MAX_DELAUNAY_DIM = 4
# Initial periodic skin, in mean walker spacings; the skin check widens it when needed.
SKIN_SPACINGS = {2: 3.0, 3: 2.5, 4: 2.5}
SKIN_GROWTH = 1.5
SKIN_ATTEMPTS = 8


class RawGraph(NamedTuple):
    """What Qhull gives, in original walker indices (host numpy arrays)."""

    simplices: np.ndarray  # (S, d + 1)
    simplex_shifts: np.ndarray | None  # (S, d + 1, d)
    nbr_rows: np.ndarray  # (E,) walker of each directed edge
    nbr_cols: np.ndarray  # (E,) its neighbour
    nbr_shifts: np.ndarray | None  # (E, d)
    hull: np.ndarray  # (N,) bool


def delaunay(points, *, box=None, periodic: bool = False, capacity=None) -> Tessellation:
    """Delaunay graph of a swarm as a padded [`jaxgeom.Tessellation`][].

    Host-only (scipy Qhull); not jittable. Points are handed to Qhull in Morton
    order, which makes it faster; all indices refer to the original order.

    **Arguments:**

    - `points`: (N, d) float array, d = 2 or 3 (4 allowed), N >= d + 2, no
      duplicates, not all on a hyperplane.
    - `box`: `(lower, upper)` scalars or (d,) vectors. Every walker must lie
      inside; cells reaching outside the box are tier 0.
    - `periodic`: wrap the box (needs `box`). Periodic images in a skin around
      the box are triangulated and mapped back to original indices with the
      integer image shift of each neighbour and simplex vertex. The skin starts
      at `SKIN_SPACINGS[d]` mean spacings and grows until every circumsphere of
      a simplex with an original vertex lies inside it, so the result is exact.
    - `capacity`: `Capacity(simplices, neighbors)`, a `(simplices, neighbors)`
      tuple or another `Tessellation` to reuse its capacities. `None` buckets
      them (neighbours to a multiple of 8, simplices on an 8-steps-per-octave
      ladder; in 2D the exact bound 2N), so rebuilt graphs of a moving swarm
      reuse compiled kernels. A graph that does not fit raises `ValueError`.

    **Returns:**

    A `Tessellation` with simplices, neighbours (ascending index), tiers and hull flags.
    """
    x = host_points(points, "points", func="jaxgeom.delaunay")
    n, d = x.shape
    _check_delaunay_dim(d)
    check_min_points(n, d + 2, "points", f"a {d}D Delaunay tessellation")
    box_arr = host_box(box, x, periodic=periodic)
    check_full_rank(x)
    raw = _periodic_graph(x, box_arr) if periodic else _plain_graph(x)
    cap = _resolve_capacity(raw, n, d, capacity, periodic)
    return _assemble(x, raw, cap, box_arr, periodic)


def _check_delaunay_dim(d: int) -> None:
    if d < 2 or d > MAX_DELAUNAY_DIM:
        raise ValueError(
            f"`points` has dimension d={d}; jaxgeom.delaunay supports d = 2, 3 and 4 "
            "(Qhull's cost explodes beyond: at d=5, N=1e4 takes 13 s and 155 simplices per point). "
            "Use jaxgeom.knn_graph(points, k) instead, which works in any dimension."
        )


def morton_order(x: np.ndarray) -> np.ndarray:
    """Permutation sorting points along a Z-order (Morton) curve."""
    n, d = x.shape
    bits = max(1, 60 // d)
    lo, hi = x.min(axis=0), x.max(axis=0)
    q = ((x - lo) / np.where(hi > lo, hi - lo, 1.0) * (2**bits - 1)).astype(np.uint64)
    code = np.zeros(n, np.uint64)
    for b in range(bits):
        for k in range(d):
            code |= ((q[:, k] >> np.uint64(b)) & np.uint64(1)) << np.uint64(b * d + k)
    return np.argsort(code, kind="stable")


def _qhull(x: np.ndarray) -> tuple[Delaunay, np.ndarray]:
    """Qhull on Morton-sorted points; returns the triangulation and the sort permutation."""
    perm = morton_order(x)
    try:
        tri = Delaunay(np.ascontiguousarray(x[perm], dtype=np.float64), qhull_options=QHULL_OPTIONS)
    except QhullError as err:
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else "no details"
        raise ValueError(
            "`points` is degenerate for Delaunay: Qhull could not build a full-dimensional "
            "triangulation (walkers nearly collinear/coplanar or too few distinct). "
            f"Spread the walkers out or add jitter. Qhull said: {first_line}"
        ) from None
    if len(tri.coplanar):
        _raise_duplicates(x, perm, tri)
    return tri, perm


def _raise_duplicates(x: np.ndarray, perm: np.ndarray, tri: Delaunay) -> None:
    i, j = perm[tri.coplanar[0, 0]], perm[tri.coplanar[0, 2]]
    kind = "duplicates" if np.array_equal(x[i], x[j]) else "nearly coincident"
    raise ValueError(
        f"`points` has {len(tri.coplanar)} walker(s) left out of the triangulation; e.g. rows {i} and {j} "
        f"are {kind} ({x[i].tolist()}). Remove duplicate walkers (np.unique(points, axis=0)) or jitter them."
    )


def _csr_rows(tri: Delaunay, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Directed Delaunay edges (src, dst) leaving the sorted points `rows`, grouped by src."""
    indptr, indices = tri.vertex_neighbor_vertices
    counts = indptr[rows + 1] - indptr[rows]
    src = np.repeat(rows, counts)
    group_start = np.repeat(np.cumsum(counts) - counts, counts)
    dst = indices[np.repeat(indptr[rows], counts) + np.arange(counts.sum()) - group_start]
    return src, dst


def _plain_graph(x: np.ndarray) -> RawGraph:
    tri, perm = _qhull(x)
    hull = np.zeros(len(x), bool)
    hull[perm[tri.convex_hull.ravel()]] = True
    src, dst = _csr_rows(tri, np.arange(len(x)))
    return RawGraph(perm[tri.simplices], None, perm[src], perm[dst], None, hull)


def _periodic_graph(x: np.ndarray, box: np.ndarray) -> RawGraph:
    n, d = x.shape
    lengths = box[1] - box[0]
    y = x - box[0]
    skin = SKIN_SPACINGS[d] * (np.prod(lengths) / n) ** (1.0 / d)
    for _ in range(SKIN_ATTEMPTS):
        ext, ids, shifts = _periodic_images(y, lengths, skin)
        tri, perm = _qhull(ext)
        ids, shifts = ids[perm], shifts[perm]
        central = ~shifts.any(axis=1)
        simp = tri.simplices[central[tri.simplices].any(axis=1)]
        if _circumballs_inside(tri.points[simp], -skin, lengths + skin):
            break
        skin *= SKIN_GROWTH
    else:
        raise RuntimeError("periodic Delaunay: the skin check failed after widening the skin; please report this input.")
    simp = simp[_canonical_images(ids[simp], shifts[simp])]
    src, dst = _csr_rows(tri, np.flatnonzero(central))
    hull = np.zeros(n, bool)
    return RawGraph(ids[simp], shifts[simp], ids[src], ids[dst], shifts[dst], hull)


def _periodic_images(y: np.ndarray, lengths: np.ndarray, skin: float):
    """Original points (first, shift 0) and their images within `skin` of the box."""
    n, d = y.shape
    layers = int(np.ceil(skin / lengths.min()))
    pts, ids, shifts = [y], [np.arange(n)], [np.zeros((n, d), np.int8)]
    for s in itertools.product(range(-layers, layers + 1), repeat=d):
        if not any(s):
            continue
        img = y + np.asarray(s) * lengths
        keep = np.flatnonzero(np.all((img > -skin) & (img < lengths + skin), axis=1))
        pts.append(img[keep])
        ids.append(keep)
        shifts.append(np.broadcast_to(np.asarray(s, np.int8), (keep.size, d)))
    return np.concatenate(pts), np.concatenate(ids), np.concatenate(shifts)


def _circumballs_inside(p: np.ndarray, lo, hi) -> bool:
    """Whether every (finite) circumball of the simplices `p` (S, d+1, d) lies in [lo, hi]."""
    e = p[:, 1:] - p[:, :1]
    gram = np.einsum("sik,sjk->sij", e, e)
    with np.errstate(all="ignore"):
        lam = np.linalg.solve(gram, 0.5 * np.einsum("sii->si", gram)[..., None])[..., 0]
    offset = np.einsum("si,sik->sk", lam, e)
    radius = np.linalg.norm(offset, axis=1, keepdims=True)
    center = p[:, 0] + offset
    inside = np.all((center - radius >= lo) & (center + radius <= hi), axis=1)
    return bool(np.all(inside | ~np.isfinite(radius[:, 0])))


def _canonical_images(ids: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Mask keeping one translate of each periodic simplex.

    The translate kept is the one in which the vertex with the smallest key
    (original index, then shift) has shift zero; translating a simplex does not
    change which vertex that is, so exactly one translate qualifies.
    """
    span = int(np.abs(shifts).max()) if shifts.size else 0
    base = 2 * span + 1
    key = ids.astype(np.int64)
    for k in range(shifts.shape[-1]):
        key = key * base + (shifts[..., k].astype(np.int64) + span)
    first = np.argmin(key, axis=1)
    return ~shifts[np.arange(len(ids)), first].any(axis=1)


def _as_capacity(capacity) -> Capacity:
    if isinstance(capacity, Tessellation):
        return capacity.capacity
    try:
        simplices, neighbors = (int(v) for v in capacity)
    except (TypeError, ValueError):
        raise TypeError(
            "`capacity` must be a jaxgeom.Capacity, a (simplices, neighbors) tuple of ints, "
            f"a Tessellation or None; got {capacity!r}."
        ) from None
    return Capacity(simplices, neighbors)


def _resolve_capacity(raw: RawGraph, n: int, d: int, capacity, periodic: bool) -> Capacity:
    need = Capacity(len(raw.simplices), int(np.bincount(raw.nbr_rows, minlength=n).max()))
    if capacity is None:
        # In 2D a triangulation has at most 2N triangles (exactly 2N on the torus).
        simplices = 2 * n if d == 2 else bucket_simplices(need.simplices)
        return Capacity(simplices, bucket_neighbors(need.neighbors))
    pinned = _as_capacity(capacity)
    if pinned.simplices < need.simplices or pinned.neighbors < need.neighbors:
        raise ValueError(
            f"`capacity` {tuple(pinned)} is too small for this graph: it needs simplices >= "
            f"{need.simplices} and neighbors >= {need.neighbors}. Pass capacity=None to size it "
            "automatically, or a larger Capacity."
        )
    return pinned


def _pad_neighbors(raw: RawGraph, n: int, k_cap: int):
    """Scatter grouped directed edges into (N, K) rows, sorted by neighbour index."""
    rows, cols = raw.nbr_rows, raw.nbr_cols
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    slot = np.arange(rows.size) - np.repeat(starts, np.diff(np.r_[starts, rows.size]))
    nbrs = np.full((n, k_cap), n, np.int32)
    nbrs[rows, slot] = cols
    order = np.argsort(nbrs, axis=1, kind="stable")
    nbrs = np.take_along_axis(nbrs, order, axis=1)
    if raw.nbr_shifts is None:
        return nbrs, None
    shifts = np.zeros((n, k_cap, raw.nbr_shifts.shape[1]), np.int8)
    shifts[rows, slot] = raw.nbr_shifts
    return nbrs, np.take_along_axis(shifts, order[..., None], axis=1)


def _pad_simplices(raw: RawGraph, n: int, s_cap: int):
    s, d1 = raw.simplices.shape
    simplices = np.full((s_cap, d1), n, np.int32)
    simplices[:s] = raw.simplices
    if raw.simplex_shifts is None:
        return simplices, None
    shifts = np.zeros((s_cap, d1, d1 - 1), np.int8)
    shifts[:s] = raw.simplex_shifts
    return simplices, shifts


def _assemble(x: np.ndarray, raw: RawGraph, cap: Capacity, box, periodic: bool) -> Tessellation:
    n = len(x)
    nbrs, nbr_shifts = _pad_neighbors(raw, n, cap.neighbors)
    simplices, simplex_shifts = _pad_simplices(raw, n, cap.simplices)
    as_jnp = lambda a: None if a is None else jnp.asarray(a)  # noqa: E731
    tess = Tessellation(
        points=jnp.asarray(x),
        neighbors=jnp.asarray(nbrs),
        tier=jnp.full((n,), 2, jnp.int8),
        hull=jnp.asarray(raw.hull),
        simplices=jnp.asarray(simplices),
        neighbor_shifts=as_jnp(nbr_shifts),
        simplex_shifts=as_jnp(simplex_shifts),
        box=None if box is None else jnp.asarray(box, dtype=jnp.asarray(x).dtype),
        overflow=jnp.asarray(False),
        periodic=periodic,
    )
    if periodic:
        return tess
    return eqx.tree_at(lambda t: t.tier, tess, boundary_tiers(tess))


@jax.jit
def boundary_tiers(tess: Tessellation):
    """Tier 0: unbounded cell, or a Voronoi vertex (circumcentre) outside the box;
    tier 1: a neighbour of tier 0; tier 2: the rest."""
    tier0 = tess.hull
    if tess.box is not None:
        centers = jax.vmap(simplex_circumcenter)(simplex_vertices(tess))
        outside = jnp.any((centers < tess.box[0]) | (centers > tess.box[1]), axis=-1) & tess.simplex_mask
        votes = jnp.broadcast_to(outside[:, None], tess.simplices.shape).astype(jnp.int32)
        touches = jax.ops.segment_sum(votes.ravel(), tess.simplices.ravel(), num_segments=tess.n_points) > 0
        tier0 = tier0 | touches
    tier1 = neighbor_any(tess, tier0) & ~tier0
    return jnp.where(tier0, 0, jnp.where(tier1, 1, 2)).astype(jnp.int8)
