"""What the bench scripts share: one warm call timed until its arrays are ready, and the
median (min, max) of several."""

from __future__ import annotations

import time

import jax
import numpy as np


def timed(fn) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn())
    return time.perf_counter() - start


def summary(values) -> dict:
    return {"median": float(np.median(values)), "min": float(min(values)), "max": float(max(values))}
