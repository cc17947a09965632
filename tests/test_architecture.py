"""The package's layers (README, Architecture): a module imports only from layers below it."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parent.parent / "jaxgeom"

# Bottom to top, the data flow points -> Tessellation -> kernels -> dynamics -> simulate -> CLI.
LAYERS = [
    ("_simplex", "_planar"),  # small dense linear algebra; 2D triangle-fan rows
    ("_graph",),  # the Tessellation pytree and its gathers
    ("_checks",),  # host-boundary validation
    ("_landscapes", "_progress", "_sharding"),  # built-in fitness functions; tqdm bars; device meshes
    ("_contacts",),
    ("_delaunay", "_knn"),  # points -> Tessellation (host builds)
    ("_cellgrid",),  # the device cell list
    ("_cellclip",),  # the Delaunay rebuild on the device (per-cell Voronoi clipping, certified)
    ("_boxclip",),  # Voronoi cells clipped to the box (volumes of tier-0 cells)
    ("_volumes",),
    ("_metric",),
    ("_cells", "_curvature", "_heat"),
    ("_geodesic",),  # heat method, Dijkstra, Bellman-Ford behind one entry point
    ("_weights",),  # edge weight rules
    ("_forces", "_spectral", "_estimation"),
    ("_dynamics",),  # SwarmParams, SwarmState, the three phases of a step
    ("_observables",),
    ("_rebuild",),  # graph lifecycle of a moving swarm
    ("_swarm_init", "_divergence", "_history"),  # the initial state; divergence checks; the history
    ("_steps",),  # the step bodies every driver shares
    ("_drivers",),  # host chunks, one traced scan, the split swarm: one function each
    ("_simulate",),  # the entry point: checks, dispatch, batches of swarms
    ("_tuning",),  # simulation_loss: theta -> objective of whole simulations
    ("_tune",),  # the optimistix / jaxopt driver
    ("_validation", "_plots"),
    ("cli",),
]
LEVEL = {name: level for level, names in enumerate(LAYERS) for name in names}


def internal_imports(path: Path) -> set[str]:
    """The package modules `path` imports (every import statement, function-local ones too);
    inside jaxgeom/cli/ only those of the package above it."""
    depth = 2 if path.parent.name == "cli" else 1
    return {node.module.split(".")[0] for node in ast.walk(ast.parse(path.read_text()))
            if isinstance(node, ast.ImportFrom) and node.level == depth and node.module}


def module_name(path: Path) -> str:
    return "cli" if path.parent.name == "cli" else path.stem


MODULES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent.name == "cli")


def test_every_module_has_a_layer():
    assert {module_name(p) for p in MODULES} <= set(LEVEL), {module_name(p) for p in MODULES} - set(LEVEL)


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_down_the_layers(path):
    me = LEVEL[module_name(path)]
    for name in internal_imports(path):
        assert LEVEL[name] < me, f"{path.name} (layer {me}) imports {name} (layer {LEVEL[name]})"
