"""A pytest plugin that counts, per test, the programs traced and compiled and the cache hits.

Wall time on this 2-core VM drifts by 20% within a morning, so a change that removes a few
percent of the suite's compilation cannot show in single timed runs; the counts do not drift:

    PYTHONPATH=bench .venv/bin/python -m pytest -p compile_counts tests/geometry/test_heat.py
    .venv/bin/python bench/compile_counts.py   # the summary, largest backend compile first

Each worker writes <tmp>/jaxgeom-compile-counts/<worker>.json (another folder:
$JAXGEOM_COMPILE_COUNTS_DIR; clear it between runs): {test id: [compile requests,
persistent-cache hits, seconds in XLA's backend compile]}. A compile request is a program
that missed JAX's in-memory caches, so it was traced and lowered; XLA compiled it unless the
persistent cache held it (a hit).
"""

import json
import os
import sys
import tempfile
import time
from pathlib import Path

_OUT = Path(os.environ.get("JAXGEOM_COMPILE_COUNTS_DIR", Path(tempfile.gettempdir()) / "jaxgeom-compile-counts"))
_current = {"test": "<outside tests>"}
_counts: dict[str, list] = {}
_spans: dict[str, list] = {}  # test id: [start, end] in seconds since the epoch


def _row() -> list:
    return _counts.setdefault(_current["test"], [0, 0, 0.0])


def _on_event(event: str, **_):
    if event == "/jax/compilation_cache/compile_requests_use_cache":
        _row()[0] += 1
    elif event == "/jax/compilation_cache/cache_hits":
        _row()[1] += 1


_STAGES = {
    "/jax/core/compile/jaxpr_trace_duration": 1,
    "/jax/core/compile/jaxpr_to_mlir_module_duration": 2,
    "/jax/core/compile/backend_compile_duration": 3,
}
_programs: dict[str, list] = {}  # program name: [compiles, tracing s, lowering s, backend s]
_compiled_in: dict[str, dict] = {}  # program name: {test id: compiles}


def _on_duration(event: str, seconds: float, fun_name: str = "?", **_):
    if event == "/jax/core/compile/backend_compile_duration":
        _row()[2] += seconds
    stage = _STAGES.get(event)
    if stage is not None:
        program = _programs.setdefault(fun_name, [0, 0.0, 0.0, 0.0])
        program[0] += stage == 3
        program[stage] += seconds
        if stage == 3:
            by_test = _compiled_in.setdefault(fun_name, {})
            by_test[_current["test"]] = by_test.get(_current["test"], 0) + 1


def pytest_configure(config):
    from jax import monitoring

    monitoring.register_event_listener(_on_event)
    monitoring.register_event_duration_secs_listener(_on_duration)


def pytest_runtest_logstart(nodeid, location):
    _current["test"] = nodeid
    _spans[nodeid] = [time.time(), None]


def pytest_runtest_logfinish(nodeid, location):
    _spans[nodeid][1] = time.time()


def pytest_unconfigure(config):
    _OUT.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (_OUT / f"{worker}.json").write_text(json.dumps(_counts, indent=0))
    (_OUT / f"{worker}.spans").write_text(json.dumps(_spans, indent=0))
    (_OUT / f"{worker}.programs").write_text(json.dumps(_programs, indent=0))
    (_OUT / f"{worker}.compiled_in").write_text(json.dumps(_compiled_in, indent=0))


def programs(folder: Path, top: int = 40) -> None:
    """The programs by seconds spent tracing, lowering and compiling them, over all workers."""
    rows: dict[str, list] = {}
    for path in sorted(folder.glob("*.programs")):
        for name, values in json.loads(path.read_text()).items():
            row = rows.setdefault(name, [0, 0.0, 0.0, 0.0])
            for k in range(4):
                row[k] += values[k]
    total = [sum(r[k] for r in rows.values()) for k in range(4)]
    print(
        f"{len(rows)} programs, {total[0]} compiles: tracing {total[1]:.0f} s, lowering {total[2]:.0f} s, "
        f"backend {total[3]:.0f} s"
    )
    for name, (count, trace, lower, backend) in sorted(rows.items(), key=lambda kv: -sum(kv[1][1:]))[:top]:
        print(f"{trace + lower + backend:7.1f} s ({trace:5.1f} + {lower:5.1f} + {backend:5.1f}) {count:4d}x  {name}")


def timeline(folder: Path) -> None:
    """Each worker's busy seconds per module, in the order it ran them, and when it finished."""
    spans = {path.stem: json.loads(path.read_text()) for path in sorted(folder.glob("*.spans"))}
    if not spans:
        return
    t0 = min(s for worker in spans.values() for s, _ in worker.values())
    for worker, tests in spans.items():
        modules: dict[str, list] = {}
        for test, (start, end) in tests.items():
            span = modules.setdefault(test.split("::")[0], [start, end or start])
            span[0], span[1] = min(span[0], start), max(span[1], end or start)
        end = max(e for _, e in modules.values())
        print(f"{worker}: done at {end - t0:.0f} s")
        for module, (start, stop) in sorted(modules.items(), key=lambda kv: kv[1][0]):
            print(f"  {start - t0:6.0f} +{stop - start:6.1f} s  {module}")


def summary(folder: Path, top: int = 30) -> None:
    rows: dict[str, list] = {}
    for path in sorted(folder.glob("*.json")):
        for test, (requests, hits, seconds) in json.loads(path.read_text()).items():
            row = rows.setdefault(test, [0, 0, 0.0])
            row[0], row[1], row[2] = row[0] + requests, row[1] + hits, row[2] + seconds
    total = [sum(r[k] for r in rows.values()) for k in range(3)]
    print(
        f"{len(rows)} tests: {total[0]} compile requests, {total[1]} persistent-cache hits, "
        f"{total[2]:.1f} s in XLA's backend compile"
    )
    for test, (requests, hits, seconds) in sorted(rows.items(), key=lambda kv: -kv[1][2])[:top]:
        print(f"{seconds:7.1f} s {requests:5d} requests {hits:4d} hits  {test}")


if __name__ == "__main__":
    summary(Path(sys.argv[1]) if len(sys.argv) > 1 else _OUT)
    programs(Path(sys.argv[1]) if len(sys.argv) > 1 else _OUT)
    timeline(Path(sys.argv[1]) if len(sys.argv) > 1 else _OUT)
