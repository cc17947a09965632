"""Host-boundary validation: clear errors that name the argument and the fix."""

from __future__ import annotations

from collections.abc import Iterable

import jax
import numpy as np


def reject_tracer(value, name: str, func: str) -> None:
    if isinstance(value, jax.core.Tracer):
        raise TypeError(
            f"{func} runs on the host (scipy Qhull) and cannot be traced: `{name}` is a "
            f"JAX tracer. Call {func} outside jax.jit/vmap/grad and pass concrete arrays."
        )


def host_points(points, name: str = "points", *, func: str = "jaxgeom") -> np.ndarray:
    """Validate an (N, d) float array of finite coordinates and return it as numpy."""
    reject_tracer(points, name, func)
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 1:
        raise ValueError(
            f"`{name}` must have shape (N, d) with one row per walker; got shape {arr.shape}. "
            "Reshape with points.reshape(N, d)."
        )
    if not np.issubdtype(arr.dtype, np.floating):
        raise TypeError(
            f"`{name}` must be a float array (float32 or float64); got dtype {arr.dtype}. "
            "Convert with points.astype(float)."
        )
    if not np.isfinite(arr).all():  # whole-array test first: the per-row one is 40x slower
        rows = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        raise ValueError(
            f"`{name}` has NaN or inf coordinates in {rows.size} row(s), first rows {rows[:5].tolist()}. "
            "Remove or repair those walkers."
        )
    return arr


def check_nonnegative(value, name: str) -> None:
    """A physical parameter that must be finite and >= 0 (tracers pass)."""
    if value is None or isinstance(value, jax.core.Tracer):
        return
    arr = np.asarray(value)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError(f"`{name}` must be a finite number >= 0; got {value}.")


def check_positive(value, name: str, hint: str = "") -> None:
    """A parameter that must be > 0 (None and tracers pass); `hint` follows the rule in the message."""
    if value is not None and not isinstance(value, jax.core.Tracer) and not np.all(np.asarray(value) > 0):
        raise ValueError(f"`{name}` must be > 0{hint}; got {value}.")


def check_min_points(n: int, minimum: int, name: str, why: str) -> None:
    if n < minimum:
        raise ValueError(f"`{name}` has {n} walker(s); {why} needs at least {minimum}.")


def mean_spacing(points: np.ndarray) -> float:
    """Mean walker spacing (bounding-box volume / N)^(1/d), over the axes of non-zero extent."""
    n, d = points.shape
    extent = np.ptp(np.asarray(points, np.float64), axis=0)
    extent = extent[extent > 0]
    return float(np.exp(np.mean(np.log(extent)))) / n ** (1.0 / d) if extent.size else 0.0


def check_representable_spacing(points: np.ndarray, dtype, name: str = "points") -> None:
    """Cell volumes and circumcentres multiply up to four lengths (spacing^4): reject swarms
    whose mean spacing puts that outside the dtype's normal range (float32: about 1e-9 to
    4e9), with the fix, instead of returning zero or infinite volumes."""
    spacing = mean_spacing(points)
    if spacing == 0.0:
        return
    info = np.finfo(dtype)
    lo, hi = 10.0 * float(info.tiny) ** 0.25, 0.1 * float(info.max) ** 0.25
    if not lo <= spacing <= hi:
        raise ValueError(
            f"`{name}` has a mean spacing of {spacing:.3g}, outside what {np.dtype(dtype).name} cell volumes "
            f"and curvature can represent (their products reach spacing^4: spacings in [{lo:.1g}, {hi:.1g}]). "
            "Rescale the positions (e.g. x / spacing) or use float64 (jax.config.update('jax_enable_x64', True))."
        )


def check_full_rank(points: np.ndarray, name: str = "points") -> None:
    """Reject point sets that span fewer than d dimensions (collinear in 2D, coplanar in 3D).

    Scale-relative: the walkers are scaled to a unit box and centred on their mean first (no overflow
    for huge coordinates), and a thin but genuine sample (a strip [0, 1] x [0, 1e-7]) passes.
    A set is degenerate when its thinnest direction is at the rounding level of the input
    coordinates (their float64 resolution at the largest |x|).
    """
    x = np.asarray(points, np.float64)
    lo, hi = x.min(axis=0), x.max(axis=0)
    extent = float(np.max(hi - lo))
    if extent > 0:
        centred = (x - 0.5 * (lo + hi)) / extent
        centred -= centred.mean(axis=0)  # the rank of the affine hull needs the mean, not the midrange
        gram = centred.T @ centred
        ev = np.linalg.eigvalsh(gram)
        if ev[0] > 1e-8 * ev[-1]:  # the common case, decided by a cheap (d, d) Gram matrix
            return
        # Thin sets: singular values of the centred cloud itself (no squaring of the condition number).
        sv = np.linalg.svd(centred, compute_uv=False)
        rounding = 64.0 * np.finfo(np.float64).eps * max(float(np.max(np.abs(x))) / extent, 1.0)
        if sv[-1] > rounding * np.sqrt(len(x)):
            return
    d = x.shape[1]
    what = {2: "collinear", 3: "coplanar"}.get(d, f"in a subspace of dimension < {d}")
    raise ValueError(
        f"`{name}` is degenerate: all walkers are {what}, so there is no {d}-dimensional "
        "tessellation. Spread the walkers out, or drop the flat coordinate(s)."
    )


def host_box(box, points: np.ndarray, *, periodic: bool) -> np.ndarray | None:
    """Validate `box=(lower, upper)` and that every walker lies inside it."""
    if box is None:
        if periodic:
            raise ValueError(
                "`periodic=True` needs `box=(lower, upper)`: the periodic cell is not known otherwise."
            )
        return None
    reject_tracer(box, "box", "jaxgeom")
    d = points.shape[1]
    arr = np.asarray(box, dtype=np.float64)
    if arr.ndim == 1 and arr.size == 2:
        arr = np.repeat(arr[:, None], d, axis=1)
    if arr.shape != (2, d):
        raise ValueError(
            f"`box` must be (lower, upper) with scalars or length-{d} vectors; got shape {arr.shape}."
        )
    if not np.isfinite(arr).all() or np.any(arr[1] <= arr[0]):
        raise ValueError(f"`box` must satisfy lower < upper in every coordinate; got lower={arr[0]}, upper={arr[1]}.")
    upper_ok = points < arr[1] if periodic else points <= arr[1]
    outside = ~np.all((points >= arr[0]) & upper_ok, axis=1)
    if outside.any():
        rows = np.flatnonzero(outside)
        interval = "[lower, upper)" if periodic else "[lower, upper]"
        raise ValueError(
            f"{rows.size} walker(s) lie outside `box` {interval}, first rows {rows[:5].tolist()}. "
            "Enlarge the box, or wrap periodic coordinates with lower + (x - lower) % (upper - lower)."
        )
    return arr


def check_choice(value: str, name: str, valid: Iterable[str]) -> str:
    valid = tuple(valid)
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid values are {', '.join(map(repr, valid))}.")
    return value
