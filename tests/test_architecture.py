"""The package's layers (README, Architecture): one folder per layer, and a module imports only
from its own layer's earlier modules or from the layers below."""

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parent.parent / "jaxgeom"

# Bottom to top, the data flow points -> Tessellation -> kernels -> swarm -> applications -> CLI.
# Within a folder, each tuple may import the tuples before it.
LAYERS = {
    "base": [
        (
            "_checks",
            "_simplex",
            "_progress",
            "_sharding",
            "_compact",
        ),  # validation; dense algebra; bars; meshes; flagged ids
        ("_h5md",),  # H5MD trajectory files through h5py
    ],
    "tessellation": [
        ("_device_check",),  # the cheap check of a GPU backend's triangles, on the device
        ("_planar", "_graph", "_triangulators"),  # 2D fan rows; the Tessellation pytree; host backends
        ("_contacts", "_slabs"),  # zero-measure contacts; open 3D Qhull in slabs on threads
        ("_delaunay", "_knn"),  # points -> Tessellation (host builds)
        ("_cellgrid",),  # the device cell list
        ("_cellclip",),  # the Delaunay rebuild on the device (per-cell Voronoi clipping, certified)
    ],
    "geometry": [
        ("_boxclip", "_transport"),  # Voronoi cells clipped to the box; exact small transport problems
        ("_dualclip",),  # the Delaunay dual's pieces cut to the box (3D)
        ("_dual",),  # 3D faces, volumes, centroids and vertex counts from the Delaunay dual
        ("_volumes", "_facets"),  # cell volumes; the faces, centroids and vertex counts of the cells
        ("_metric",),
        (
            "_cells",
            "_curvature",
            "_heat",
            "_metric_curvature",
            "_ollivier",
            "_scutoids",
        ),  # ..., the curvature of a callable
        # metric, Ollivier-Ricci curvature of the graph
        ("_geodesic",),  # heat method, Dijkstra, Bellman-Ford behind one entry point
        ("_weights",),  # edge weight rules
        ("_forces", "_spectral", "_estimation"),
    ],
    "swarm": [
        ("_dynamics",),  # SwarmParams, SwarmState, the three phases of a step
        ("_observables",),
        ("_rebuild",),  # graph lifecycle of a moving swarm
        ("_swarm_init", "_divergence", "_history"),  # the initial state; divergence; the history
        ("_steps",),  # the step bodies every driver shares
        ("_drivers",),  # host chunks, one traced scan, the split swarm: one function each
        ("_simulate",),  # the entry point: checks, dispatch, batches of swarms
        ("_tuning",),  # simulation_loss: theta -> objective of whole simulations
        ("_tune",),  # the optimistix / jaxopt driver
        ("_trajectory",),  # the observables of a recorded trajectory
    ],
    "apps": [
        ("_landscapes",),
        ("_validation", "_plots"),
    ],
    "cli": [  # one unit: its modules import each other freely
        ("__init__", "__main__", "_analyze", "_simulate", "_tune", "_legend", "_trajectory"),
    ],
}
FOLDERS = list(LAYERS)
PUBLIC = "jaxgeom/__init__.py"
ORDER = FOLDERS[:-1] + [PUBLIC, "cli"]  # only the CLI may import the public surface
LEVEL = {
    (folder, name): level for folder, tuples in LAYERS.items() for level, names in enumerate(tuples) for name in names
}


def internal_imports(path: Path) -> set[tuple[str, str]]:
    """(folder, module) of every jaxgeom module `path` imports, function-local imports too."""
    folder = path.parent.name
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            found.add((folder, node.module.split(".")[0]))
        elif isinstance(node, ast.ImportFrom) and node.level == 2 and node.module:
            found.add(tuple(node.module.split(".")[:2]))
        elif isinstance(node, ast.Import) and any(a.name == "jaxgeom" for a in node.names):
            found.add((PUBLIC, "jaxgeom"))  # the public surface, jaxgeom/__init__.py
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            absolute = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            assert getattr(node, "level", 0) < 3 and not any(n.split(".")[0] == "jaxgeom" for n in absolute), (
                f"{path}: import jaxgeom's private modules relatively (from ._x or from ..folder._x)"
            )
    return found


MODULES = sorted(p for p in PACKAGE.glob("*/*.py"))


def where(path: Path) -> tuple[str, str]:
    return path.parent.name, path.stem


def test_the_top_level_holds_only_the_public_surface():
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"]
    assert {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"} == set(FOLDERS)


def test_every_module_has_a_layer():
    placed = {where(p) for p in MODULES if p.name != "__init__.py" or p.parent.name == "cli"}
    assert placed <= set(LEVEL), placed - set(LEVEL)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down_the_folders(path):
    mine = ORDER.index(path.parent.name)
    for folder, name in internal_imports(path):
        assert ORDER.index(folder) <= mine, (
            f"{path.relative_to(PACKAGE)} (folder {path.parent.name}) imports {folder}/{name}: "
            f"{folder} is a layer above; move the shared code down or the caller up"
        )


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down_within_a_folder(path):
    if path.parent.name == "cli" or path.name == "__init__.py":
        return
    me = LEVEL[where(path)]
    for folder, name in internal_imports(path):
        if folder == path.parent.name:
            assert LEVEL[folder, name] < me, (
                f"{path.relative_to(PACKAGE)} (level {me}) imports {name} (level {LEVEL[folder, name]})"
            )


def test_the_public_surface_imports_every_layer_but_cli():
    top = {
        node.module.split(".")[0]
        for node in ast.walk(ast.parse((PACKAGE / "__init__.py").read_text()))
        if isinstance(node, ast.ImportFrom) and node.level == 1
    }
    assert top == set(FOLDERS) - {"cli"}


def architecture_section() -> str:
    readme = (PACKAGE.parent / "README.md").read_text()
    start = readme.index("## Architecture")
    return readme[start : readme.index("\n## ", start + 1)]


def test_the_readme_names_every_module_by_a_path_that_exists():
    text = architecture_section()
    for folder, name in re.findall(r"`([a-z]+)/(_[a-z_]+\.py)`", text):
        where_it_is = PACKAGE / name if folder == "jaxgeom" else PACKAGE / folder / name
        assert where_it_is.exists(), f"README names {folder}/{name}, which does not exist"
    for name in set(re.findall(r"`(_[a-z_]+\.py)`", text)):
        assert list(PACKAGE.glob(f"*/{name}")), f"README names {name}, which no folder holds"
    for path in MODULES:
        if path.name != "__init__.py":
            assert f"`{path.name}`" in text or f"`{path.parent.name}/{path.name}`" in text, (
                f"README's Architecture does not place {path.relative_to(PACKAGE)}"
            )


def test_the_test_run_checks_jaxgeoms_annotations_at_runtime(request):
    """README, Contributing: the tests check every annotation of jaxgeom at runtime (pyproject's
    addopts install jaxtyping's hook with beartype). A shape that contradicts an annotation
    fails; a run without the hook (bench/gpu_check.sh's `-o addopts=""`) skips this check."""
    import jax.numpy as jnp
    import jaxtyping

    pyproject = (PACKAGE.parent / "pyproject.toml").read_text()
    assert re.search(r'^addopts = """[^"]*--jaxtyping-packages=jaxgeom,beartype', pyproject, flags=re.M)
    if not request.config.getoption("--jaxtyping-packages", default=None):
        pytest.skip("this run was started without pyproject's addopts")
    from jaxgeom.geometry._transport import transport_cost

    square, vector = jnp.ones((3, 3)), jnp.ones(3)
    with pytest.raises(jaxtyping.TypeCheckError, match="transport_cost"):
        transport_cost(square, jnp.ones(4), vector, square > 0)  # (M,) masses of another M
