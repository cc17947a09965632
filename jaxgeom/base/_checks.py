"""Host-boundary validation: clear errors that name the argument and the fix."""

from __future__ import annotations

import contextlib
import functools
import os
import sys
import types
import warnings
import weakref
from collections.abc import Iterable

import jax
import jax.numpy as jnp
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
    try:
        arr = np.asarray(points)
    except ValueError as err:
        raise TypeError(f"`{name}` must be a rectangular (N, d) array; got a ragged sequence ({err}).") from None
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


def real_array(value, name: str) -> np.ndarray:
    """A concrete numeric argument as numpy; TypeError for strings, objects, ragged lists, complex."""
    try:
        arr = np.asarray(value)
    except ValueError as err:  # ragged nested lists
        raise TypeError(f"`{name}` must be a rectangular numeric array; got a ragged sequence ({err}).") from None
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise TypeError(f"`{name}` must be numeric; got {type(value).__name__} with dtype {arr.dtype}.")
    if np.iscomplexobj(arr):
        raise TypeError(
            f"`{name}` must be real; got complex dtype {arr.dtype}. Pass `x.real` if the "
            "imaginary part is meant to be zero."
        )
    return arr


def check_number(value, name: str, *, low=None, high=None, strict: bool = False, hint: str = "") -> None:
    """A scalar parameter: real, finite, low <= value (low < value if `strict`) <= high.
    None and JAX tracers pass (checked only where the value is concrete)."""
    if value is None or isinstance(value, jax.core.Tracer):
        return
    arr = real_array(value, name)
    if arr.ndim != 0:
        raise ValueError(
            f"`{name}` must be a scalar; got shape {arr.shape}. For an ensemble of values, "
            "jax.vmap a function that builds the object from one value."
        )
    v = float(arr)
    below = low is not None and (v <= low if strict else v < low)
    if not np.isfinite(v) or below or (high is not None and v > high):
        rule = " and ".join(
            r
            for r in (
                f"{'>' if strict else '>='} {low}" if low is not None else "",
                f"<= {high}" if high is not None else "",
            )
            if r
        )
        raise ValueError(f"`{name}` must be a finite number{' ' + rule if rule else ''}{hint}; got {v:g}.")


def check_integer(value, name: str, low: int = 0) -> None:
    """A concrete int (not bool) >= `low`: TypeError for another type, ValueError below."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"`{name}` must be an int >= {low}; got {value!r} ({type(value).__name__}).")
    if value < low:
        raise ValueError(f"`{name}` must be an int >= {low}; got {value}.")


def check_nonnegative(value, name: str) -> None:
    """A physical parameter: a finite real scalar >= 0 (None and tracers pass)."""
    check_number(value, name, low=0)


def check_positive(value, name: str, hint: str = "") -> None:
    """A finite real scalar > 0 (None and tracers pass); `hint` follows the rule in the message."""
    check_number(value, name, low=0, strict=True, hint=hint)


def _concrete(value) -> bool:
    return value is not None and not callable(value) and not isinstance(value, (str, jax.core.Tracer))


def check_walker_array(value, name: str, shape: tuple, *, nonnegative: bool = False) -> None:
    """A per-walker input of a kernel: of `shape` (static, so traced values too), real and
    floating (a traced value: by its dtype), and with `nonnegative` (cell volumes) >= 0
    where finite."""
    if value is None or callable(value):
        return
    if isinstance(value, jax.core.Tracer):
        _check_real_dtype(value.dtype, name)
    else:
        value = real_array(value, name)
        if nonnegative and np.any(value < 0):
            rows = np.flatnonzero(value < 0) if value.ndim == 1 else np.zeros(0, int)
            raise ValueError(
                f"`{name}` must be >= 0 (cell volumes or weights); got negative entries, first "
                f"rows {list(map(int, rows[:5]))}."
            )
    if np.shape(value) != shape:
        raise ValueError(f"`{name}` must have shape {shape}, one entry per walker of `tess`; got {np.shape(value)}.")


def _check_real_dtype(dtype, name: str) -> None:
    if np.issubdtype(dtype, np.complexfloating):
        raise TypeError(
            f"`{name}` must be real; got complex dtype {dtype}. Pass `x.real` if the imaginary part "
            "is meant to be zero."
        )


def check_walker_mask(value, name: str, shape: tuple) -> None:
    """A per-walker bool mask (None: every walker) of `shape`, traced values by their dtype."""
    if value is None:
        return
    if not isinstance(value, jax.core.Tracer):
        if isinstance(value, str):
            raise TypeError(f"`{name}` must be a bool array of shape {shape}; got the string {value!r}.")
        value = real_array(value, name)
    if value.dtype != np.bool_:
        raise TypeError(
            f"`{name}` must be a bool mask; got dtype {value.dtype}. Compare to get one, e.g. "
            f"`{name}=tess.interior` or `values > 0`."
        )
    if np.shape(value) != shape:
        raise ValueError(f"`{name}` must have shape {shape}, one entry per walker; got {np.shape(value)}.")


def walker_values(value, name: str, *, nonnegative: bool = False):
    """A 1-D per-walker array of real values for the functions that take no graph
    (checked where concrete; a traced value by its rank and dtype); returned as a JAX array."""
    if isinstance(value, str):
        raise TypeError(f"`{name}` must be a 1-D array of per-walker values; got the string {value!r}.")
    arr = value if isinstance(value, jax.core.Tracer) else real_array(value, name)
    if np.ndim(arr) != 1:
        raise ValueError(f"`{name}` must be 1-D, one value per walker (N,); got shape {np.shape(arr)}.")
    check_walker_array(arr, name, np.shape(arr), nonnegative=nonnegative)
    return jnp.asarray(arr, dtype=None if np.issubdtype(arr.dtype, np.floating) else float)


def check_metric_array(metric, n: int, d: int) -> None:
    """A concrete (N, d, d) metric: real, finite, symmetric to rounding and positive definite."""
    if not _concrete(metric) or _already_checked(metric):
        return
    g = real_array(metric, "metric")
    if g.shape != (n, d, d):
        return  # the kernel's own shape message follows
    nonfinite = ~np.isfinite(g).all(axis=(1, 2))
    if nonfinite.any():
        rows = np.flatnonzero(nonfinite)
        raise ValueError(
            f"`metric` must be finite; {rows.size} walker(s) have NaN or inf entries, first rows "
            f"{rows[:5].tolist()}. (The emergent metric of a walker without neighbours is NaN: give it "
            "neighbours, e.g. a larger k, or a metric of its own.)"
        )
    asym, indefinite = metric_defect_masks(g, np)
    if asym.any():
        rows = np.flatnonzero(asym)
        raise ValueError(
            f"`metric` must be symmetric; {rows.size} walker(s) are not, first rows "
            f"{rows[:5].tolist()}. Symmetrise with 0.5 * (g + g.swapaxes(-1, -2))."
        )
    if indefinite.any():
        rows = np.flatnonzero(indefinite)
        raise ValueError(
            f"`metric` must be positive definite; {rows.size} walker(s) have an eigenvalue <= 0, "
            f"first rows {rows[:5].tolist()}. Floor the spectrum, e.g. "
            "jaxgeom.hessian_metric(V, eps_sigma) for a Hessian."
        )
    _remember_checked(metric)


# JAX arrays are immutable: one that passed is not checked again (the check is O(N) on the
# host and costs as much as a kernel, bench/README.md). Keyed by id, dropped when the array is freed.
_CHECKED: dict[int, weakref.ref] = {}


def _already_checked(value) -> bool:
    ref = _CHECKED.get(id(value))
    return ref is not None and ref() is value


def _remember_checked(value) -> None:
    if isinstance(value, jax.Array):
        key = id(value)
        _CHECKED[key] = weakref.ref(value, functools.partial(_forget, key))


def _forget(key: int, _reference) -> None:
    _CHECKED.pop(key, None)


def metric_defect_masks(g, xp):
    """(asymmetric, not positive definite), each (N,) bool over the finite rows of an
    (N, d, d) metric `g`; rows with a NaN or inf entry are in neither. `xp` is numpy (the
    host check) or jax.numpy (the jittable `jaxgeom.metric_defects`). Symmetric means to
    100 eps of the row's largest entry; definiteness from Sylvester's leading minors up to
    d = 3 (elementwise over (N,) columns), eigenvalues above."""
    wide = xp.float64 if xp is np else g.dtype
    eps = float(xp.finfo(g.dtype if xp.issubdtype(g.dtype, xp.floating) else wide).eps)
    # whole-array reductions, not one op per entry: XLA's compile time grows steeply with
    # the number of ops (d^2 of them took 40 s to compile at d = 35)
    g = g.astype(wide)
    finite = xp.all(xp.isfinite(g), axis=(-2, -1))
    scale = xp.max(xp.abs(g), axis=(-2, -1))
    skew = xp.max(xp.abs(g - g.swapaxes(-1, -2)), axis=(-2, -1))
    # definiteness of g / scale: the minors of g itself overflow or underflow (g = 1e-200 I)
    unit = xp.where(scale > 0, scale, 1.0)
    return finite & (skew > 100 * eps * scale), finite & ~_positive_definite(g / unit[:, None, None], xp)


def _positive_definite(g, xp):
    """(N,) bool: Sylvester's leading minors of (N, d, d) `g` up to d = 3, eigenvalues above
    (NaN rows come out False and are masked by the caller)."""
    d = g.shape[-1]
    if d > 3:
        sym = xp.nan_to_num(0.5 * (g + g.swapaxes(-1, -2)))
        return xp.linalg.eigvalsh(sym)[:, 0] > 0
    c = {(i, j): g[:, i, j] for i in range(d) for j in range(d)}
    ok = c[0, 0] > 0
    if d >= 2:
        ok &= c[0, 0] * c[1, 1] - c[0, 1] * c[1, 0] > 0
    if d == 3:
        det = (
            c[0, 0] * (c[1, 1] * c[2, 2] - c[1, 2] * c[2, 1])
            - c[0, 1] * (c[1, 0] * c[2, 2] - c[1, 2] * c[2, 0])
            + c[0, 2] * (c[1, 0] * c[2, 1] - c[1, 1] * c[2, 0])
        )
        ok &= det > 0
    return ok


def check_min_points(n: int, minimum: int, name: str, why: str) -> None:
    if n < minimum:
        raise ValueError(f"`{name}` has {n} walker(s); {why} needs at least {minimum}.")


def columns(points: np.ndarray) -> np.ndarray:
    """(d, N) float64 copy of (N, d) points: numpy reduces a contiguous row 40x faster than
    a strided (N, 2) column (0.43 ms for min(axis=0) at N = 1e4)."""
    return np.ascontiguousarray(np.asarray(points, np.float64).T)


def mean_spacing(points: np.ndarray) -> float:
    """Mean walker spacing (bounding-box volume / N)^(1/d), over the axes of non-zero extent."""
    cols = columns(points)
    return spacing_of_box(cols.min(axis=1), cols.max(axis=1), len(points))


def spacing_of_box(lower: np.ndarray, upper: np.ndarray, n: int) -> float:
    """`mean_spacing` of n walkers whose bounding box is (lower, upper)."""
    extent = np.asarray(upper, np.float64) - np.asarray(lower, np.float64)
    d = extent.size
    extent = extent[extent > 0]
    return float(np.exp(np.mean(np.log(extent)))) / n ** (1.0 / d) if extent.size else 0.0


def check_representable_spacing(points: np.ndarray, dtype, name: str = "points") -> None:
    """Cell volumes and circumcentres multiply up to four lengths (spacing^4): reject swarms
    whose mean spacing puts that outside the dtype's normal range (float32: about 1e-9 to
    4e9), with the fix, instead of returning zero or infinite volumes."""
    refuse_unrepresentable_spacing(mean_spacing(points), dtype, name)


def refuse_unrepresentable_spacing(spacing: float, dtype, name: str = "points") -> None:
    """`check_representable_spacing` of a swarm whose mean spacing is `spacing`."""
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


RESOLUTION_LIMIT = 1e-3  # rounding of the positions over the mean spacing that is refused


def check_resolved_positions(points: np.ndarray, dtype, name: str = "points") -> None:
    """Refuse walkers that `dtype` cannot resolve where they are: far from the origin its
    rounding eps |x| reaches the spacing, and walkers collapse onto a few distinct values
    (float32, 5000 walkers in [1e6, 1e6 + 1]^2: 17 distinct x, tier-2 volumes summing to 1.003
    instead of 0.875; at an offset of 1e3 the rounding is 0.8% of the spacing and one cell came
    out negative; at 1e2, 0.08%, the volumes agree with float64 to 5 digits)."""
    refuse_unresolved_positions(mean_spacing(points), float(np.max(np.abs(points))), dtype, name)


def refuse_unresolved_positions(spacing: float, largest: float, dtype, name: str = "points") -> None:
    """`check_resolved_positions` of a swarm of mean spacing `spacing` whose largest |x| is `largest`."""
    if spacing == 0.0:
        return
    rounding = float(np.finfo(dtype).eps) * largest
    if rounding > RESOLUTION_LIMIT * spacing:
        fix = " or use float64 (jax.config.update('jax_enable_x64', True))" if np.dtype(dtype) == np.float32 else ""
        raise ValueError(
            f"`{name}` cannot be resolved in {np.dtype(dtype).name}: at |x| up to {largest:.3g} its "
            f"rounding is {rounding:.3g}, {rounding / spacing:.2g} of the mean walker spacing {spacing:.3g} (at most "
            f"{RESOLUTION_LIMIT:g}); walkers collapse and cell volumes lose their sign. Centre the walkers "
            f"(points - points.mean(axis=0)){fix}."
        )


def flat_word(d: int, other: str = "on a hyperplane") -> str:
    """What walkers spanning fewer than d dimensions are: collinear (2D), coplanar (3D), `other`."""
    return {2: "collinear", 3: "coplanar"}.get(d, other)


def thinness(points: np.ndarray) -> float | None:
    """RMS distance of the walkers from their best-fit hyperplane over their extent (their
    smallest singular value, centred and scaled to unit extent, over sqrt(N)); None when a
    cheap (d, d) Gram matrix already shows the set is not thin (the common case) or the
    extent is 0. Singular values of the cloud itself: no squaring of its condition number."""
    x = columns(points)
    extent = float(np.max(x.max(axis=1) - x.min(axis=1)))
    if extent == 0:
        return None
    centred = (x - x.mean(axis=1, keepdims=True)) / extent
    ev = np.linalg.eigvalsh(centred @ centred.T)
    if ev[0] > 1e-8 * ev[-1]:
        return None
    return float(np.linalg.svd(centred, compute_uv=False)[-1]) / np.sqrt(x.shape[1])


def check_full_rank(points: np.ndarray, name: str = "points") -> None:
    """Reject point sets that span fewer than d dimensions (collinear in 2D, coplanar in 3D).

    Scale-relative: the walkers are scaled to a unit box and centred on their mean first (no overflow
    for huge coordinates), and a thin but genuine sample (a strip [0, 1] x [0, 1e-7]) passes.
    A set is degenerate when its thinnest direction is at the rounding level of the input
    coordinates (their float64 resolution at the largest |x|).
    """
    x = columns(points)
    extent = float(np.max(x.max(axis=1) - x.min(axis=1)))
    if extent > 0:
        thin = thinness(points)
        rounding = 64.0 * np.finfo(np.float64).eps * max(float(np.max(np.abs(x))) / extent, 1.0)
        if thin is None or thin > rounding:
            return
    d = x.shape[0]
    raise ValueError(
        f"`{name}` is degenerate: all walkers are {flat_word(d, f'in a subspace of dimension < {d}')}, so there "
        f"is no {d}-dimensional tessellation. Spread the walkers out, or drop the flat coordinate(s)."
    )


def host_box(box, points: np.ndarray, *, periodic: bool) -> np.ndarray | None:
    """Validate `box=(lower, upper)` and that every walker lies inside it."""
    if box is None:
        if periodic:
            raise ValueError("`periodic=True` needs `box=(lower, upper)`: the periodic cell is not known otherwise.")
        return None
    reject_tracer(box, "box", "jaxgeom")
    d = points.shape[1]
    if isinstance(box, str):
        raise TypeError(
            f"`box` must be (lower, upper) with scalars or length-{d} vectors, e.g. box=(0.0, 1.0); "
            f"got the string {box!r}."
        )
    arr = real_array(box, "box").astype(np.float64)
    if arr.ndim == 1 and arr.size == 2:
        arr = np.repeat(arr[:, None], d, axis=1)
    if arr.shape != (2, d):
        raise ValueError(f"`box` must be (lower, upper) with scalars or length-{d} vectors; got shape {arr.shape}.")
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


def refuse_unused(arguments: dict, *, of: str, chosen: str, why: str = "") -> None:
    """Refuse the `arguments` (name -> value, None when not given) that only `of` uses (e.g.
    "method='heat'") when the caller chose `chosen`, which ignores them; `why` says how."""
    given = [name for name, value in arguments.items() if value is not None]
    if given:
        raise ValueError(
            f"{', '.join(f'`{g}`' for g in given)} of {of} given with {chosen}, which does not use "
            f"them{why}. Drop them, or use {of}."
        )


def check_choice(value: str, name: str, valid: Iterable[str]) -> str:
    valid = tuple(valid)
    if value not in valid:
        raise ValueError(f"unknown {name} {value!r}; valid values are {', '.join(map(repr, valid))}.")
    return value


@functools.cache
def _library_dirs() -> tuple[str, ...]:
    import equinox
    import jaxtyping

    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))  # the jaxgeom package
    dirs = [os.path.dirname(os.path.abspath(str(m.__file__))) for m in (jax, equinox, jaxtyping)] + [here]
    return tuple(d + os.sep for d in dirs)


_STDLIB_WRAPPERS = (os.path.abspath(contextlib.__file__), os.path.abspath(functools.__file__))


def warn_at_caller(message: str, category: type[Warning] = UserWarning) -> None:
    """`warnings.warn` attributed to the first frame outside jaxgeom, JAX, equinox and jaxtyping:
    the user's own line, however deep the library's call (decorators, jit tracing) runs."""
    inside, level = _library_dirs(), 2
    frame: types.FrameType | None = sys._getframe(1)
    while frame is not None and (
        os.path.abspath(frame.f_code.co_filename).startswith(inside)
        or os.path.abspath(frame.f_code.co_filename) in _STDLIB_WRAPPERS
    ):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level)
