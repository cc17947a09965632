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
from pathlib import Path

_OUT = Path(os.environ.get("JAXGEOM_COMPILE_COUNTS_DIR", Path(tempfile.gettempdir()) / "jaxgeom-compile-counts"))
_current = {"test": "<outside tests>"}
_counts: dict[str, list] = {}


def _row() -> list:
    return _counts.setdefault(_current["test"], [0, 0, 0.0])


def _on_event(event: str, **_):
    if event == "/jax/compilation_cache/compile_requests_use_cache":
        _row()[0] += 1
    elif event == "/jax/compilation_cache/cache_hits":
        _row()[1] += 1


def _on_duration(event: str, seconds: float, **_):
    if event == "/jax/core/compile/backend_compile_duration":
        _row()[2] += seconds


def pytest_configure(config):
    from jax import monitoring

    monitoring.register_event_listener(_on_event)
    monitoring.register_event_duration_secs_listener(_on_duration)


def pytest_runtest_logstart(nodeid, location):
    _current["test"] = nodeid


def pytest_unconfigure(config):
    _OUT.mkdir(parents=True, exist_ok=True)
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    (_OUT / f"{worker}.json").write_text(json.dumps(_counts, indent=0))


def summary(folder: Path, top: int = 30) -> None:
    rows: dict[str, list] = {}
    for path in sorted(folder.glob("*.json")):
        for test, (requests, hits, seconds) in json.loads(path.read_text()).items():
            row = rows.setdefault(test, [0, 0, 0.0])
            row[0], row[1], row[2] = row[0] + requests, row[1] + hits, row[2] + seconds
    total = [sum(r[k] for r in rows.values()) for k in range(3)]
    print(f"{len(rows)} tests: {total[0]} compile requests, {total[1]} persistent-cache hits, "
          f"{total[2]:.1f} s in XLA's backend compile")
    for test, (requests, hits, seconds) in sorted(rows.items(), key=lambda kv: -kv[1][2])[:top]:
        print(f"{seconds:7.1f} s {requests:5d} requests {hits:4d} hits  {test}")


if __name__ == "__main__":
    summary(Path(sys.argv[1]) if len(sys.argv) > 1 else _OUT)
