"""`jaxgeom.analyze_trajectory`: the observables of a recorded trajectory, frame by frame.

Each analysed frame becomes the state a swarm would have entering that step (positions,
velocities, fitness, clone parents, its graph), and the observables of `simulate`'s table
are measured on it by the same code (`_observables.observe_state`); consecutive analysed
frames give the expansion and the scutoids. Frames are read one at a time (memory does not
grow with T), the graphs keep one capacity bucket (grown by `simulate`'s rule when a frame
needs more: one recompilation), and the host triangulation of the next frame overlaps the
kernels of the current one (JAX dispatches them asynchronously).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..base._checks import check_choice
from ..base._h5md import H5MD_SUFFIXES, H5MDTrajectory
from ..base._progress import check_progress, close_bar, open_bar, raise_if_interrupted
from ..tessellation._delaunay import build_delaunay
from ..tessellation._knn import knn_graph
from ._dynamics import SwarmParams, SwarmState
from ._history import _bulk_gap
from ._observables import ALL_OBSERVABLES, OBSERVABLE_TABLE, observe_state, prepare_scutoid_trace
from ._rebuild import capacity_with_headroom, growing_capacity, pad_to_capacity
from ._swarm_init import fresh_state

NEVER = {
    "nu": "a parameter of the simulation that wrote the trajectory, not of its frames",
    "eps_sigma": "a parameter of the simulation that wrote the trajectory, not of its frames",
}


class TrajectoryInterrupted(KeyboardInterrupt):
    """Ctrl-C during `analyze_trajectory`: `history` holds the frames analysed before it."""

    def __init__(self, history: dict, frames: int):
        super().__init__(f"analyze_trajectory: interrupted after {frames} frames")
        self.history, self.frames = history, frames


class _Source:
    """Frames from an array (T, N, d), a .npy (memory-mapped), an .npz, an H5MD file or an
    iterable of (N, d) arrays: `frame(t)` dicts, `n_frames` and `dim` (None for an iterable),
    metadata."""

    def __init__(self, source):
        self.name, self.box, self.periodic, self.steps, self.times, self._close = (
            "frames",
            None,
            False,
            None,
            None,
            None,
        )
        self.extra: dict = {}
        if isinstance(source, (str, Path)):
            self._from_file(Path(source))
        elif isinstance(source, (np.ndarray, jax.Array)):
            self._from_array(np.asarray(source) if isinstance(source, jax.Array) else source, "frames")
        elif isinstance(source, Iterable):
            self.n_frames, self._iter, self.dim = None, iter(source), None
        else:
            raise TypeError(
                "`source` must be an array (T, N, d), a path to a .npy, .npz or H5MD file, or an "
                f"iterable of (N, d) arrays; got {type(source).__name__}."
            )

    def _from_array(self, array, name):
        if array.ndim != 3:
            raise ValueError(f"{name}: positions must be (frames, N, d); got shape {array.shape}.")
        self.positions, self.n_frames, self.name, self.dim = array, array.shape[0], name, array.shape[2]

    def _from_file(self, path: Path):
        if not path.exists():
            raise ValueError(f"{path}: no such file.")
        suffix = path.suffix.lower()
        if suffix == ".npy":
            self._from_array(np.load(path, mmap_mode="r"), str(path))
        elif suffix == ".npz":
            data = np.load(path)
            if "positions" not in data:
                raise ValueError(
                    f"{path}: an .npz trajectory needs an array named 'positions' (T, N, d); it holds "
                    f"{', '.join(data.files) or 'nothing'}."
                )
            self._from_array(data["positions"], f"{path}:positions")
            for key in ("fitness", "velocities", "parents"):
                if key in data:
                    self.extra[key] = (data[key], f"{path}:{key}")
            if "box" in data:
                box = np.asarray(data["box"], float)
                self.box = (box[0], box[1])
            self.periodic = bool(data["periodic"]) if "periodic" in data else False
            self.times = np.asarray(data["times"], float) if "times" in data else None
            unknown = set(data.files) - {"positions", "fitness", "velocities", "parents", "box", "periodic", "times"}
            if unknown:
                raise ValueError(
                    f"{path}: unknown arrays {sorted(unknown)}; a trajectory .npz holds positions and "
                    "optionally fitness, velocities, parents, box, periodic, times."
                )
        elif suffix in H5MD_SUFFIXES:
            h5 = H5MDTrajectory(path)
            self.name, self.n_frames, self._h5, self._close, self.dim = str(path), h5.n_frames, h5, h5.close, h5.d
            self.box, self.periodic, self.steps, self.times = h5.box, h5.periodic, h5.steps, h5.times
        else:
            raise ValueError(
                f"{path}: unknown extension {suffix!r}; give a .npy, .npz or H5MD ({', '.join(H5MD_SUFFIXES)}) file."
            )

    def frame(self, t: int) -> dict:
        if hasattr(self, "_h5"):
            return self._h5.frame(t)
        out = {"positions": np.asarray(self.positions[t])}
        for key, (array, _) in self.extra.items():
            out[key] = np.asarray(array[t])
        return out

    def close(self):
        if self._close is not None:
            self._close()


def _check_frame(frame: dict, name: str, t: int, shape) -> np.ndarray:
    x = np.asarray(frame["positions"])
    where = f"{name}, frame {t}"
    if x.ndim != 2 or not np.issubdtype(x.dtype, np.number):
        raise ValueError(f"{where}: positions must be a numeric (N, d) array; got {x.dtype} {x.shape}.")
    if shape is not None and x.shape != shape:
        raise ValueError(
            f"{where}: positions have shape {x.shape}, the first frame {shape}; every frame needs the "
            "same walkers (N) and dimension."
        )
    bad = ~np.isfinite(x).all(axis=1)
    if bad.any():
        raise ValueError(
            f"{where}: {int(bad.sum())} walker(s) have NaN or inf coordinates (first: walker {int(np.argmax(bad))})."
        )
    n = x.shape[0]
    for key, want in (("fitness", (n,)), ("velocities", x.shape), ("parents", (n,))):
        if key in frame and np.shape(frame[key]) != want:
            raise ValueError(f"{where}: {key} has shape {np.shape(frame[key])}; the positions need {want}.")
    if "velocities" in frame and not np.isfinite(frame["velocities"]).all():
        raise ValueError(f"{where}: velocities have NaN or inf entries.")
    if "parents" in frame:
        p = np.asarray(frame["parents"])
        if not np.issubdtype(p.dtype, np.integer) or p.min(initial=0) < 0 or p.max(initial=0) >= n:
            raise ValueError(f"{where}: parents must be integer walker indices in [0, {n}).")
    return x


def _per_frame(array, name: str, n_frames):
    """A per-frame argument (T, ...) checked against the source's frame count."""
    if array is None:
        return None
    array = np.asarray(array) if not isinstance(array, np.ndarray) else array
    if n_frames is not None and array.shape[0] != n_frames:
        raise ValueError(f"`{name}` has {array.shape[0]} frames; the trajectory has {n_frames}.")
    return array


def _determined(has: set, landscape, params: SwarmParams, graph: str) -> dict:
    """{observable: why it cannot be measured} for every observable the data do not determine."""
    missing = dict(NEVER)
    for name in ("mean_fitness", "best_fitness"):
        if "fitness" not in has:
            missing[name] = "needs fitness values: pass fitness= (T, N) or a landscape"
    if "velocities" not in has:
        missing["velocity_variance"] = missing["degree_weighted_variance"] = "needs velocities= (T, N, d)"
    elif params.weights.startswith("metric") and landscape is None:
        missing["degree_weighted_variance"] = f"its '{params.weights}' weights need the landscape's Hessian metric"
    if "parents" not in has:
        missing["n_clones"] = "needs the clone parents (parents= (T, N))"
    if landscape is None:
        missing["mean_metric_curvature"] = "needs a landscape (the curvature of its Hessian metric)"
        missing["mean_ricci"] = missing["ricci_resolution"] = (
            "without a landscape the metric is Euclidean, which is flat (R = 0 exactly); a landscape gives its "
            "Hessian metric"
        )
    if graph == "knn":
        for name, row in OBSERVABLE_TABLE.items():
            if row.geometric:
                missing[name] = "needs Voronoi cells (a Delaunay graph), not a k-NN graph"
    return missing


def _default_observe(missing: dict) -> tuple[str, ...]:
    return tuple(name for name in ALL_OBSERVABLES if name not in missing and name != "mean_metric_curvature")


def _graph(x, graph, k, box, periodic, triangulator, capacity):
    """(graph, capacity, grew) of one frame at the run's capacity, grown when it does not fit."""
    if graph == "knn":
        return knn_graph(x, k, box=box, periodic=periodic), None, False
    if capacity is not None:
        floor = growing_capacity(capacity, x.shape[1], len(x))
        tess = build_delaunay(x, box=box, periodic=periodic, capacity=floor, triangulator=triangulator)[0]
        return tess, tess.capacity, tess.capacity != floor.floor
    fresh = build_delaunay(x, box=box, periodic=periodic, triangulator=triangulator)[0]
    grown = capacity_with_headroom(fresh)
    return pad_to_capacity(fresh, grown), grown, False


def _first_state(x, tess, dtype) -> SwarmState:
    """The state that carries the frames' graphs; each frame puts its own data in place."""
    xj = jnp.asarray(x, dtype)
    zeros = jnp.zeros_like(xj)
    return fresh_state(xj, zeros, jnp.zeros(xj.shape[0], dtype), zeros, jax.random.PRNGKey(0), tess)


# jax.jit, not eqx.filter_jit: its call returns at once (eqx.filter_jit's blocks until the
# kernels are done), so the host reads and triangulates the next frame while they run.
@functools.partial(jax.jit, static_argnames=("fitness", "observe"))
def _observe_frame(fitness, params, state, frame_data, step, dt, observe):
    """The state of one frame (its data in place) observed: (state, {name: scalar})."""
    positions, velocities, values, parents = frame_data
    n = positions.shape[0]
    if values is None:  # a landscape: evaluated here, in the compiled program
        values = jax.vmap(fitness)(positions).astype(positions.dtype)
    alive = jnp.isfinite(values)
    cloned = parents != jnp.arange(n, dtype=jnp.int32)
    state = eqx.tree_at(
        lambda s: (s.positions, s.velocities, s.fitness, s.alive, s.cloned, s.step, s.scutoid_trace.parents),
        state,
        (positions, velocities, values, alive, cloned, step, parents),
    )
    params = eqx.tree_at(lambda p: p.dt, params, dt)
    return observe_state(fitness, params, state, jnp.asarray(1.0, positions.dtype), observe)


def _compose(parents_between: list, n: int) -> np.ndarray:
    """The clone parents from one analysed frame to the next across the skipped frames."""
    total = np.arange(n)
    for p in parents_between:  # frame by frame: walker i now came from p[i] one frame before
        total = total[p]
    return total


def analyze_trajectory(
    source,
    *,
    fitness=None,
    landscape: Callable | None = None,
    velocities=None,
    parents=None,
    times=None,
    dt: float | None = None,
    box=None,
    periodic: bool | None = None,
    params: SwarmParams | None = None,
    observe=None,
    every: int = 1,
    start: int = 0,
    stop: int | None = None,
    graph: str = "delaunay",
    k: int = 12,
    triangulator: str = "auto",
    spectral_gap_every: int = 0,
    dtype=None,
    progress=False,
) -> dict:
    """The observables of `jaxgeom.simulate`'s history, measured on a recorded trajectory.

    **Arguments:**

    - `source`: the frames: an array (T, N, d), a path to a `.npy` (memory-mapped), an `.npz`
      (arrays `positions` and optionally `fitness`, `velocities`, `parents`, `box` (2, d),
      `periodic`, `times`) or an H5MD file (`.h5md`, `.h5`, `.hdf5`: positions, box,
      velocities and jaxgeom's `fitness` and `parents`, steps and times), or any iterable
      of (N, d) arrays.
    - `fitness`: (T, N) V at the walkers; or `landscape`: a JAX function x (d,) -> V(x),
      evaluated at every frame (and giving the curvature observables the Hessian metric
      g = floor(H) + eps_Sigma I of `params`; without it they use the Euclidean metric).
    - `velocities` (T, N, d), `parents` (T, N) (each walker's clone parent in the step that led
      to the frame): per-frame data besides the source's (an argument and the source's own
      data for the same thing are refused together).
    - `times` (T,) or `dt`: the frames' times (default: the file's, else one per frame), used by
      the expansion d ln V / dt.
    - `box`, `periodic`: the box (`jaxgeom.delaunay`'s), default the file's.
    - `params`: `SwarmParams` for the observables that read them (eps_Sigma and the floor of the
      Hessian metric, the viscous weights of "degree_weighted_variance").
    - `observe`: names from `ALL_OBSERVABLES`; default every one the data determine (the opt-in
      "mean_metric_curvature" only when named). A name the data cannot give is refused with
      the reason.
    - `every`, `start`, `stop`: analyse frames start, start + every, ... < stop (clone parents
      are composed over the skipped frames).
    - `graph`, `k`, `triangulator`: "delaunay" (2D, 3D) or "knn" (any d, `k` neighbours).
    - `spectral_gap_every`: M > 0 records the spectral gap every M analysed frames.
    - `dtype`: float32 or float64 (default: JAX's default float).
    - `progress`: a progress bar, as in `simulate`.

    **Returns:**

    A history dict like `simulate`'s: each observable (T',); `frame` (the frame indices),
    `step` and `time` (T',); `spectral_gap_step` (index into the observables), `spectral_gap`,
    `spectral_components`, `spectral_gap_rounding`; `n_reallocations`; `seconds_rebuild`
    (triangulation) and `seconds_steps` (the rest); `unavailable`: {observable: why the data
    do not determine it}. Ctrl-C raises `TrajectoryInterrupted` carrying the history of the
    frames done.
    """
    check_choice(graph, "graph", ("delaunay", "knn"))
    check_progress(progress)
    for name, value in (("every", every), ("start", start)):
        if not isinstance(value, (int, np.integer)) or value < (1 if name == "every" else 0):
            raise ValueError(f"`{name}` must be an integer >= {1 if name == 'every' else 0}; got {value!r}.")
    if fitness is not None and landscape is not None:
        raise ValueError("give `fitness` (values per frame) or `landscape` (a function to evaluate), not both.")
    if landscape is not None and not callable(landscape):
        raise TypeError("`landscape` must be a JAX function x (d,) -> V(x).")
    if times is not None and dt is not None:
        raise ValueError("give `times` or `dt`, not both.")
    params = SwarmParams() if params is None else params
    if not isinstance(params, SwarmParams):
        raise TypeError("`params` must be a jaxgeom.SwarmParams.")
    owned = not isinstance(source, _Source)  # the command line passes the trajectory it opened
    src = _Source(source) if owned else source
    try:
        return _analyze(
            src,
            fitness,
            landscape,
            velocities,
            parents,
            times,
            dt,
            box,
            periodic,
            params,
            observe,
            every,
            start,
            stop,
            graph,
            k,
            triangulator,
            spectral_gap_every,
            dtype,
            progress,
        )
    finally:
        if owned:
            src.close()


def _analyze(
    src,
    fitness,
    landscape,
    velocities,
    parents,
    times,
    dt,
    box,
    periodic,
    params,
    observe,
    every,
    start,
    stop,
    graph,
    k,
    triangulator,
    gap_every,
    dtype,
    progress,
):
    n_frames = src.n_frames
    supplied = {
        "fitness": _per_frame(fitness, "fitness", n_frames),
        "velocities": _per_frame(velocities, "velocities", n_frames),
        "parents": _per_frame(parents, "parents", n_frames),
    }
    file_has = set(src.extra) | set(getattr(getattr(src, "_h5", None), "has", ()))
    file_has = {{"velocity": "velocities"}.get(e, e) for e in file_has}
    for key, value in supplied.items():
        if value is not None and key in file_has:
            raise ValueError(f"{src.name} already holds {key}; the `{key}` argument would replace them. Give one.")
    has = file_has | {key for key, value in supplied.items() if value is not None}
    if landscape is not None:
        has.add("fitness")
    missing = _determined(has, landscape, params, graph)
    if observe is None:
        observe = _default_observe(missing)
    observe = (observe,) if isinstance(observe, str) else tuple(observe)
    for name in observe:
        check_choice(name, "observable", ALL_OBSERVABLES)
        if name in missing:
            raise ValueError(f"analyze_trajectory: {name!r} cannot be measured on {src.name}: {missing[name]}.")
    box = src.box if box is None else box
    periodic = src.periodic if periodic is None else periodic
    if periodic and box is None:
        raise ValueError("`periodic=True` needs a box.")
    dtype = jnp.zeros(0).dtype if dtype is None else jnp.dtype(dtype)
    stop = n_frames if stop is None else (min(stop, n_frames) if n_frames is not None else stop)
    if n_frames is not None and start >= n_frames:
        raise ValueError(f"`start` = {start} is past the last of the {n_frames} frames of {src.name}.")
    frame_times = _times(src, times, dt, n_frames)
    wanted = range(start, stop if stop is not None else 2**62, every)

    series, gaps, kept, indices, seconds = {name: [] for name in observe}, [], [], [], {"rebuild": 0.0, "steps": 0.0}
    state, capacity, reallocations, shape, between = None, None, 0, None, []
    bar, owned = open_bar(progress, len(wanted) if n_frames is not None else None, "analyze_trajectory")
    previous_time, done = None, 0
    try:
        for t, frame in _frames(src, supplied, start, stop):
            raise_if_interrupted()
            if "parents" in frame:
                between.append(np.asarray(frame["parents"]))
            if (t - start) % every:
                continue
            t0 = time.perf_counter()
            x = _check_frame(frame, src.name, t, shape)
            shape = x.shape
            if box is not None and not periodic:
                lo, hi = (np.broadcast_to(np.asarray(b, float), (x.shape[1],)) for b in box)
                outside = np.any((x < lo) | (x > hi), axis=1)
                if outside.any():
                    raise ValueError(
                        f"{src.name}, frame {t}: {int(outside.sum())} walker(s) lie outside the box "
                        f"(first: walker {int(np.argmax(outside))} at {x[np.argmax(outside)]})."
                    )
            try:
                tess, capacity, grew = _graph(x, graph, k, box, periodic, triangulator, capacity)
            except ValueError as err:
                raise ValueError(f"{src.name}, frame {t}: the graph could not be built: {err}") from None
            reallocations += grew
            t1 = time.perf_counter()
            n = x.shape[0]
            xj = jnp.asarray(x, dtype)
            if state is None:
                state = _first_state(x, tess, dtype)
            state = eqx.tree_at(lambda s: s.tess, state, eqx.tree_at(lambda g: g.points, tess, xj))
            if grew or state.scutoid_trace.neighbors.shape[1] == 0:
                state = prepare_scutoid_trace(state, observe)
            values = _fitness(frame, landscape, xj, n, dtype)
            v = jnp.asarray(frame["velocities"], dtype) if "velocities" in frame else jnp.zeros_like(xj)
            p = _compose(between, n) if between else np.arange(n)
            between = []
            now = frame_times(t)
            step_dt = jnp.asarray(now - previous_time if previous_time is not None else 1.0, dtype)
            state, obs = _observe_frame(
                landscape,
                params,
                state,
                (xj, v, values, jnp.asarray(p, jnp.int32)),
                jnp.asarray(done, jnp.int32),
                step_dt,
                observe,
            )
            previous_time = now
            for name in observe:
                series[name].append(obs[name])  # device scalars: the next frame's build overlaps them
            indices.append(t)
            kept.append(now)
            if gap_every and done % gap_every == 0:
                gaps.append((done,) + _bulk_gap(state.tess))
            done += 1
            seconds["rebuild"] += t1 - t0
            seconds["steps"] += time.perf_counter() - t1
            if bar is not None:
                bar.update(1)
    except KeyboardInterrupt:
        close_bar(bar, owned)
        history = _trajectory_history(series, indices, kept, src, gaps, reallocations, seconds, missing, dtype)
        raise TrajectoryInterrupted(history, done) from None
    close_bar(bar, owned)
    if not indices:
        raise ValueError(f"{src.name}: no frame in range(start={start}, stop={stop}, every={every}).")
    return _trajectory_history(series, indices, kept, src, gaps, reallocations, seconds, missing, dtype)


def _frames(src: _Source, supplied: dict, start: int, stop):
    """(t, frame dict) from `start` to `stop`, the supplied per-frame arrays merged in."""

    def merged(t, frame):
        for key, array in supplied.items():
            if array is not None:
                if t >= len(array):
                    raise ValueError(f"`{key}` has {len(array)} frames; the trajectory has more.")
                frame[key] = np.asarray(array[t])
        return frame

    if src.n_frames is None:
        for t, x in enumerate(src._iter):
            if stop is not None and t >= stop:
                return
            if t >= start:
                yield t, merged(t, {"positions": x})
        return
    for t in range(start, stop):
        yield t, merged(t, src.frame(t))


def _times(src: _Source, times, dt, n_frames):
    if times is not None:
        times = np.asarray(times, float)
        if n_frames is not None and times.shape != (n_frames,):
            raise ValueError(f"`times` has shape {times.shape}; the trajectory has {n_frames} frames.")
        return lambda t: float(times[t])
    if dt is not None:
        if not dt > 0:
            raise ValueError(f"`dt` must be > 0; got {dt!r}.")
        return lambda t: t * float(dt)
    if src.times is not None:
        return lambda t: float(src.times[t])
    return float


def _fitness(frame: dict, landscape, xj, n: int, dtype):
    """The frame's fitness values; None with a landscape (`_observe_frame` evaluates it)."""
    if landscape is not None:
        return None
    if "fitness" in frame:
        return jnp.asarray(frame["fitness"], dtype)
    return jnp.zeros(n, dtype)


def _trajectory_history(series, indices, times, src, gaps, reallocations, seconds, missing, dtype) -> dict:
    history: dict[str, Any] = {name: np.asarray([float(v) for v in values], dtype) for name, values in series.items()}
    steps = np.asarray(src.steps)[indices] if src.steps is not None and len(indices) else np.asarray(indices)
    history.update(
        frame=np.asarray(indices, np.int64),
        step=np.asarray(steps, np.int64),
        time=np.asarray(times, float),
        spectral_gap_step=np.asarray([g[0] for g in gaps], np.int32).reshape(-1),
        spectral_gap=np.asarray([g[1] for g in gaps], dtype).reshape(-1),
        spectral_components=np.asarray([g[2] for g in gaps], np.int32).reshape(-1),
        spectral_gap_rounding=np.asarray([g[3] for g in gaps], bool).reshape(-1),
        n_reallocations=np.asarray(reallocations, np.int32),
        seconds_rebuild=np.asarray(seconds["rebuild"]),
        seconds_steps=np.asarray(seconds["steps"]),
        unavailable={name: why for name, why in missing.items()},
    )
    return history
