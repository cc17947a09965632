"""Open 3D Delaunay from slabs triangulated in parallel threads (Qhull releases the GIL).

The walkers are cut along their bounding box's longest side into slabs of equal counts. Each
slab triangulates its own walkers, those within a skin around it, and the vertices of the
convex hull of all (so that its hull is the swarm's). It keeps the simplices whose circumcentre
(the axis coordinate clamped to the box) lies in its range and whose circumball holds no
walker it did not see: the balls that reach past its skin inside the box are tested against
the others (a KD-tree). A neighbour's tested simplex that lies in its range and that it missed
is taken too. What is left uncovered (holes: the hull's layer of wide, flat simplices, whose
walkers lie further apart than a skin) is triangulated again from the holes' vertices, the
walkers no simplex holds and the hull's vertices, and its tested simplices are added.

Every simplex kept has an empty circumball, so in general position it is a simplex of the
Delaunay triangulation of all walkers. The union must then be a triangulation of their hull:
no facet shared by three simplices, every facet with one simplex on the hull (no vertex of the
hull beyond its plane), the volumes summing to the hull's and every walker a vertex. Where any
of this fails (co-spherical walkers split unalike by two slabs, holes that one more
triangulation did not fill, coincident walkers) `slab_triangulation` returns None and the
caller triangulates all walkers at once.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from ._triangulators import (
    _Triangulation,
    check_coordinates,
    check_thick_enough_for_qhull,
    circumballs_and_determinants,
    host_chunks,
    qhull,
    qhull_input,
)

# From this many walkers an open 3D Qhull build runs in slabs (uniform walkers, 2 cores,
# bench/README.md: N = 3e4 0.9x the single call's time, 1e5 0.8x; 1e4 no faster).
SLAB_MIN_POINTS = 30_000
SLAB_SKIN_SPACINGS = 2.6  # the skin around a slab, in mean spacings (the periodic slabs' at N = 1e4)
SLAB_MIN_SKINS = 2  # a slab is at least this many skins thick
MAX_OPEN_SLABS = 4
EMPTY_BALL_RELATIVE = 1e-10  # a walker this close to a circumsphere (times its radius) lies on it
HULL_PLANE_RELATIVE = 1e-12  # a hull vertex this far beyond a facet's plane (times the extent) is beyond it
VOLUME_RELATIVE = 1e-9  # the simplices' volumes sum to the hull's to this
HOLE_ROUNDS = 2


def slab_count(n: int, x: np.ndarray) -> int:
    """How many slabs an open 3D Qhull build of `x` (N, 3) runs in: one per core, at most
    MAX_OPEN_SLABS, each at least SLAB_MIN_SKINS skins thick; 1 (no slabs) below SLAB_MIN_POINTS
    or from 2^21 walkers (a facet's three ids fill a 64-bit key), and for walkers on a grid
    (fewer distinct coordinates along the slabs' axis than half the walkers: a lattice, whose
    co-spherical cells Qhull splits into flat simplices a slab cannot test; trying the slabs
    first cost a 32^3 lattice 4.6 s against 3.3 s)."""
    if not SLAB_MIN_POINTS <= n < 2**21 or x.shape[1] != 3:
        return 1
    lengths = np.ptp(x, axis=0).astype(np.float64)
    skin = _skin(n, lengths)
    if not skin > 0 or len(np.unique(x[:, int(np.argmax(lengths))])) < n // 2:
        return 1
    return max(1, min(os.cpu_count() or 1, MAX_OPEN_SLABS, int(lengths.max() // (SLAB_MIN_SKINS * skin))))


def _skin(n: int, lengths: np.ndarray) -> float:
    return SLAB_SKIN_SPACINGS * float(np.prod(lengths) / n) ** (1.0 / len(lengths))


def slab_triangulation(x: np.ndarray, slabs: int) -> _Triangulation | None:
    """The Delaunay triangulation of `x` (N, 3) from `slabs` slabs in threads (module
    docstring), in scipy's layout with original walker indices; None where the union fails its
    checks (the caller then triangulates all walkers at once). Raises what `qhull` raises for
    coordinates no triangulator takes or walkers too flat for Qhull."""
    check_coordinates(x)
    check_thick_enough_for_qhull(x)
    xf = np.asarray(x, np.float64)
    n = len(xf)
    try:
        hull = ConvexHull(qhull_input(xf))
    except QhullError:
        return None
    lo, hi = xf.min(axis=0), xf.max(axis=0)
    extent = float(np.max(hi - lo))
    on_hull = np.zeros(n, bool)
    on_hull[hull.vertices] = True
    axis = int(np.argmax(hi - lo))
    cuts = np.quantile(xf[:, axis], np.linspace(0.0, 1.0, slabs + 1))
    cuts[0], cuts[-1] = -np.inf, np.inf
    skin = _skin(n, hi - lo)
    with ThreadPoolExecutor(slabs) as pool:
        ranges = [(float(cuts[j]), float(cuts[j + 1])) for j in range(slabs)]
        parts = list(pool.map(lambda r: _slab(xf, on_hull, axis, r[0], r[1], skin), ranges))
    if any(part is None for part in parts):
        return None
    _take_missed(parts, cuts, n)
    union = _Union(xf, hull.vertices)
    for part in parts:
        union.add(part)
    tree = None
    for hole_round in range(HOLE_ROUNDS + 1):
        holes = union.holes()
        if holes is None or (len(holes) and hole_round == HOLE_ROUNDS):
            return None  # a facet of three simplices, or holes left
        if not len(holes):
            break
        tree = cKDTree(xf) if tree is None else tree
        wanted = on_hull | ~union.used()
        wanted[holes.ravel()] = True
        part = _part(xf, np.flatnonzero(wanted).astype(np.int32))
        if part is None:
            return None
        part["kept"] = _empty(tree, part["centre"], part["radius"]) & ~union.holds(part["simplices"], wanted)
        union.add(part)
    hull_volume = hull.volume * extent**3  # `qhull_input` scales by the extent
    if abs(union.volume - hull_volume) > VOLUME_RELATIVE * hull_volume or not union.used().all():
        return None
    return union.triangulation()


def _slab(x, on_hull, axis: int, start: float, stop: float, skin: float):
    """One slab's triangulation (`_part`) with `kept`: its simplices whose clamped centre lies in
    [start, stop) and whose balls are empty of the walkers it did not see; and `tested`, the
    simplices whose balls are empty (any centre), `ranged` their clamped centres, `seen` its
    walkers. None where Qhull refused its walkers (the caller's single call says why) or a flat
    simplex lies in its range."""
    lo, hi = x.min(axis=0), x.max(axis=0)
    region = (x[:, axis] >= start - skin) & (x[:, axis] < stop + skin)
    seen = region | on_hull
    part = _part(x, np.flatnonzero(seen).astype(np.int32))
    if part is None:
        return None
    centre, radius = part["centre"], part["radius"]
    # how far each ball reaches along the axis inside the walkers' bounding box
    off_axis = np.zeros(len(radius))
    for k in range(x.shape[1]):
        if k != axis:
            off_axis += np.maximum(np.maximum(lo[k] - centre[:, k], centre[:, k] - hi[k]), 0.0) ** 2
    reach = np.sqrt(np.maximum(radius**2 - off_axis, 0.0)) * (1.0 + EMPTY_BALL_RELATIVE)
    finite = np.isfinite(radius)
    pokes = finite & ((centre[:, axis] - reach < start - skin) | (centre[:, axis] + reach >= stop + skin))
    tested = finite.copy()
    unseen = np.flatnonzero(~seen)
    if len(unseen):
        at = np.flatnonzero(pokes)
        tested[at] = _empty(cKDTree(x[unseen]), centre[at], radius[at])
    ranged = np.clip(np.nan_to_num(centre[:, axis], nan=lo[axis]), lo[axis], hi[axis])
    if not finite[(ranged >= start) & (ranged < stop)].all():
        return None  # a flat simplex (co-spherical walkers: a lattice) cannot be tested
    part.update(tested=tested, ranged=ranged, seen=seen, kept=tested & (ranged >= start) & (ranged < stop))
    del part["centre"], part["radius"]  # 32 bytes a simplex not needed further
    return part


def _part(x, ids):
    """Qhull on the walkers `ids`: simplices in original indices (S, 4), their adjacency
    (local, -1 on this part's hull), circumcentres, radii (inf where flat) and volumes; None
    where Qhull refused them (coincident or too flat: the single call says so)."""
    try:
        tri, perm = qhull(x[ids])
    except ValueError:
        return None
    simplices = ids[tri.simplices if perm is None else perm[tri.simplices]]
    centre, radius, volume = [], [], []
    for rows in host_chunks(len(simplices)):
        c, r, det = circumballs_and_determinants(x[simplices[rows]])
        centre.append(c)
        radius.append(r)
        volume.append(np.abs(det) / 6.0)
    balls = {"centre": np.concatenate(centre), "radius": np.concatenate(radius), "volume": np.concatenate(volume)}
    return {"simplices": simplices, "adjacency": tri.neighbors, **balls}


def _empty(tree, centre, radius):
    """Whether no point of `tree` lies strictly inside each ball (to EMPTY_BALL_RELATIVE)."""
    if not len(radius):
        return np.ones(0, bool)
    distance, _ = tree.query(centre, k=1)
    return np.isfinite(radius) & (distance >= radius * (1.0 - EMPTY_BALL_RELATIVE))


def _take_missed(parts, cuts, n: int) -> None:
    """Each slab also keeps its tested simplices that lie in a neighbour's range and that the
    neighbour did not keep (it did not see all their walkers)."""
    missed = []
    for j, part in enumerate(parts):
        extra = np.zeros(len(part["kept"]), bool)
        for other in (j - 1, j + 1):
            if not 0 <= other < len(parts):
                continue
            theirs = parts[other]
            lies = (part["ranged"] >= cuts[other]) & (part["ranged"] < cuts[other + 1])
            candidates = np.flatnonzero(part["tested"] & ~part["kept"] & lies)
            kept = theirs["simplices"][theirs["kept"] & part["seen"][theirs["simplices"]].all(axis=1)]
            new = ~_isin_rows(part["simplices"][candidates], kept)
            extra[candidates[new]] = True
        missed.append(extra)
    for part, extra in zip(parts, missed, strict=True):
        part["kept"] = part["kept"] | extra


def _keys(facets, n: int):
    """One uint64 per facet (M, 3) of vertex ids below `n` (any order): the sorted ids packed
    (21 bits each: `slab_count` keeps N below 2^21)."""
    rows = np.sort(facets, axis=1).astype(np.uint64)
    bits = np.uint64(max(1, int(n - 1).bit_length()))
    return (((rows[:, 0] << bits) | rows[:, 1]) << bits) | rows[:, 2]


def _isin_rows(rows, among):
    """(M,) whether each row of vertex ids (M, k) is a row of `among` (L, k), in any order."""
    if not len(rows) or not len(among):
        return np.zeros(len(rows), bool)
    rows, among = np.sort(rows, axis=1), np.sort(among, axis=1)
    both = np.concatenate([among, rows])
    order = np.lexsort(both.T[::-1])
    ordered = both[order]
    starts = np.r_[True, np.any(ordered[1:] != ordered[:-1], axis=1)]
    group = np.cumsum(starts) - 1
    theirs = order < len(among)
    has_theirs = np.bincount(group, weights=theirs) > 0
    found = np.zeros(len(rows), bool)
    found[order[~theirs] - len(among)] = has_theirs[group[~theirs]]
    return found


class _Union:
    """The kept simplices of several triangulations, their adjacency matched across them."""

    def __init__(self, x, hull_vertices):
        self.x, self.hull_vertices = x, hull_vertices
        self.simplices, self.adjacency = [], []
        self.count, self.volume = 0, 0.0
        self.open_keys = np.zeros(0, np.uint64)
        self.open_at = np.zeros(0, np.int64)  # flat (simplex * 4 + corner) of each facet without a partner yet

    def add(self, part) -> None:
        kept = part["kept"]
        ids = np.full(len(kept) + 1, -1, np.int64)  # local -> global; -1 (and the padding) for the rest
        ids[np.flatnonzero(kept)] = self.count + np.arange(int(kept.sum()))
        simplices, adjacency = part["simplices"][kept], ids[part["adjacency"][kept]]
        rows, corners = np.nonzero(adjacency < 0)
        facets = _facets(simplices[rows], corners)
        self.open_keys = np.concatenate([self.open_keys, _keys(facets, len(self.x))])
        self.open_at = np.concatenate([self.open_at, (self.count + rows) * 4 + corners])
        self.simplices.append(simplices)
        self.adjacency.append(adjacency)
        self.count += len(simplices)
        self.volume += float(part["volume"][kept].sum())

    def holes(self):
        """The facets with one simplex that are not on the hull (M, 3) after matching the open
        facets; None where a facet has three simplices."""
        order = np.argsort(self.open_keys, kind="stable")
        keys, at = self.open_keys[order], self.open_at[order]
        same = keys[1:] == keys[:-1]
        if np.any(same[1:] & same[:-1]):
            return None
        pairs = np.flatnonzero(same)
        adjacency = np.concatenate(self.adjacency).ravel()
        adjacency[at[pairs]] = at[pairs + 1] // 4
        adjacency[at[pairs + 1]] = at[pairs] // 4
        self.adjacency = [adjacency.reshape(-1, 4)]
        alone = np.ones(len(keys), bool)
        alone[pairs] = alone[pairs + 1] = False
        self.open_keys, self.open_at = keys[alone], at[alone]
        simplices = np.concatenate(self.simplices)
        self.simplices = [simplices]
        facets = _facets(simplices[self.open_at // 4], self.open_at % 4)
        beyond = _beyond_hull(self.x, facets, simplices[self.open_at // 4, self.open_at % 4], self.hull_vertices)
        return facets[beyond]

    def used(self):
        return np.bincount(np.concatenate(self.simplices).ravel(), minlength=len(self.x)) > 0

    def holds(self, simplices, among):
        """Whether each of `simplices` is already kept (only kept ones with all vertices `among`
        can be)."""
        kept = np.concatenate(self.simplices)
        kept = kept[among[kept].all(axis=1)]
        return _isin_rows(simplices, kept)

    def triangulation(self) -> _Triangulation:
        simplices, adjacency = np.concatenate(self.simplices), np.concatenate(self.adjacency)
        return _Triangulation(simplices.astype(np.int32), adjacency.astype(np.int32))


def _facets(simplices, corners):
    """(M, 3) the facet of each simplex (M, 4) opposite its vertex `corners` (M,)."""
    others = (corners[:, None] + np.arange(1, 4)) % 4
    return np.take_along_axis(simplices, others, axis=1)


def _beyond_hull(x, facets, apexes, hull_vertices):
    """(M,) whether some hull vertex lies beyond each facet's plane (on the side away from its
    simplex's other vertex `apexes`) by more than HULL_PLANE_RELATIVE of the extent."""
    extent = float(np.max(np.ptp(x, axis=0)))
    out = np.zeros(len(facets), bool)
    step = max(1, (1 << 18) // max(1, len(hull_vertices)))  # facets per chunk: (step, H, 3) floats
    for rows in (slice(i, i + step) for i in range(0, len(facets), step)):
        p = x[facets[rows]]
        normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), np.finfo(np.float64).tiny)
        inward = np.einsum("ij,ij->i", x[apexes[rows]] - p[:, 0], normal)
        normal *= np.where(inward > 0, -1.0, 1.0)[:, None]
        height = (x[hull_vertices][None, :, :] - p[:, :1, :]) @ normal[:, :, None]
        out[rows] = np.any(height[..., 0] > HULL_PLANE_RELATIVE * extent, axis=1)
    return out
