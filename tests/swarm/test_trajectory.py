"""analyze_trajectory against simulate's own history, and H5MD files both ways (pyh5md as the
independent writer and reader)."""

import contextlib
import json

import h5py
import numpy as np
import pyh5md
import pytest

import jaxgeom
from jaxgeom.apps._landscapes import rastrigin

PARAMS = jaxgeom.SwarmParams(dt=0.05, nu=0.3)
RECORDED = tuple(n for n in jaxgeom.ALL_OBSERVABLES if n not in ("nu", "eps_sigma", "mean_metric_curvature"))


@pytest.fixture(scope="module")
def run():
    """A 2D swarm with cloning, saved at every step (the state entering it) with its history."""
    state = jaxgeom.init_swarm(rastrigin, np.random.default_rng(0).uniform(-3, 3, (150, 2)), triangulator="qhull")
    frames, history = [], {name: [] for name in RECORDED}
    for _ in range(6):
        frames.append(
            [np.asarray(a) for a in (state.positions, state.velocities, state.fitness, state.scutoid_trace.parents)]
        )
        state, h = jaxgeom.simulate(rastrigin, state, PARAMS, n_steps=1, observe=RECORDED)
        for name in RECORDED:
            history[name].append(float(h[name][0]))
    x, v, f, p = map(np.stack, zip(*frames, strict=True))
    assert (p != np.arange(150)).any()  # the run cloned
    return x, v, f, p, {name: np.asarray(values) for name, values in history.items()}


def test_a_saved_run_reanalysed_gives_its_own_history(run):
    x, v, f, p, history = run
    out = jaxgeom.analyze_trajectory(
        x, landscape=rastrigin, velocities=v, parents=p, dt=0.05, params=PARAMS, triangulator="qhull"
    )
    for name in RECORDED:
        np.testing.assert_allclose(out[name], history[name], rtol=1e-9, atol=1e-12, equal_nan=True, err_msg=name)
    assert set(out["unavailable"]) == {"nu", "eps_sigma"}
    # the fitness values recorded instead of the landscape: the same fitness statistics
    values = jaxgeom.analyze_trajectory(
        x, fitness=f, dt=0.05, triangulator="qhull", observe=("mean_fitness", "best_fitness", "mean_expansion")
    )
    for name in ("mean_fitness", "best_fitness", "mean_expansion"):
        np.testing.assert_allclose(values[name], history[name], rtol=1e-9, equal_nan=True)


def test_h5md_written_by_jaxgeom_is_read_by_pyh5md_and_reanalysed(run, tmp_path):
    x, v, f, p, history = run
    path = tmp_path / "run.h5md"
    with jaxgeom.H5MDWriter(path, 150, 2) as out:
        for t in range(len(x)):
            out.append(10 * t, 0.05 * t, position=x[t], velocity=v[t], fitness=f[t], parents=p[t])
        out.write_observables(history, 10 * np.arange(len(x)), 0.05 * np.arange(len(x)))
    with pyh5md.File(str(path), "r") as h5:
        position = pyh5md.element(h5.particles_group("swarm"), "position")
        np.testing.assert_array_equal(position.value[()], x)
        np.testing.assert_array_equal(position.step[()], 10 * np.arange(len(x)))
        assert list(h5["particles/swarm/box"].attrs["boundary"]) == [b"none", b"none"]
        np.testing.assert_array_equal(h5["observables/mean_ricci/value"][()], history["mean_ricci"])
    out = jaxgeom.analyze_trajectory(path, landscape=rastrigin, params=PARAMS, triangulator="qhull")
    for name in RECORDED:
        np.testing.assert_allclose(out[name], history[name], rtol=1e-9, atol=1e-12, equal_nan=True, err_msg=name)
    np.testing.assert_array_equal(out["step"], 10 * np.arange(len(x)))


def test_a_periodic_3d_file_written_by_pyh5md_is_read(tmp_path):
    rng = np.random.default_rng(2)
    x = rng.uniform(0, 2.0, (4, 120, 3))
    path = tmp_path / "lammps_like.h5"
    with pyh5md.File(str(path), "w", creator="test") as h5:
        part = h5.particles_group("atoms")
        part.create_box(dimension=3, boundary=["periodic"] * 3, store="fixed", data=np.full(3, 2.0))
        position = pyh5md.element(part, "position", store="linear", step=5, time=0.5, shape=(120, 3), dtype=np.float64)
        for frame in x:
            position.append(frame)
    out = jaxgeom.analyze_trajectory(path, observe=("volume_distortion", "mean_expansion"))
    same = jaxgeom.analyze_trajectory(
        x, box=(0.0, 2.0), periodic=True, dt=0.5, observe=("volume_distortion", "mean_expansion")
    )
    for name in ("volume_distortion", "mean_expansion"):
        np.testing.assert_allclose(out[name], same[name], rtol=1e-12, equal_nan=True)
    np.testing.assert_array_equal(out["step"], 5 * np.arange(4))
    np.testing.assert_allclose(out["time"], 0.5 * np.arange(4))
    # a torus neither grows nor shrinks: the covered volume is the box's at every frame
    np.testing.assert_allclose(out["mean_expansion"][1:], 0.0, atol=1e-9)


def test_sources_and_frame_ranges_agree(run, tmp_path):
    x, v, f, p, _ = run
    np.save(tmp_path / "x.npy", x)
    np.savez(tmp_path / "x.npz", positions=x, fitness=f, parents=p)
    observe = ("mean_fitness", "volume_distortion", "mean_expansion", "n_clones", "mean_neighbor_change")
    memory = jaxgeom.analyze_trajectory(x, fitness=f, parents=p, every=2, start=1, observe=observe)
    npz = jaxgeom.analyze_trajectory(tmp_path / "x.npz", every=2, start=1, observe=observe)
    frames = jaxgeom.analyze_trajectory(iter(list(x)), fitness=f, parents=p, every=2, start=1, observe=observe)
    for name in observe:
        np.testing.assert_array_equal(npz[name], memory[name])
        np.testing.assert_array_equal(frames[name], memory[name])
    np.testing.assert_array_equal(memory["frame"], [1, 3, 5])
    # two steps' parents composed: a walker's parent two frames back
    composed = p[2][p[3]]  # walker i of frame 3 came from p3[i] of frame 2, which came from p2[p3[i]]
    assert memory["n_clones"][1] == np.sum(composed != np.arange(150))
    npy = jaxgeom.analyze_trajectory(tmp_path / "x.npy", observe=("volume_distortion",))
    np.testing.assert_array_equal(npy["volume_distortion"][1::2], memory["volume_distortion"])


def test_knn_in_4d_gives_what_the_data_determine():
    x = np.random.default_rng(3).normal(size=(3, 60, 4))
    v = np.random.default_rng(4).normal(size=(3, 60, 4))
    out = jaxgeom.analyze_trajectory(x, velocities=v, graph="knn", k=8)
    assert "velocity_variance" in out and "mean_ricci" not in out
    assert "Delaunay" in out["unavailable"]["mean_ricci"]
    np.testing.assert_allclose(out["velocity_variance"], [np.mean(np.var(vt, axis=0)) for vt in v], rtol=1e-9)
    with pytest.raises(ValueError, match="mean_ricci.*Delaunay"):
        jaxgeom.analyze_trajectory(x, graph="knn", observe=("mean_ricci",))


def test_bad_input_names_the_file_the_dataset_and_the_frame(run, tmp_path):
    x, v, f, p, _ = run
    bad = x.copy()
    bad[3, 7, 1] = np.nan
    with pytest.raises(ValueError, match="frame 3.*NaN"):
        jaxgeom.analyze_trajectory(bad)
    with pytest.raises(ValueError, match="frame 2.*same walkers"):
        jaxgeom.analyze_trajectory([x[0], x[1], x[2][:-1]])
    with pytest.raises(ValueError, match="fitness has shape"):
        jaxgeom.analyze_trajectory(x, fitness=f[:, :-1])
    with pytest.raises(ValueError, match="outside the box"):
        jaxgeom.analyze_trajectory(x, box=(-1.0, 1.0))
    (tmp_path / "x.csv").write_text("1")
    with pytest.raises(ValueError, match="unknown extension"):
        jaxgeom.analyze_trajectory(tmp_path / "x.csv")
    with pytest.raises(ValueError, match="needs fitness"):
        jaxgeom.analyze_trajectory(x, observe=("mean_fitness",))
    with pytest.raises(ValueError, match="nu.*parameter of the simulation"):
        jaxgeom.analyze_trajectory(x, observe=("nu",))
    path = tmp_path / "run.h5md"
    with jaxgeom.H5MDWriter(path, 150, 2, elements=("position",)) as out:
        for frame in x:
            out.append(0, 0.0, position=frame)
    with h5py.File(path, "a") as h5:
        h5.move("particles/swarm", "particles/walkers")
    with pytest.raises(ValueError, match="no dataset particles/swarm/position"):
        jaxgeom.H5MDTrajectory(path, group="swarm")
    truncated = tmp_path / "truncated.h5md"
    truncated.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(ValueError, match="truncated.h5md: not a readable HDF5 file"):
        jaxgeom.analyze_trajectory(truncated)
    with pytest.raises(ValueError, match="already holds fitness"):
        np.savez(tmp_path / "f.npz", positions=x, fitness=f)
        jaxgeom.analyze_trajectory(tmp_path / "f.npz", fitness=f)


def test_simulate_writes_an_h5md_trajectory_that_reanalyses_to_its_history(tmp_path, capsys):
    import json

    from jaxgeom.cli import main

    out = tmp_path / "run"
    assert (
        main(
            [
                "simulate",
                "--n",
                "80",
                "--steps",
                "4",
                "--gap-every",
                "0",
                "--out",
                str(out),
                "--trajectory",
                "--save-every",
                "2",
                "--triangulator",
                "qhull",
                "--precision",
                "float64",
            ]
        )
        == 0
    )
    assert "wrote trajectory" in capsys.readouterr().out
    series = json.loads((out / "history.json").read_text())["series"]
    config = json.loads((out / "history.json").read_text())["config"]
    params = jaxgeom.SwarmParams(
        dt=config["dt"],
        gamma=config["gamma"],
        temperature=config["temperature"],
        nu=config["nu"],
        eps_sigma=config["eps_sigma"],
    )
    with jaxgeom.H5MDTrajectory(out / "trajectory.h5md") as h5:
        np.testing.assert_array_equal(h5.steps, [0, 2, 4])
        assert h5.has == ("velocity", "fitness")  # a state holds only its last step's clone parents
    again = jaxgeom.analyze_trajectory(
        out / "trajectory.h5md",
        landscape=rastrigin,
        params=params,
        triangulator="qhull",
        observe=("mean_fitness", "mean_ricci", "volume_distortion"),
    )
    for name in ("mean_fitness", "mean_ricci", "volume_distortion"):
        np.testing.assert_allclose(again[name], np.asarray(series[name], float)[[0, 2, 4]], rtol=1e-9, err_msg=name)
    with h5py.File(out / "trajectory.h5md") as h5:
        np.testing.assert_allclose(h5["observables/mean_ricci/value"][()], np.asarray(series["mean_ricci"], float))


@pytest.fixture(scope="module")
def saved_run(tmp_path_factory):
    """`jaxgeom simulate --trajectory` at every step: a file and the run's own history."""
    import json

    from jaxgeom.cli import main

    out = tmp_path_factory.mktemp("saved") / "run"
    assert (
        main(
            [
                "simulate",
                "--n",
                "120",
                "--steps",
                "7",
                "--gap-every",
                "0",
                "--out",
                str(out),
                "--trajectory",
                "--scutoids",
                "--triangulator",
                "qhull",
                "--precision",
                "float64",
                "--no-progress",
            ]
        )
        == 0
    )
    return out / "trajectory.h5md", json.loads((out / "history.json").read_text())


def _table(text: str) -> dict:
    """{row name: [initial, final, min, max]} of a printed observables table."""
    rows = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 5 and parts[0].replace("_", "").isalpha() and parts[0] != "observable":
            rows[parts[0]] = [float(p) if p != "rounding" else np.nan for p in parts[1:]]
    return rows


def test_the_command_line_reports_a_saved_run_as_its_own_history(saved_run, tmp_path, capsys):
    from jaxgeom.cli import main

    path, run = saved_run
    out = tmp_path / "an"
    assert (
        main(["analyze", "--trajectory", str(path), "--landscape", "rastrigin", "--gap-every", "3", "--out", str(out)])
        == 0
    )
    printed = capsys.readouterr().out
    table = _table(printed)
    for name in (
        "mean_fitness",
        "mean_ricci",
        "volume_distortion",
        "mean_expansion",
        "n_clones",
        "complex_scutoid_fraction",
        "velocity_variance",
    ):
        series = np.asarray(run["series"][name], float)
        # the saved run's own series (the table rounds to 5 digits)
        np.testing.assert_allclose(table[name][:2], series[[0, -1]], rtol=1e-4, equal_nan=True, err_msg=name)
    assert "not measured: nu" in printed and "frames analysed 8 of 8" in printed
    saved = json.loads((out / "observables.json").read_text())
    for name in ("mean_fitness", "mean_ricci", "mean_expansion", "n_clones", "complex_scutoid_fraction"):
        np.testing.assert_allclose(
            np.asarray(saved["series"][name], float),
            np.asarray(run["series"][name], float),
            rtol=1e-9,
            equal_nan=True,
            err_msg=name,
        )
    # the spectral gap every 3 analysed frames, each the gap of its own frame's graph
    assert saved["spectral_gap"]["frame"] == [0, 3, 6]
    with jaxgeom.H5MDTrajectory(path) as h5:
        for frame, gap in zip(saved["spectral_gap"]["frame"], saved["spectral_gap"]["value"], strict=True):
            alone = jaxgeom.spectral_gap(jaxgeom.delaunay(h5.frame(frame)["positions"]), k=2)[1]
            np.testing.assert_allclose(gap, float(alone), rtol=1e-6)
    # the observables' H5MD file, read by an independent reader
    with pyh5md.File(str(out / "observables.h5md"), "r") as h5:
        np.testing.assert_array_equal(h5["observables/mean_fitness/step"][()], np.arange(8))
        np.testing.assert_allclose(h5["observables/mean_fitness/value"][()], saved["series"]["mean_fitness"])
        np.testing.assert_array_equal(h5["observables/spectral_gap/step"][()], [0, 3, 6])
    for figure in ("observables.png", "swarm.png"):
        assert (out / figure).stat().st_size > 10_000


def test_the_command_line_takes_frame_ranges_and_files_without_a_landscape(saved_run, tmp_path, capsys):
    from jaxgeom.cli import main

    path, run = saved_run
    with jaxgeom.H5MDTrajectory(path) as h5:
        x = np.stack([h5.frame(t)["positions"] for t in range(h5.n_frames)])
    np.save(tmp_path / "x.npy", x)
    out = tmp_path / "an"
    assert (
        main(
            [
                "analyze",
                "--trajectory",
                str(tmp_path / "x.npy"),
                "--frames",
                "1:7",
                "--every",
                "2",
                "--gap-every",
                "0",
                "--snapshots",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    saved = json.loads((out / "observables.json").read_text())
    assert saved["frame"] == [1, 3, 5] and "mean_fitness" not in saved["series"]
    assert "not measured: mean_fitness: needs fitness" in printed
    assert "not measured: mean_ricci: without a landscape the metric is Euclidean, which is flat" in printed
    want = jaxgeom.analyze_trajectory(x[1:7:2], observe=("volume_distortion", "mean_shape_distortion"))
    for name in ("volume_distortion", "mean_shape_distortion"):
        np.testing.assert_allclose(saved["series"][name], want[name], rtol=1e-12)
    assert (out / "swarm.png").exists()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--n", "100"], "--n describe"),
        (["--metric", "emergent"], "--metric describe"),
        (["--frames", "5:2"], "--frames must be A:B"),
        (["--graph", "delaunay", "--every", "0"], "--every must be"),
    ],
)
def test_the_command_line_refuses_options_of_the_other_mode(saved_run, argv, message, capsys):
    from jaxgeom.cli import main

    path, _ = saved_run
    with pytest.raises(SystemExit) if message.startswith("--every") else contextlib.nullcontext():
        assert main(["analyze", "--trajectory", str(path), *argv]) == 2
    assert message in capsys.readouterr().err


def test_trajectory_options_without_a_trajectory_are_refused(tmp_path, capsys):
    from jaxgeom.cli import main

    assert main(["analyze", "--every", "3"]) == 2
    assert "--every appl" in capsys.readouterr().err
    (tmp_path / "t.csv").write_text("1")
    assert main(["analyze", "--trajectory", str(tmp_path / "t.csv")]) == 2
    assert "t.csv: unknown extension" in capsys.readouterr().err


def test_ctrl_c_returns_the_frames_done(run):
    x = run[0]

    def frames():
        yield from x[:3]
        raise KeyboardInterrupt

    with pytest.raises(jaxgeom.TrajectoryInterrupted) as stopped:
        jaxgeom.analyze_trajectory(frames(), observe=("volume_distortion",))
    assert stopped.value.frames == 3
    np.testing.assert_array_equal(stopped.value.history["frame"], [0, 1, 2])
    np.testing.assert_array_equal(
        stopped.value.history["volume_distortion"],
        jaxgeom.analyze_trajectory(x[:3], observe=("volume_distortion",))["volume_distortion"],
    )
