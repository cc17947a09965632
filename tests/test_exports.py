"""Issue 63: every exception class the library raises can be caught by its public name."""

import ast
import builtins
from pathlib import Path

import jaxgeom

PACKAGE = Path(jaxgeom.__file__).parent
# raised, and always caught inside jaxgeom before a user could see it
INTERNAL = {"TooManyTriangles": "padded_triangles' callers catch it and fall back to CDT"}


def raised_names() -> dict[str, str]:
    """Name of every class after `raise` in jaxgeom's source -> where it is raised first."""
    found = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Raise) and node.exc is not None:
                target = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
                if isinstance(target, ast.Name) and target.id[:1].isupper():
                    found.setdefault(target.id, f"{path.relative_to(PACKAGE)}:{node.lineno}")
    return found


def test_every_raised_exception_class_is_exported_or_a_builtin():
    missing = {
        name: where
        for name, where in raised_names().items()
        if not hasattr(builtins, name) and not hasattr(jaxgeom, name) and name not in INTERNAL
    }
    assert not missing, f"raised but not exported from jaxgeom: {missing}"


def test_the_walk_finds_the_library_s_own_exceptions():
    names = raised_names()
    assert {"SimulationDiverged", "CoincidentPointsError", "CapacityError", "TuningFailed"} <= set(names)
    assert set(INTERNAL) <= set(names)  # an entry for an exception no longer raised is stale


def test_the_readme_s_exceptions_are_catchable_by_name():
    assert issubclass(jaxgeom.SimulationDiverged, FloatingPointError)
    assert issubclass(jaxgeom.CoincidentPointsError, ValueError)
    assert issubclass(jaxgeom.CapacityError, ValueError)
    assert issubclass(jaxgeom.SimulationInterrupted, KeyboardInterrupt)
