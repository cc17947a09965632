"""The README's claims, read from the README itself: the names it gives exist, the kernels it
calls jitted are jitted, the command-line options it lists exist, and its first screen is a
front page (no dates, commit hashes or machine anecdotes; short sections)."""

import contextlib
import io
import json
import logging
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxgeom
from jaxgeom.cli import main

README = (Path(__file__).parents[1] / "README.md").read_text()


def sections() -> dict:
    parts = re.split(r"^## ", README, flags=re.M)
    return {part.splitlines()[0]: part for part in parts[1:]}


def test_the_first_screen_is_a_front_page():
    first = "\n".join(README.splitlines()[:40])
    assert not re.search(r"20\d\d-\d\d-\d\d", first), "a date on the first screen"
    assert not re.search(r"\b[0-9a-f]{7,40}\b", first), "a commit hash on the first screen"
    assert not re.search(r"\b(VM|CI run|fresh-clone|slower than)\b", first), "a machine anecdote on the first screen"
    assert "## Contents" in first
    for title, text in sections().items():
        assert len(text.splitlines()) <= 62, f"section {title!r} has {len(text.splitlines())} lines"


def test_every_jaxgeom_name_in_the_readme_exists():
    names = set(re.findall(r"\bjaxgeom\.([A-Za-z_]\w*)", README))
    names |= {m for m in re.findall(r"^\| `(\w+)\(", README, flags=re.M)}  # table rows: `name(args)`
    names |= {m for row in re.findall(r"^\| `(\w+)`(?:, `(\w+)`)*", README, flags=re.M) for m in row if m}
    names -= {"py"}
    missing = sorted(n for n in names if not hasattr(jaxgeom, n))
    assert not missing, f"the README names {missing}, which jaxgeom does not have"
    assert len(names) > 30


def jitted_rows() -> list:
    """The kernels the README's table says run jitted ("jit" in their row's second column)."""
    table = sections()["Geometry of your own points"]
    rows = []
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 3 and "jit" in cells[1]:
            rows += re.findall(r"`(\w+)", cells[0])
    return rows


@pytest.fixture(scope="module")
def calls():
    """One call of every public kernel on a small graph, by name: (function of values, values)."""
    jax.config.update("jax_enable_x64", True)
    rng = np.random.default_rng(0)
    x = rng.random((120, 2))
    tess = jaxgeom.delaunay(x, box=(0.0, 1.0))
    metric = jaxgeom.hessian_metric(lambda p: jnp.sum(p**4) + jnp.sum(p**2), 0.1)
    v = rng.normal(size=(120, 2))
    vol = np.asarray(jaxgeom.voronoi_volumes(tess))
    f = np.sin(3 * x[:, 0]) + x[:, 1] ** 2

    return {
        "knn_graph": (lambda y: jaxgeom.knn_graph(y, 6, method="brute").neighbors, x),
        "rebuild": (lambda y: jaxgeom.rebuild(tess, y).neighbors, x),
        "voronoi_volumes": (lambda y: jaxgeom.voronoi_volumes(_moved(tess, y)), x),
        "voronoi_facets": (lambda y: jaxgeom.voronoi_facets(_moved(tess, y)).areas, x),
        "circumcenters": (lambda y: jaxgeom.circumcenters(_moved(tess, y)), x),
        "edge_lengths": (lambda y: jaxgeom.edge_lengths(_moved(tess, y), metric=metric), x),
        "metric_at_walkers": (lambda y: jaxgeom.metric_at_walkers(_moved(tess, y), metric), x),
        "metric_defects": (lambda y: jaxgeom.metric_defects(_moved(tess, y), metric), x),
        "emergent_metric": (lambda y: jaxgeom.emergent_metric(_moved(tess, y)), x),
        "riemannian_volumes": (lambda y: jaxgeom.riemannian_volumes(_moved(tess, y), metric=metric), x),
        "riemannian_mean": (lambda w: jaxgeom.riemannian_mean(w, w), vol),
        "deficit_angles": (lambda y: jaxgeom.deficit_angles(_moved(tess, y), metric=metric), x),
        "angle_sums": (lambda y: jaxgeom.angle_sums(_moved(tess, y), metric=metric), x),
        "ricci_scalar": (lambda y: jaxgeom.ricci_scalar(_moved(tess, y), metric=metric), x),
        "ricci_resolution": (lambda y: jaxgeom.ricci_resolution(_moved(tess, y), metric=metric), x),
        "volume_distortion": (lambda y: jaxgeom.volume_distortion(_moved(tess, y)), x),
        "shape_distortion": (lambda y: jaxgeom.shape_distortion(_moved(tess, y)), x),
        "vertex_distance_variance": (lambda y: jaxgeom.vertex_distance_variance(_moved(tess, y)), x),
        "raychaudhuri_expansion": (lambda w: jaxgeom.raychaudhuri_expansion(w, 1.1 * w, 0.1), vol),
        "mean_curvature_estimate": (lambda w: jaxgeom.mean_curvature_estimate(w), vol),
        "viscous_force": (lambda u: jaxgeom.viscous_force(tess, u, nu=0.1), v),
        "edge_weights": (lambda y: jaxgeom.edge_weights(_moved(tess, y), weights="metric_full", metric=metric), x),
        "graph_laplacian": (lambda y: jaxgeom.graph_laplacian(_moved(tess, y)).weights, x),
        "spectral_gap": (lambda y: jaxgeom.spectral_gap(_moved(tess, y), k=3, method="lobpcg"), x),
        "geodesic_distances": (lambda y: jaxgeom.geodesic_distances(_moved(tess, y), [0], metric), x),
        "estimate_gradient": (lambda w: jaxgeom.estimate_gradient(tess, w, weights="gaussian"), f),
        "estimate_hessian": (lambda w: jaxgeom.estimate_hessian(tess, w), f),
        "geometric_hessian": (lambda y: jaxgeom.geometric_hessian(_moved(tess, y), 0.1), x),
        "metric_curvature": (lambda y: jaxgeom.metric_curvature(metric, y), x),
        "ollivier_ricci": (lambda y: jaxgeom.ollivier_ricci(_moved(tess, y)).edge_curvature, x),
        "scutoids": (lambda y: jaxgeom.scutoids(tess, _moved(tess, y)).kind, x),
    }


def _moved(tess, y):
    import equinox as eqx

    return eqx.tree_at(lambda t: t.points, tess, jnp.asarray(y))


def compiles_during(fn) -> list:
    """The XLA compilations logged while `fn` runs (jax_log_compiles)."""
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    loggers = [logging.getLogger(name) for name in ("jax._src.dispatch", "jax._src.interpreters.pxla")]
    with jax.log_compiles(True), contextlib.ExitStack() as stack:
        for logger in loggers:
            logger.addHandler(handler)
            stack.callback(logger.removeHandler, handler)
        jax.block_until_ready(fn())
    return [line for line in stream.getvalue().splitlines() if "Compiling" in line or "compil" in line.lower()]


def test_the_table_lists_only_kernels_the_tests_call(calls):
    rows = jitted_rows()
    assert len(rows) > 25
    assert set(rows) - {"delaunay", "spectral_gap", "graph_laplacian"} <= set(calls), set(rows) - set(calls)


@pytest.mark.parametrize("name", [r for r in jitted_rows() if r not in ("delaunay",)])
def test_every_kernel_the_readme_calls_jitted_compiles_once_and_reruns_without_tracing(calls, name):
    """A second call with new values of the same shapes compiles nothing and traces nothing: the
    kernel is one jitted program (an op-by-op kernel retraces its Python on every call, as
    `edge_weights` once did: 23 ms at N = 1e3 against 0.31 ms jitted)."""
    fn, values = calls[name]
    jax.block_until_ready(fn(values))  # compile
    again = np.asarray(values) * 1.0001
    traced = []
    with _count_traces(traced):
        assert not compiles_during(lambda: fn(again)), f"{name} compiled again"
    # a few host-side conversions are allowed (jnp.asarray of an argument); a kernel run op by
    # op binds dozens of primitives
    assert len(traced) <= 4, f"{name} ran {len(traced)} primitives outside a compiled program: {traced[:12]}"


@contextlib.contextmanager
def _count_traces(out: list):
    """Record every primitive bound outside a compiled program (op-by-op execution)."""
    from jax._src import core

    original = core.Primitive.bind

    def bind(self, *args, **params):
        eager = isinstance(core.trace_ctx.trace, core.EvalTrace)  # not staged into a traced program
        if eager and self.name not in ("pjit", "jit", "device_put", "convert_element_type"):
            out.append(self.name)
        return original(self, *args, **params)

    core.Primitive.bind = bind
    try:
        yield
    finally:
        core.Primitive.bind = original


def test_every_command_line_option_in_the_readme_exists(capsys):
    text = sections()["The command line"]
    for command in ("simulate", "analyze", "tune"):
        block = text[text.index(f"`jaxgeom {command}") :]
        block = block[: block.index("\n- ", 1)] if "\n- " in block[1:] else block
        flags = set(re.findall(r"(--[a-z][a-z0-9-]*)", block))
        with pytest.raises(SystemExit):
            main([command, "--help"])
        helptext = capsys.readouterr().out
        missing = sorted(flag for flag in flags if flag not in helptext)
        assert not missing, f"jaxgeom {command} --help has no {missing}"
    for flag in re.findall(r"`(--[a-z][a-z0-9-]*)`", text.split("- `jaxgeom simulate")[0]):
        with pytest.raises(SystemExit):
            main(["simulate", "--help"])
        assert flag in capsys.readouterr().out


def test_every_bench_section_the_readme_cites_exists():
    """`bench/README.md, "Title"` in the README names a heading of bench/README.md."""
    bench = (Path(__file__).parents[1] / "bench" / "README.md").read_text()
    headings = [line.lstrip("#").strip() for line in bench.splitlines() if line.startswith("## ")]
    cited = re.findall(r'bench/README\.md`?,?\s+"([^"]+)"', " ".join(README.split()))
    assert cited, "the README cites no bench section"
    for title in cited:
        assert any(h.startswith(title) for h in headings), f"bench/README.md has no section {title!r}"


@pytest.mark.slow
def test_the_quick_tour_runs_and_tunes_to_the_answer_it_prints():
    """The quick tour's code block, run as it is; its tuning answer is the one its comment prints,
    a converged value inside the chapter's range (0.01-0.5) it is bounded to."""
    block = re.search(r"```python\n(.*?)```", sections()["Quick tour"], flags=re.S).group(1)
    namespace = {}
    exec(compile(block, "README.md (quick tour)", "exec"), namespace)
    result = namespace["result"]
    printed = eval(re.search(r"^result\.values\s+# (\{[^}]*\})", block, flags=re.M).group(1))
    assert result.converged and result.zero_gradient == ()
    assert result.values.keys() == printed.keys()
    np.testing.assert_allclose(list(result.values.values()), list(printed.values()), rtol=1e-6)
    assert all(0.01 <= value <= 0.5 for value in result.values.values())


@pytest.mark.slow
def test_the_hero_image_is_what_simulate_draws_at_its_defaults(tmp_path):
    """The README's first figure and its history.json come from `jaxgeom simulate` at today's
    defaults: the same configuration, the same series over the first steps (before the
    trajectories' chaos could amplify rounding differences between machines), and a figure of
    the same layout and pixels (a different seed's figure differs by 0.047 on average; an equal
    run by 0)."""
    import matplotlib.image

    hero = Path(__file__).parents[1] / re.search(r"!\[[^\]]*\]\(([^)]+)\)", README).group(1)
    kept = json.loads((hero.parent / "history.json").read_text())
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["simulate", "--no-progress", "--out", str(tmp_path)]) == 0
    fresh = json.loads((tmp_path / "history.json").read_text())
    assert {k: v for k, v in kept["config"].items() if k != "out"} == {
        k: v for k, v in fresh["config"].items() if k != "out"
    }
    for name, series in fresh["series"].items():
        np.testing.assert_allclose(
            np.asarray(kept["series"][name][:10], float),
            np.asarray(series[:10], float),
            rtol=1e-6,
            atol=1e-9,
            err_msg=name,
        )
    a, b = matplotlib.image.imread(hero), matplotlib.image.imread(tmp_path / "swarm.png")
    assert a.shape == b.shape and np.abs(a - b).mean() < 0.1
