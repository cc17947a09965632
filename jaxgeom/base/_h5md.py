"""H5MD files (the HDF5 layout for particle trajectories that LAMMPS, ESPResSo and pyh5md write
and MDAnalysis reads), both ways, through h5py (the `h5md` extra).

Layout (H5MD 1.1): `particles/<group>/position/{value (T, N, d), step (T,), time (T,)}`, the
box `particles/<group>/box` with attributes `dimension` and `boundary` ("periodic" or "none"
per axis) and the dataset `edges` (d,), optionally `velocity` like `position`; jaxgeom adds
the per-walker elements `fitness` (T, N) and `parents` (T, N) (clone parents, int32) and the
box's lower corner `particles/<group>/box/jaxgeom_lower` (H5MD boxes start at the origin; a
file without it is read with lower = 0). Observables: `observables/<name>/{value, step, time}`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

H5MD_SUFFIXES = (".h5md", ".h5", ".hdf5")
ELEMENTS = ("position", "velocity", "fitness", "parents")


def require_h5py():
    try:
        import h5py
    except ImportError:
        raise ImportError("reading and writing H5MD files needs h5py: pip install 'jaxgeom[h5md]'.") from None
    return h5py


def h5py_group():
    return require_h5py().Group


class _OpenFile:
    """An open HDF5 file (`_file`), closed by `close()` or at the end of a `with` block."""

    def close(self):
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class H5MDTrajectory(_OpenFile):
    """A trajectory in an H5MD file, read frame by frame (the file stays open; `close()` or use
    it as a context manager). Attributes: `path`, `group`, `n_frames`, `n`, `d`, `box`
    ((lower, upper) or None), `periodic`, `steps` (T,), `times` (T,), and `has` (the elements
    present besides positions: "velocity", "fitness", "parents")."""

    def __init__(self, path, group: str | None = None):
        h5py = require_h5py()
        self.path = Path(path)
        try:
            self._file = h5py.File(self.path, "r")
        except (OSError, ValueError) as err:
            raise ValueError(
                f"{self.path}: not a readable HDF5 file ({err}); a truncated or partly written file cannot be read."
            ) from None
        try:
            self._open(group)
        except Exception:
            self._file.close()
            raise

    def _open(self, group):
        f = self._file
        if "particles" not in f:
            raise ValueError(
                f"{self.path}: no 'particles' group; an H5MD file holds its trajectories in particles/<group>/position."
            )
        groups = [name for name in f["particles"] if "position" in f["particles"][name]]
        if group is None:
            if len(groups) != 1:
                raise ValueError(
                    f"{self.path}: particles/ holds {len(groups)} groups with positions "
                    f"({', '.join(groups) or 'none'}); name one with group=."
                )
            group = groups[0]
        if group not in groups:
            raise ValueError(
                f"{self.path}: no dataset particles/{group}/position/value (groups with positions: "
                f"{', '.join(groups) or 'none'})."
            )
        self.group = group
        g = f["particles"][group]
        self._value = {}
        for element in ELEMENTS:
            if element in g:
                if "value" not in g[element]:
                    raise ValueError(f"{self.path}: particles/{group}/{element} has no 'value' dataset.")
                self._value[element] = g[element]["value"]
        position = self._value["position"]
        if position.ndim != 3:
            raise ValueError(
                f"{self.path}: particles/{group}/position/value must be (frames, N, d); got shape {position.shape}."
            )
        self.n_frames, self.n, self.d = position.shape
        for element, data in self._value.items():
            want = (self.n_frames, self.n) + ((self.d,) if element in ("position", "velocity") else ())
            if data.shape != want:
                raise ValueError(
                    f"{self.path}: particles/{group}/{element}/value has shape {data.shape}; the positions give {want}."
                )
        self.has = tuple(e for e in ELEMENTS[1:] if e in self._value)
        self.steps = self._series(g["position"], "step", np.arange(self.n_frames))
        self.times = self._series(g["position"], "time", self.steps.astype(float))
        self.box, self.periodic = self._box(g)

    def _series(self, element, name, default):
        if name not in element:
            return default
        data = element[name]
        if data.shape == ():  # fixed interval: step (or time) = offset + index x value (H5MD 1.1)
            return data.attrs.get("offset", 0) + np.arange(self.n_frames) * data[()]
        values = np.asarray(data[()])
        if values.shape != (self.n_frames,):
            raise ValueError(
                f"{self.path}: particles/{self.group}/position/{name} has shape {values.shape}; "
                f"{self.n_frames} frames need ({self.n_frames},)."
            )
        return values

    def _box(self, g):
        if "box" not in g:
            return None, False
        box = g["box"]
        boundary = [
            b.decode() if isinstance(b, bytes) else str(b) for b in np.atleast_1d(box.attrs.get("boundary", []))
        ]
        periodic = [b == "periodic" for b in boundary]
        if "edges" not in box:
            if any(periodic):
                raise ValueError(f"{self.path}: particles/{self.group}/box is periodic but has no 'edges' dataset.")
            return None, False
        edges = box["edges"]
        if isinstance(edges, h5py_group()):  # a time-dependent box: jaxgeom needs it fixed
            values = np.asarray(edges["value"][()], float)
            if len(values) and np.any(values != values[:1]):
                raise ValueError(
                    f"{self.path}: particles/{self.group}/box/edges changes over time; jaxgeom "
                    "analyses trajectories in a fixed box."
                )
            edges = values[0]
        else:
            edges = np.asarray(edges[()], float)
        if edges.ndim == 2:  # H5MD allows the box's edge vectors; jaxgeom's boxes are rectangular
            if np.any(edges != np.diag(np.diag(edges))):
                raise ValueError(
                    f"{self.path}: particles/{self.group}/box/edges is a triclinic box; jaxgeom "
                    "analyses rectangular boxes only."
                )
            edges = np.diag(edges)
        if edges.shape != (self.d,) or not np.all(np.isfinite(edges)) or np.any(edges <= 0):
            raise ValueError(
                f"{self.path}: particles/{self.group}/box/edges must be {self.d} positive lengths; got {edges}."
            )
        lower = np.asarray(box["jaxgeom_lower"][()], float) if "jaxgeom_lower" in box else np.zeros(self.d)
        if any(periodic) and not all(periodic):
            raise ValueError(
                f"{self.path}: particles/{self.group}/box is periodic along some axes only "
                f"({boundary}); jaxgeom wraps all axes or none."
            )
        return (lower, lower + edges), all(periodic) and len(periodic) == self.d

    def frame(self, t: int) -> dict:
        """{"positions": (N, d), and "velocities", "fitness", "parents" where the file has them}."""
        names = {"position": "positions", "velocity": "velocities", "fitness": "fitness", "parents": "parents"}
        return {names[e]: np.asarray(data[t]) for e, data in self._value.items()}


class H5MDWriter(_OpenFile):
    """Writes frames into a new H5MD file, one `append` per frame (datasets grown by a frame at a
    time, so memory does not grow with the run), and the observables' series at the end."""

    def __init__(
        self,
        path,
        n: int,
        d: int,
        *,
        box=None,
        periodic: bool = False,
        group: str = "swarm",
        elements=("position", "velocity", "fitness", "parents"),
        creator_version: str = "",
    ):
        h5py = require_h5py()
        self.path = Path(path)
        self._file = f = h5py.File(self.path, "w")
        _write_header(f, creator_version)
        g = f.create_group(f"particles/{group}")
        b = g.create_group("box")
        b.attrs["dimension"] = d
        b.attrs["boundary"] = np.array([b"periodic" if periodic else b"none"] * d)
        if box is not None:
            lower, upper = (np.broadcast_to(np.asarray(v, float), (d,)) for v in box)
            b.create_dataset("edges", data=upper - lower)
            b.create_dataset("jaxgeom_lower", data=lower)
        self._elements = {}
        for element in elements:
            shape = (n, d) if element in ("position", "velocity") else (n,)
            dtype = np.int32 if element == "parents" else np.float64
            e = g.create_group(element)
            self._elements[element] = (
                e.create_dataset(
                    "value", shape=(0,) + shape, maxshape=(None,) + shape, dtype=dtype, chunks=(1,) + shape
                ),
                e.create_dataset("step", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(1024,)),
                e.create_dataset("time", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(1024,)),
            )
        self.n_frames = 0

    @property
    def elements(self) -> tuple[str, ...]:
        """The per-frame elements each `append` takes."""
        return tuple(self._elements)

    def append(self, step: int, time: float, **data):
        """One frame: `position=` (N, d) and the other elements named at construction."""
        missing = set(self._elements) - set(data)
        if missing or set(data) - set(self._elements):
            raise ValueError(f"H5MDWriter.append: give exactly {sorted(self._elements)}; got {sorted(data)}.")
        for element, (value, steps, times) in self._elements.items():
            for dataset in (value, steps, times):
                dataset.resize(self.n_frames + 1, axis=0)
            value[self.n_frames] = np.asarray(data[element])
            steps[self.n_frames], times[self.n_frames] = step, time
        self.n_frames += 1

    def write_observables(self, series: dict, steps, times):
        """`observables/<name>/{value, step, time}` for every series (one value per step)."""
        for name, values in series.items():
            values = np.asarray(values)
            if values.ndim != 1 or len(values) != len(steps):
                continue  # not a per-step series (a counter, the spectral gaps): not an H5MD time series
            _write_series(self._file, name, values, steps, times)


def _write_header(f, creator_version: str) -> None:
    meta = f.create_group("h5md")
    meta.attrs["version"] = np.array([1, 1])
    meta.create_group("author").attrs["name"] = "jaxgeom user"
    creator = meta.create_group("creator")
    creator.attrs["name"], creator.attrs["version"] = "jaxgeom", creator_version or "unknown"


def _write_series(f, name: str, values, steps, times) -> None:
    g = f.create_group(f"observables/{name}")
    g.create_dataset("value", data=np.asarray(values))
    g.create_dataset("step", data=np.asarray(steps, np.int64))
    g.create_dataset("time", data=np.asarray(times, float))


def write_h5md_observables(path, series: dict, *, creator_version: str = "") -> Path:
    """A new H5MD file holding only `observables/<name>/{value, step, time}`, one group per
    entry of `series` {name: (values (K,), steps (K,), times (K,))} (each series at its own
    steps: the spectral gap is measured less often than the rest)."""
    h5py = require_h5py()
    path = Path(path)
    with h5py.File(path, "w") as f:
        _write_header(f, creator_version)
        for name, (values, steps, times) in series.items():
            if not len(values) == len(steps) == len(times):
                raise ValueError(
                    f"write_h5md_observables: {name} has {len(values)} values, {len(steps)} steps and "
                    f"{len(times)} times."
                )
            _write_series(f, name, values, steps, times)
    return path
