"""The notebooks: executed top to bottom in a Jupyter kernel (nbclient), and kept clean.

Executing all eight takes ~5 minutes on 2 cores, beyond the default run's budget, so those tests
carry the `notebooks` marker: `pytest -m notebooks` runs them (CI does, after the suite). The
With JAXGEOM_EXECUTED_NOTEBOOKS set to a folder, the executed notebooks are written
there, outputs and figures included, for the documentation site to show (docs/hooks.py). The
default run checks what needs no kernel: each notebook is valid, committed without outputs, saves
the figures it names, and those figures are committed, small, and linked from the README.
"""

import json
import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))
FIGURES = ROOT / "notebooks" / "figures"
MAX_FIGURE_BYTES = 200_000
TEST_XLA_FLAGS = ("--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true")


def code_of(path: Path) -> str:
    cells = json.loads(path.read_text())["cells"]
    return "\n".join("".join(c["source"]) for c in cells if c["cell_type"] == "code")


def figures_named(path: Path) -> list[str]:
    """The PNG files a notebook writes under FIGURES (its own savefig / plot calls)."""
    return re.findall(r'FIGURES / "([\w.]+\.png)"', code_of(path))


def test_there_are_the_eight_notebooks():
    assert [p.name[:2] for p in NOTEBOOKS] == ["01", "02", "03", "04", "05", "06", "07", "08"]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_clean_and_its_figures_are_small(path):
    nb = json.loads(path.read_text())
    assert nb["nbformat"] == 4
    for cell in nb["cells"]:
        if cell["cell_type"] == "code":
            assert not cell["outputs"] and cell["execution_count"] is None, f"{path.name}: clear the outputs"
    names = figures_named(path)
    assert names, f"{path.name} saves no figure under FIGURES"
    for name in names:
        size = (FIGURES / name).stat().st_size
        assert 10_000 < size <= MAX_FIGURE_BYTES, (name, size)


def test_readme_links_every_notebook():
    readme = (ROOT / "README.md").read_text()
    for path in NOTEBOOKS:
        assert f"(notebooks/{path.name})" in readme, f"README.md does not link {path.name}"


def kernel_environment(figures: Path) -> dict:
    """The test process's environment for the kernel, figures redirected, and XLA's
    optimisation back at its default (conftest lowers it for this process only)."""
    env = dict(os.environ, JAXGEOM_FIGURES=str(figures))
    flags = [f for f in env.get("XLA_FLAGS", "").split() if f not in TEST_XLA_FLAGS]
    env["XLA_FLAGS"] = " ".join(flags)
    return env


@pytest.mark.notebooks
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs_and_writes_its_figures(path, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(path.parent)}}
    )
    client.execute(env=kernel_environment(tmp_path))  # raises CellExecutionError on any failing cell
    if executed := os.environ.get("JAXGEOM_EXECUTED_NOTEBOOKS"):  # the site shows these (docs/hooks.py)
        Path(executed).mkdir(parents=True, exist_ok=True)
        nbformat.write(nb, Path(executed) / path.name)
    for name in figures_named(path):
        assert (tmp_path / name).stat().st_size > 10_000, name
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors


@pytest.mark.notebooks
def test_progress_auto_is_a_widget_in_a_notebook():
    """simulate(progress="auto") is silent in a pipe (tests/apps/test_presentation.py) and a tqdm
    widget inside a Jupyter kernel."""
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    pytest.importorskip("ipywidgets")
    nb = nbformat.v4.new_notebook(
        metadata={"kernelspec": {"name": "python3", "display_name": "Python 3", "language": "python"}}
    )
    nb.cells = [
        nbformat.v4.new_code_cell(
            "import numpy as np, jaxgeom\nfrom jaxgeom.apps._landscapes import rastrigin\n"
            "st = jaxgeom.init_swarm(rastrigin, np.random.default_rng(0).uniform(-2, 2, (50, 2)))\n"
            "_ = jaxgeom.simulate(rastrigin, st, jaxgeom.SwarmParams(cloning=False), n_steps=3, progress='auto')"
        )
    ]
    nbclient.NotebookClient(nb, timeout=300, kernel_name="python3").execute(env=kernel_environment(Path(".")))
    kinds = [key for o in nb.cells[0].outputs for key in o.get("data", {})]
    assert "application/vnd.jupyter.widget-view+json" in kinds, nb.cells[0].outputs
