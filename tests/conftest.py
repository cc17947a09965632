import gc
import os
import shutil
import tempfile
from importlib.metadata import version

import numpy as np
import pytest


def _jaxlib_at_least(*wanted: int) -> bool:
    parts = version("jaxlib").split(".")[: len(wanted)]
    return tuple(int("".join(ch for ch in p if ch.isdigit()) or 0) for p in parts) >= wanted


# The default run compiles with LLVM's optimisation off and with XLA's loop emitters instead of
# its newer fusion emitters: the suite is compile-bound (most tests compile their kernels once and
# run them once). Optimisation off made it ~1.4x faster; the loop emitters then halve the
# compilation left (`jaxgeom analyze --n 400 --dim 3`: 13.8 s -> 7.4 s of it; test_trust.py +
# apps/test_cli.py side by side: 185 s -> 124 s). Results are the same IEEE arithmetic (XLA's
# fast-math stays off), differing from XLA's defaults by rounding only. JAXGEOM_TEST_XLA_OPT=default
# keeps XLA's own settings; CI runs the slow reliability studies that way (the jaxlib miscompile
# guard among them).
# LLVM's code generation then runs in one piece instead of split for a thread pool, which two
# busy xdist workers on 2 cores cannot use: 15% less XLA compilation (tests/geometry test_heat,
# test_curvature, test_ollivier, test_volumes, two alternating rounds: 120 and 121 s -> 101 and
# 104 s, bench/compile_counts.py; bench/README.md, "The README's commands").
# (The emitter and split flags exist in the jaxlib 0.8 the suite is measured with; an unknown
# flag aborts XLA, so older jaxlibs do without them.)
if os.environ.get("JAXGEOM_TEST_XLA_OPT", "0") != "default":
    emitters = (
        " --xla_cpu_use_fusion_emitters=false --xla_cpu_parallel_codegen_split_count=1"
        if _jaxlib_at_least(0, 8)
        else ""
    )
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
        " --xla_llvm_disable_expensive_passes=true" + emitters
    ).strip()

import jax  # noqa: E402  (after XLA_FLAGS)

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")

# CPython's cyclic collector less often: tracing and lowering, half the suite's time, allocate
# millions of short-lived containers, and the default young-generation threshold (700) runs the
# collector thousands of times per program (~20% of their time: bench/gc_thresholds.py).
# JAXGEOM_TEST_GC=default keeps Python's thresholds.
if os.environ.get("JAXGEOM_TEST_GC") != "default":
    gc.set_threshold(50_000, 20, 100)

# One persistent compilation cache for the whole run, shared by the xdist workers and by the
# command lines the tests start (in-process or as children): a program compiled by one test is
# read back by the next that needs it, in any worker, also after `_free_compiled_programs`
# dropped it from memory. The controller creates the directory before the workers start (they
# inherit its environment) and removes it at the end. JAXGEOM_TEST_COMPILE_CACHE=0 turns it off.
_CACHE_OWNER = "JAXGEOM_COMPILE_CACHE_DIR" not in os.environ
if os.environ.get("JAXGEOM_TEST_COMPILE_CACHE", "1") != "0":
    if _CACHE_OWNER:
        os.environ["JAXGEOM_COMPILE_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaxgeom-test-xla-")
    from jaxgeom.cli import use_compile_cache  # the command lines' own set-up: their folder (one per CPU type)

    if use_compile_cache(True) is None:
        raise RuntimeError(f"the suite's compile cache in {os.environ['JAXGEOM_COMPILE_CACHE_DIR']} cannot be created")
else:
    os.environ.setdefault("JAXGEOM_COMPILE_CACHE", "0")  # and the command lines the tests run


def pytest_unconfigure(config):
    if _CACHE_OWNER and not hasattr(config, "workerinput") and "JAXGEOM_COMPILE_CACHE_DIR" in os.environ:
        shutil.rmtree(os.environ.pop("JAXGEOM_COMPILE_CACHE_DIR"), ignore_errors=True)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def own_messages():
    """jaxgeom's own refusals of ill-typed arguments, as a user sees them: the test run checks
    every annotation at runtime (jaxtyping's hook, pyproject addopts), which would refuse such
    an argument first, with its own message."""
    import jaxtyping

    before = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    yield
    jaxtyping.config.update("jaxtyping_disable", before)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop each module's compiled programs when it ends. XLA's CPU code lives in ~3 memory
    maps per executable; a whole suite in one process passed Linux's vm.max_map_count (65530)
    and segfaulted inside the compiler."""
    yield
    jax.clear_caches()
    gc.collect()
