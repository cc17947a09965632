"""What the bench scripts share: one warm call timed until its arrays are ready, the
median (min, max) of several, and a results file with the machine it ran on."""

from __future__ import annotations

import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np


def timed(fn) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def summary(values) -> dict:
    return {"median": float(np.median(values)), "min": float(min(values)), "max": float(max(values))}


def write_rows(name: str, rows: list) -> Path:
    """bench/results/`name`: the `rows` with the machine, its cores, jax's version and the date."""
    out = Path(__file__).parent / "results" / name
    machine = {
        "machine": platform.processor() or platform.machine(),
        "cores": len(os.sched_getaffinity(0)),
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d"),
    }
    out.write_text(json.dumps({"rows": rows, **machine}, indent=1))
    print(f"wrote {out}")
    return out
