"""Host triangulators behind one interface.

- "qhull": scipy's Qhull, the reference, always installed (2D-4D). It builds a d-dimensional
  Delaunay as a (d + 1)-dimensional convex hull, in floating point (options `QHULL_OPTIONS`).
- "cdt": pythoncdt (MPL-2.0; BSD-3 and Apache-2.0 parts), 2D incremental Delaunay with
  Shewchuk's exact predicates; a hard dependency.
- "shull": shull (GPL-3.0), sweep-hull in Rust, 2D and 3D, exact predicates; only with the
  opt-in extra `pip install "jaxgeom[gpl]"`.
- "cupy": CuPy's `cupyx.scipy.spatial.Delaunay` (MIT; gDel2D: parallel insertion and flips on
  the GPU, exact predicates with symbolic perturbation), 2D, with the opt-in extra
  `jaxgeom[cuda12]` or `[cuda13]` and a CUDA device. Positions go to it as float64 device
  arrays through DLPack (float32 input gives wrong triangles, cupy#8765); only its simplices
  are read (its `neighbors` are wrong, cupy#9220); its result is checked on the device
  (`_device_check.py`) and a failure falls back to CDT. Its triangles stay on the device
  (`DEVICE_BACKENDS`): the 2D graph is built there (`_delaunay.planar_graph_on_device`).
- "auto": the fastest installed for the dimension (`AUTO_ORDER`, measured in bench/README.md);
  "cupy" first where JAX's default backend is a CUDA GPU and CuPy imports.

Every backend returns scipy's layout (`simplices`, `neighbors` opposite each vertex, -1 on
the hull, `convex_hull`, `coplanar` = points left out). A
result from a backend other than Qhull is checked cheaply (`check_triangulation`: indices,
every walker used, positive orientation, symmetric adjacency, Euler's formula); a backend
that raises or fails the check is replaced by Qhull for that call, and the caller is told
(`Triangulated.fallback`), never silently.
"""

from __future__ import annotations

import functools
import importlib.util
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial import Delaunay, QhullError

from ..base._checks import check_choice, columns, flat_word, thinness

TRIANGULATORS = ("auto", "qhull", "cdt", "shull", "cupy")
DIMENSIONS = {"qhull": (2, 3, 4), "cdt": (2,), "shull": (2, 3), "cupy": (2,)}
MODULES = {"qhull": "scipy", "cdt": "pythoncdt", "shull": "shull", "cupy": "cupy"}
INSTALL = {
    "cdt": "pip install pythoncdt (MPL-2.0)",
    "shull": 'pip install "jaxgeom[gpl]" (shull, GPL-3.0)',
    "cupy": 'pip install "jaxgeom[cuda12]" (or [cuda13]: CuPy for that CUDA), on a machine with a CUDA GPU',
}
AUTO_ORDER = ("cupy", "shull", "cdt", "qhull")  # fastest first, per dimension where supported
FALLBACK = {"cupy": "cdt"}  # the backend that builds a call whose result failed (default: Qhull)
# Q5 skips Qhull's final check of its outer planes (the simplices and left-out walkers are the
# same): a periodic 3D build 7-9% faster, 1e4 and 1e5 (bench/README.md)
QHULL_OPTIONS = "Qbb Qc Qz Q12 Q5"
QHULL_ENCLOSED_OPTIONS = "Qbb Qc Q12 Q5"  # input enclosed by far points of its own: no point at infinity (Qz)
MORTON_MIN_POINTS = 30_000


COINCIDENT_RELATIVE = 1e-6  # a left-out walker this close to its partner (times the extent) coincides with it


class CoincidentPointsError(ValueError):
    """Walkers that coincide (or nearly) for the triangulator. `rows` are the walkers it left
    out of the triangulation and `partners` the vertex each coincides with (original indices)."""

    def __init__(self, message: str, rows: np.ndarray, partners: np.ndarray):
        super().__init__(message)
        self.rows, self.partners = rows, partners


class Triangulated(NamedTuple):
    """A host triangulation in original walker indices: `tri` has scipy's layout on the points
    `x[perm]` (`perm` None: unsorted); `fallback` is None, or why the asked-for backend was
    replaced by Qhull; `edge_keys` the `_pair_keys` of `tri.simplices` where its check already
    computed them (3D), for `simplex_edges`, else None."""

    tri: Any
    perm: np.ndarray | None
    fallback: str | None
    edge_keys: tuple[np.ndarray, int] | None = None


@functools.cache
def installed(name: str) -> bool:
    if name == "cupy":
        return cuda_cupy_available()
    return importlib.util.find_spec(MODULES[name]) is not None


def cuda_cupy_available() -> bool:
    """CuPy imports and JAX's default backend is a CUDA GPU (where the positions already are)."""
    if importlib.util.find_spec("cupy") is None:
        return False
    try:
        import cupy
        import jax

        return jax.default_backend() == "gpu" and cupy.cuda.runtime.getDeviceCount() > 0
    except Exception:  # noqa: BLE001 - a CuPy without its CUDA libraries: not available
        return False


def resolve_triangulator(name: str, d: int) -> str:
    """The backend `name` stands for in dimension `d` ("auto": the fastest installed); a
    clear `ValueError` for an unknown name, an unsupported dimension or a missing package."""
    if not isinstance(name, str):
        raise TypeError(f"`triangulator` must be a string, one of {TRIANGULATORS}; got {type(name).__name__}.")
    check_choice(name, "triangulator", TRIANGULATORS)
    if name == "auto":
        return next((b for b in AUTO_ORDER if d in DIMENSIONS[b] and installed(b)), "qhull")
    if d not in DIMENSIONS[name]:
        raise ValueError(
            f"triangulator={name!r} builds d = {', '.join(map(str, DIMENSIONS[name]))} only; these "
            f"points have d = {d}. Use triangulator='auto' or 'qhull'."
        )
    if not installed(name):
        if name == "cupy" and importlib.util.find_spec("cupy") is not None:
            import jax

            raise ValueError(
                f"triangulator='cupy' needs JAX's default backend on a CUDA GPU, where the positions "
                f"live; CuPy is installed, but JAX's backend is {jax.default_backend()!r} (or CuPy finds "
                'no CUDA device). Install jax with CUDA (pip install "jax[cuda12]"), or use '
                "triangulator='auto'."
            )
        raise ValueError(f"triangulator={name!r} is not installed: {INSTALL[name]}. Or use triangulator='auto'.")
    return name


# Beyond this |coordinate| the predicates' products of four coordinates overflow float64: CDT
# then looped for minutes (one walker at 1e200) or allocated until the machine ran out of memory
# (an infinite coordinate), as a diverging swarm's rebuild did (`jaxgeom tune` on Rosenbrock).
MAX_COORDINATE = 1e75


def check_coordinates(x: np.ndarray) -> None:
    """Refuse non-finite coordinates, and coordinates beyond +-`MAX_COORDINATE`, with a ValueError
    (a traced rebuild turns it into REBUILD_FAILED, the swarm's divergence flag)."""
    bad = ~np.isfinite(x).all(axis=1)
    if x.dtype.itemsize >= 8:  # float32 cannot exceed 3.4e38
        bad |= np.abs(np.where(bad[:, None], 0.0, x)).max(axis=1) > MAX_COORDINATE
    if bad.any():
        raise ValueError(
            f"{int(bad.sum())} walker(s) have non-finite coordinates or coordinates beyond "
            f"+-{MAX_COORDINATE:g} (first rows {np.flatnonzero(bad)[:5].tolist()}), which no "
            "triangulator can take: the walkers diverged, or the input is corrupt."
        )


def triangulate(x: np.ndarray, name: str, *, enclosed: bool = False) -> Triangulated:
    """Delaunay triangulation of `x` (N, d) by the resolved backend `name`, Qhull where it
    fails. Raises `CoincidentPointsError` for walkers the triangulation leaves out, and
    `ValueError` for degenerate input (all walkers on a hyperplane) and for coordinates no
    backend can take (`check_coordinates`). `enclosed`: a few far points of `x` enclose the
    rest (a periodic slab's guards), so Qhull needs no point at infinity (`qhull`)."""
    check_coordinates(x)
    if name == "qhull":
        return Triangulated(*qhull(x, enclosed=enclosed), None)
    try:
        tri = BUILDERS[name](x)
    except CoincidentPointsError:
        raise
    except Exception as err:  # noqa: BLE001 - any failure of a backend means Qhull builds this call
        reason: str | None = f"{name} raised {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"
    else:
        if len(tri.coplanar):
            raise_duplicates(x, tri.coplanar[:, 0], tri.coplanar[:, 2])
        reason, keys = (None, None) if getattr(tri, "checked", False) else _checked(tri, x)
        if reason is None:
            return Triangulated(tri, None, None, keys)
        reason = f"{name}'s triangulation failed its check: {reason}"
    if FALLBACK.get(name) == "cdt":
        try:
            return Triangulated(_cdt(x), None, f"{reason}; CDT built this graph instead")
        except CoincidentPointsError:
            raise
        except Exception:  # noqa: BLE001 - then Qhull, as for the other backends
            pass
    try:
        return Triangulated(*qhull(x, enclosed=enclosed), f"{reason}; Qhull built this graph instead")
    except ValueError as err:
        advice = f" Use triangulator='{name}' (exact predicates), or"  # it was used: not advice
        raise ValueError(f"{reason}, and its fallback: {err}".replace(advice, "")) from None


# --- Qhull ------------------------------------------------------------------------------


# Masks that spread 16 bits of a coordinate to every d-th bit (d = 2, 3): shift, then mask.
_SPREAD = {
    2: ((8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F), (2, 0x3333333333333333), (1, 0x5555555555555555)),
    3: (
        (32, 0x001F00000000FFFF),
        (16, 0x001F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ),
}


def morton_codes(x: np.ndarray) -> tuple[np.ndarray, int]:
    """Z-order (Morton) codes of points quantised on their bounding box, and the
    number of code bits (bits per coordinate x d); bit b * d + k is bit b of coordinate k."""
    n, d = x.shape
    bits = max(1, min(16, 60 // d))
    cols = columns(x)
    lo, hi = cols.min(axis=1), cols.max(axis=1)
    q = ((cols - lo[:, None]) / np.where(hi > lo, hi - lo, 1.0)[:, None] * (2**bits - 1)).astype(np.uint64)
    code = np.zeros(n, np.uint64)
    for k in range(d):
        code |= _spread_bits(q[k], d, bits) << np.uint64(k)
    return code, bits * d


def _spread_bits(v: np.ndarray, d: int, bits: int) -> np.ndarray:
    """Bit b of `v` moved to bit b * d, for its low `bits` bits."""
    if d in _SPREAD:
        for shift, mask in _SPREAD[d]:
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v
    out = np.zeros_like(v)
    for b in range(bits):
        out |= ((v >> np.uint64(b)) & np.uint64(1)) << np.uint64(b * d)
    return out


def morton_order(x: np.ndarray, stable: bool = True) -> np.ndarray:
    """Permutation sorting points along a Z-order (Morton) curve; ties (points in one
    quantisation cell) keep their input order where `stable`, else in no set order."""
    return np.argsort(morton_codes(x)[0], kind="stable" if stable else None)


def qhull_input(x: np.ndarray) -> np.ndarray:
    """Points as handed to Qhull: centred on their bounding box and scaled to unit size (a
    similarity, so the Delaunay triangulation is unchanged). Qhull's in-sphere tests lose
    digits with |x|^2; a grid of spacing 1e-6 centred at 1e6 is otherwise refused."""
    cols = columns(x)
    lo, hi = cols.min(axis=1), cols.max(axis=1)
    extent = float(np.max(hi - lo))
    return np.ascontiguousarray((x - 0.5 * (lo + hi)) / (extent if extent > 0 else 1.0), dtype=np.float64)


QHULL_MIN_THICKNESS = 1e-13  # RMS distance from the best-fit hyperplane over the extent


def check_thick_enough_for_qhull(x: np.ndarray) -> None:
    """Qhull's predicates are not exact: walkers within ~1e-13 of a hyperplane (relative RMS
    distance; a line with 1e-13 noise) get a triangulation that is not Delaunay, and cells
    of the wrong sign (measured: 2 of 338 cells at 1e-13, none at 1e-12, 12 seeds). CDT and
    shull decide with exact predicates."""
    thickness = thinness(x)
    if thickness is not None and thickness < QHULL_MIN_THICKNESS:
        what = flat_word(x.shape[1])
        exact = "triangulator='cdt'" if x.shape[1] == 2 else "the gpl extra's triangulator='shull'"
        raise ValueError(
            f"`points` is nearly {what} (RMS distance from the best-fit plane {thickness:.2g} of the "
            f"extent): Qhull, whose predicates are not exact, cannot triangulate it correctly. Use "
            f"{exact} (exact predicates), or spread the walkers out."
        )


def qhull(x: np.ndarray, *, enclosed: bool = False) -> tuple[Delaunay, np.ndarray | None]:
    """Qhull on Morton-sorted points; returns the triangulation and the sort permutation
    (None where the points were not sorted: sorting pays off only for large inputs,
    20% faster Qhull at N = 1e5, nothing at 1e4). `tri.points` are `qhull_input(x)`.
    `enclosed` (a few far points of `x` enclose the rest): without Qz
    (`QHULL_ENCLOSED_OPTIONS`), whose point at infinity they replace; beside them it cost
    precision (3D periodic, N = 1e5: in one of 8 samples a simplex whose circumsphere holds a
    walker 1.7e-7 of its size inside)."""
    check_thick_enough_for_qhull(x)
    perm = morton_order(x) if len(x) >= MORTON_MIN_POINTS else None
    options = QHULL_ENCLOSED_OPTIONS if enclosed else QHULL_OPTIONS
    try:
        tri = Delaunay(qhull_input(x if perm is None else x[perm]), qhull_options=options)
    except QhullError as err:
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else "no details"
        raise ValueError(
            "`points` is degenerate for Delaunay: Qhull could not build a full-dimensional "
            "triangulation (walkers nearly collinear/coplanar or too few distinct). "
            f"Spread the walkers out or add jitter. Qhull said: {first_line}"
        ) from None
    if len(tri.coplanar):
        rows, partners = tri.coplanar[:, 0], tri.coplanar[:, 2]
        raise_duplicates(x, *((rows, partners) if perm is None else (perm[rows], perm[partners])))
    return tri, perm


def raise_duplicates(x: np.ndarray, rows: np.ndarray, partners: np.ndarray) -> None:
    """`CoincidentPointsError` for walkers `rows` left out, each coinciding with `partners`;
    a `ValueError` (degenerate input) where a left-out walker is far from its partner: it lies
    within rounding of a flat piece of the swarm (walkers on a line with 1e-13 noise)."""
    i, j = rows[0], partners[0]
    extent = float(np.max(np.ptp(x, axis=0)))
    gap = np.max(np.abs(x[rows] - x[partners]), axis=1)
    if np.any(gap > COINCIDENT_RELATIVE * extent):
        far = int(np.argmax(gap))
        what = flat_word(x.shape[1])
        raise ValueError(
            f"`points` is nearly degenerate: walker {rows[far]} lies within rounding of a {what} piece of the "
            f"swarm (its nearest triangulated walker {partners[far]} is {gap[far]:.3g} away, so it is no "
            f"duplicate) and no triangulation resolves it. Spread the walkers out (nearly {what} walkers "
            "have Voronoi cells ~1/thickness large), or drop the flat coordinate(s)."
        )
    kind = "duplicates" if np.array_equal(x[i], x[j]) else "nearly coincident"
    raise CoincidentPointsError(
        f"`points` has {len(rows)} walker(s) left out of the triangulation; e.g. rows {i} and {j} "
        f"are {kind} ({x[i].tolist()}). Remove duplicate walkers (np.unique(points, axis=0)) or jitter them.",
        rows,
        partners,
    )


def _edge_columns(p: np.ndarray) -> np.ndarray:
    """(d, d, S) the edges of simplices p (S, d + 1, d) from their first vertex, each
    coordinate of each edge a contiguous (S,) row (elementwise work on them runs 2x faster
    than on strided columns)."""
    return np.ascontiguousarray((p[:, 1:] - p[:, :1]).transpose(1, 2, 0))


def _cross(u, v):
    """u x v of 3-vectors given as rows (each coordinate an array)."""
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _dot(u, v):
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def circumballs_and_determinants(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Circumcentres (S, d) and radii (S,) of simplices p (S, d + 1, d) (inf where flat), from
    E u = |e|^2 / 2 (in 3D by Cramer's rule: u = (|a|^2 b x c + |b|^2 c x a + |c|^2 a x b) /
    (2 a . b x c)), and det E (S,) of the edges from the first vertex (d! times the signed
    volume)."""
    if p.shape[1:] == (4, 3):
        a, b, c = _edge_columns(p)
        squares = [_dot(e, e) for e in (a, b, c)]
        bc = _cross(b, c)
        det = _dot(a, bc)
        flat = np.abs(det) <= 1e-12 * (squares[0] + squares[1] + squares[2]) ** 1.5
        half = 0.5 / np.where(flat, 1.0, det)
        ca, ab = _cross(c, a), _cross(a, b)
        offset = np.stack(
            [(squares[0] * bc[k] + squares[1] * ca[k] + squares[2] * ab[k]) * half for k in range(3)], axis=1
        )
    else:
        e = p[:, 1:] - p[:, :1]
        squares = np.einsum("sij,sij->si", e, e)
        det = np.linalg.det(e)
        flat = np.abs(det) <= 1e-12 * np.sum(squares, axis=1) ** (e.shape[1] / 2)
        e[flat] = np.eye(e.shape[1])
        offset = np.linalg.solve(e, 0.5 * squares[..., None])[..., 0]
    radius = np.where(flat, np.inf, np.linalg.norm(offset, axis=1))
    return p[:, 0] + offset, radius, det


# --- CDT and shull ----------------------------------------------------------------------


class _Triangulation:
    """scipy's layout for a backend that gives only simplices and their adjacency."""

    def __init__(self, simplices: np.ndarray, neighbors: np.ndarray, oriented: bool = False):
        self.simplices, self.neighbors = simplices, neighbors
        self.coplanar = np.zeros((0, 3), np.int32)
        # True where the builder already dropped every simplex that `_flat` flags (the check's
        # own orientation test, on these very simplices): the check skips repeating it.
        self.oriented = oriented
        self.checked = False  # True where the device already checked it (`_device_triangulation`)

    @functools.cached_property
    def convex_hull(self) -> np.ndarray:
        simplex, corner = np.nonzero(self.neighbors < 0)
        d1 = self.simplices.shape[1]
        others = (corner[:, None] + np.arange(1, d1)) % d1
        return self.simplices[simplex[:, None], others]


def _cdt(x: np.ndarray) -> _Triangulation:
    import pythoncdt

    # Large inputs go in Morton order: CDT's own KD-tree ordering then touches memory
    # in order (N = 1e6: 1.38 s -> 0.85 s for the insertion; the codes and the sort ~0.2 s).
    perm = morton_order(x, stable=False) if len(x) >= MORTON_MIN_POINTS else None
    points = np.ascontiguousarray(x if perm is None else x[perm], dtype=np.float64)
    tri = pythoncdt.Triangulation(
        pythoncdt.VertexInsertionOrder.AUTO, pythoncdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0
    )
    try:
        tri.insert_vertices(points)  # type: ignore[call-overload]  # its stub lists V2d; it takes (N, 2) arrays
    except RuntimeError as err:
        if "Duplicate vertex" in str(err):
            _raise_exact_duplicates(x)
        raise
    raw = tri.triangles_array(copy=False)
    # Vertices 0-2 are CDT's super-triangle: dropping its triangles here, in numpy, costs a
    # quarter of `erase_super_triangle` (1.9 ms at N = 1e4). CDT also keeps zero-area triangles
    # along an exactly collinear hull side (a sheared lattice's bottom row), which Qhull does
    # not have; they go too, leaving the middle walkers on the hull (`check_triangulation`
    # then verifies the result).
    vertices = raw["vertices"].astype(np.int32)
    keep = vertices.min(axis=1) >= 3
    vertices = vertices[keep] - 3
    keep[keep] = thick = ~_flat(points, vertices)
    renumber = np.where(keep, np.cumsum(keep, dtype=np.int32) - 1, -1)
    # CDT's neighbour k lies across the edge (v_k, v_k+1), i.e. opposite vertex k + 2.
    across = raw["neighbors"][keep][:, [1, 2, 0]]
    neighbors = np.where(across == pythoncdt.NO_NEIGHBOR, -1, renumber[np.minimum(across, len(keep) - 1)])
    simplices = vertices[thick] if perm is None else perm.astype(np.int32)[vertices[thick]]
    return _Triangulation(simplices, neighbors, oriented=True)


def _raise_exact_duplicates(x: np.ndarray) -> None:
    _, first, inverse = np.unique(x, axis=0, return_index=True, return_inverse=True)
    rows = np.flatnonzero(first[inverse.ravel()] != np.arange(len(x)))
    if rows.size:
        raise_duplicates(x, rows, first[inverse.ravel()][rows])


def _shull(x: np.ndarray):
    import shull

    return shull.Delaunay(np.ascontiguousarray(x, dtype=np.float64))


def _cupy(x) -> _Triangulation:
    return gpu_triangulation(x, "cupy")


def gpu_triangulation(x, backend: str) -> _Triangulation:
    """A device backend's 2D triangulation in scipy's layout, for the host paths (periodic
    images, `planar_triangles`): `device_triangles`, checked and its adjacency derived on the
    device (`planar_summary`; a failed check raises, and `triangulate` falls back to CDT), then
    copied to the host. Only the backend's `simplices` are read (counter-clockwise, as CuPy
    documents)."""
    import jax

    from ._device_check import REASONS, planar_summary

    triangles, flat = device_triangles(x, 2 * len(x), len(x), backend)
    (counts, _), adjacency = planar_summary(jax.numpy.asarray(x), triangles, flat, len(x))
    status, count, _ = (int(c) for c in jax.device_get(counts))
    if status:
        raise RuntimeError(REASONS[status])
    simplices, adjacency = (np.asarray(a)[:count] for a in jax.device_get((triangles, adjacency)))
    tri = _Triangulation(simplices, adjacency, oriented=True)
    tri.checked = True  # the device check ran: `triangulate` does not repeat it on the host
    return tri


BUILDERS = {"cdt": _cdt, "shull": _shull, "cupy": _cupy}


# --- backends whose triangles stay on the device ------------------------------------------


def _cupy_modules():
    import cupy
    from cupyx.scipy.spatial import Delaunay as CupyDelaunay

    return CupyDelaunay, cupy


# name -> () -> (its Delaunay class, its array module); the 2D graph is built on the device
# (`_delaunay.planar_graph_on_device`, and `traced_device_triangles` inside a trace).
DEVICE_BACKENDS = {"cupy": _cupy_modules}


class TooManyTriangles(RuntimeError):
    """A triangulation with more triangles than the rows it was given."""


def padded_triangles(p, rows: int, sentinel: int, delaunay, xp):
    """`(triangles, flat)` arrays of module `xp`: the (rows, 3) int32 triangles of `delaunay` on
    the float64 positions `p` (N, 2), padded with rows of `sentinel` (>= N), and how many are
    flat or negatively oriented (`_flat`, in float64). Raises `ValueError` for non-finite
    positions and coordinates beyond +-`MAX_COORDINATE` (before the backend sees them; the host
    path says which) and `TooManyTriangles`."""
    if not bool(xp.all(xp.abs(p) <= MAX_COORDINATE)):  # NaN fails it too
        raise ValueError(
            "walkers with non-finite coordinates or coordinates beyond "
            f"+-{MAX_COORDINATE:g}, which no triangulator can take"
        )
    simplices = xp.asarray(delaunay(p).simplices).astype(xp.int32)
    if simplices.shape[0] > rows:
        raise TooManyTriangles(f"{simplices.shape[0]} triangles for {len(p)} walkers, more than the {rows} rows")
    padded = xp.full((rows, 3), sentinel, xp.int32)
    padded[: simplices.shape[0]] = simplices
    return padded, xp.sum(_flat(p, simplices, xp)).astype(xp.int32).reshape(())


def device_triangles(points, rows: int, sentinel: int, backend: str):
    """`padded_triangles` of the device backend `backend` as JAX arrays. A JAX array goes in
    through DLPack and the triangles come back the same way: the positions never leave the
    device (a host array is copied in; with numpy standing in for the module, all is host)."""
    import jax

    delaunay, xp = DEVICE_BACKENDS[backend]()
    if xp is np:
        p = np.asarray(points)
    else:
        p = xp.from_dlpack(points) if isinstance(points, jax.Array) else xp.asarray(points)
    triangles, flat = padded_triangles(xp.ascontiguousarray(p.astype(xp.float64)), rows, sentinel, delaunay, xp)
    to_jax = jax.numpy.asarray if xp is np else jax.dlpack.from_dlpack
    return to_jax(triangles), to_jax(flat)


# What `traced_device_triangles` returns in place of a flat count when it has no triangles.
REFUSED, TOO_MANY, FAILED = -1, -2, -3


def traced_device_triangles(points, rows: int, sentinel: int, backend: str):
    """`device_triangles` inside a trace (jit, vmap (one swarm after the other), grad of the
    rest: pass `stop_gradient`ed positions), through `jax.experimental.buffer_callback`: the
    backend reads the positions' device buffer and writes the triangles into the output's, on
    XLA's stream, so the positions never cross to the host. Returns `(triangles, code)`: `code`
    the flat count (>= 0), or `REFUSED` (`padded_triangles` raised ValueError), `TOO_MANY` (more
    triangles than `rows`: the capacity overflowed) or `FAILED` (the backend raised); the
    triangles are then all padding."""
    import contextlib

    import jax
    from jax.experimental.buffer_callback import buffer_callback

    def fill(ctx, out, x):
        delaunay, xp = DEVICE_BACKENDS[backend]()
        triangles, code = (xp.asarray(buffer) for buffer in out)
        stream = contextlib.nullcontext() if xp is np else xp.cuda.ExternalStream(ctx.stream)
        with stream:
            triangles[...] = sentinel  # what a failed call leaves: padding, never stale memory
            try:
                padded, flat = padded_triangles(xp.asarray(x).astype(xp.float64), rows, sentinel, delaunay, xp)
                triangles[...], code[...] = padded, flat
            except ValueError:
                code[...] = REFUSED
            except TooManyTriangles:
                code[...] = TOO_MANY
            except Exception:  # noqa: BLE001 - any failure of the backend: the host builds this graph
                code[...] = FAILED

    shapes = (jax.ShapeDtypeStruct((rows, 3), np.int32), jax.ShapeDtypeStruct((), np.int32))
    return buffer_callback(fill, shapes, vmap_method="sequential")(points)


# --- the check --------------------------------------------------------------------------


def check_triangulation(tri, x: np.ndarray) -> str | None:
    """None if `tri` is a valid triangulation of the convex hull of `x`, else what is wrong:
    indices in range, every walker a vertex, every simplex positively oriented, adjacency
    symmetric, and Euler's formula (2D: S = 2N - b - 2 with b hull edges; 3D: V - E + F - S = 1).
    The orientation test is skipped for a triangulation marked `oriented` (CDT's builder ran
    the same `_flat` test on the same simplices)."""
    return _checked(tri, x)[0]


def _checked(tri, x: np.ndarray) -> tuple[str | None, tuple[np.ndarray, int] | None]:
    """`check_triangulation`, and the `_pair_keys` its 3D Euler count computed (else None)."""
    s, adj = np.asarray(tri.simplices), np.asarray(tri.neighbors)
    n, d = x.shape
    if s.ndim != 2 or s.shape[1] != d + 1 or adj.shape != s.shape or len(s) == 0:
        return f"simplices of shape {s.shape}, adjacency {adj.shape}", None
    if s.min() < 0 or s.max() >= n or np.bincount(s.ravel(), minlength=n).min() == 0:
        return "a vertex index out of range or a walker left out", None
    flat = np.zeros(0, bool) if getattr(tri, "oriented", False) else _flat(x, s)
    if flat.any():
        return f"{int(flat.sum())} simplices flat or negatively oriented", None
    if adj.max() >= len(s) or not _symmetric(adj):
        return "the simplex adjacency is not symmetric", None
    hull_faces = int((adj < 0).sum())
    if d == 2 and len(s) != 2 * n - hull_faces - 2:
        return f"{len(s)} triangles where Euler's formula needs {2 * n - hull_faces - 2}", None
    if d != 3:
        return None, None
    keys = _pair_keys(s, n)
    if n - len(keys[0]) + (4 * len(s) + hull_faces) // 2 - len(s) != 1:
        return "Euler's characteristic V - E + F - S is not 1", None
    return None, keys


def simplex_edges(
    simplices: np.ndarray, n: int, keys: tuple[np.ndarray, int] | None = None, sources: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Host: the directed Delaunay edges (src, dst) of `simplices` (walkers < n), each once,
    sorted by src, then dst (`_pair_keys`, each key then also reversed). `keys`: their
    `_pair_keys` where already computed (`Triangulated.edge_keys`); `sources` (n,) bool: only
    the edges from these walkers."""
    pairs, bits = _pair_keys(simplices, n) if keys is None else keys
    mask = pairs.dtype.type((1 << bits) - 1)
    high, low = pairs >> bits, pairs & mask
    reversed_ = (low << bits) | high
    if sources is not None:
        pairs, reversed_ = pairs[sources[high]], reversed_[sources[low]]
    directed = np.concatenate([pairs, reversed_])
    directed.sort()
    return (directed >> bits).astype(np.int32), (directed & mask).astype(np.int32)


def _pair_keys(simplices: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """(the edges of `simplices` as sorted distinct integer keys, the bits of an id in a key):
    every pair of vertices of a simplex as one key, the lower id in the high bits (32-bit keys
    up to n = 2^16 walkers, ids < 2^16; 64-bit above)."""
    bits = max(1, int(n - 1).bit_length())
    dtype = np.uint32 if 2 * bits <= 32 else np.uint64
    columns = simplices.T.astype(dtype, order="C")  # (d + 1, S) contiguous: each pair's key in whole-row passes
    pairs = list(zip(*np.triu_indices(len(columns), 1), strict=True))
    keys, larger = np.empty((len(pairs), columns.shape[1]), dtype), np.empty(columns.shape[1], dtype)
    for row, (a, b) in zip(keys, pairs, strict=True):  # (3D, 8.7e5 simplices: 28 ms against 54 for fancy indexing)
        np.minimum(columns[a], columns[b], out=row)
        np.maximum(columns[a], columns[b], out=larger)
        row <<= dtype(bits)
        row |= larger
    keys = keys.ravel()
    keys.sort()
    distinct = np.empty(keys.size, bool)
    distinct[0] = True
    np.not_equal(keys[1:], keys[:-1], out=distinct[1:])
    return np.compress(distinct, keys), bits  # half the time of keys[distinct] (numpy 2.2)


# simplices per chunk of the host checks (here and the periodic slabs'): their float64
# temporaries (64 kB each) stay in cache (a periodic slab's 5.2e5 simplices at N = 1e5:
# orientations 76 -> 17 ms, adjacency 56 -> 23 ms, circumballs 122 -> 65 ms against one pass)
CHECK_CHUNK = 1 << 13


def host_chunks(total: int) -> list[slice]:
    """Slices of at most CHECK_CHUNK rows covering `total`."""
    return [slice(start, start + CHECK_CHUNK) for start in range(0, total, CHECK_CHUNK)]


def _symmetric(adj: np.ndarray) -> bool:
    """Whether every simplex lists, among its own neighbours, each simplex that lists it."""
    flat, width = adj.ravel(), adj.shape[1]
    for rows in host_chunks(len(adj)):
        block = adj[rows].ravel()
        listed = np.flatnonzero(block >= 0)
        owner = (rows.start + listed // width).astype(adj.dtype)
        first = block[listed] * width  # row-major: flat indices
        if not np.logical_or.reduce([flat[first + k] == owner for k in range(width)]).all():
            return False
    return True


def _flat(x: np.ndarray, s: np.ndarray, xp=np) -> np.ndarray:
    """(S,) simplices of zero or negative volume, up to the rounding of its terms (arrays of
    module `xp`: numpy, in chunks, or CuPy on the device, at once)."""
    rounding = 8 * np.finfo(np.float64).eps
    if xp is not np:
        volume, size = _volumes(x, s, xp)
        return volume <= rounding * size
    x, flat = np.asarray(x, dtype=np.float64), np.empty(len(s), bool)
    for rows in host_chunks(len(s)):
        volume, size = _volumes(x, s[rows])
        flat[rows] = volume <= rounding * size
    return flat


def _volumes(x: np.ndarray, s: np.ndarray, xp=np) -> tuple[np.ndarray, np.ndarray]:
    """Signed volumes (times d!) of simplices `s` of `x` in float64, and the size of their
    terms (a volume within 8 float64 epsilons of it counts as flat: its sign is rounding)."""
    cols = xp.asarray(x, dtype=xp.float64).T
    base = [c[s[:, 0]] for c in cols]
    e = [[c[s[:, a]] - b for c, b in zip(cols, base, strict=True)] for a in range(1, s.shape[1])]
    if x.shape[1] == 2:
        terms = (e[0][0] * e[1][1], e[0][1] * e[1][0])
        return terms[0] - terms[1], xp.abs(terms[0]) + xp.abs(terms[1])
    minors = [
        e[1][1] * e[2][2] - e[1][2] * e[2][1],
        e[1][0] * e[2][2] - e[1][2] * e[2][0],
        e[1][0] * e[2][1] - e[1][1] * e[2][0],
    ]
    volume = e[0][0] * minors[0] - e[0][1] * minors[1] + e[0][2] * minors[2]
    a = [[xp.abs(v) for v in row] for row in e]  # the terms' sizes: the permanent of |e|
    size = (
        a[0][0] * (a[1][1] * a[2][2] + a[1][2] * a[2][1])
        + a[0][1] * (a[1][0] * a[2][2] + a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] + a[1][1] * a[2][0])
    )
    return volume, size
