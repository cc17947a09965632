import gc
import os

# The default run compiles with LLVM's optimisation off: the suite is compile-bound (most tests
# compile their kernels once and run them once) and this makes it ~1.4x faster. Results are the
# same IEEE arithmetic (XLA's fast-math stays off). JAXGEOM_TEST_XLA_OPT=default keeps XLA's own
# level; CI runs the slow set that way (the jaxlib miscompile guard among them).
if os.environ.get("JAXGEOM_TEST_XLA_OPT", "0") != "default":
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
                               " --xla_llvm_disable_expensive_passes=true").strip()

import jax  # noqa: E402  (after XLA_FLAGS)
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """Drop each module's compiled programs when it ends. XLA's CPU code lives in ~3 memory
    maps per executable; a whole suite in one process passed Linux's vm.max_map_count (65530)
    and segfaulted inside the compiler."""
    yield
    jax.clear_caches()
    gc.collect()
