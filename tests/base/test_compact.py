"""`flagged_ids`: the flagged entries' ids in a fixed-size array, against numpy."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxgeom.base import _compact
from jaxgeom.base._compact import flagged_ids


def expected(flags, size, fill, first=None):
    groups = [flags] if first is None else [flags & first, flags & ~first]
    ids = np.concatenate([np.flatnonzero(g) for g in groups])[:size]
    return np.concatenate([ids, np.full(size - len(ids), fill)]).astype(np.int32)


@pytest.mark.parametrize("backend", ["cpu", "gpu"])
@pytest.mark.parametrize("grouped", [False, True])
def test_flagged_ids_are_numpys_in_order_padded_and_cut_to_size(rng, monkeypatch, backend, grouped):
    """On the CPU (numpy through a callback) and elsewhere (`jnp.nonzero`, run here on the CPU
    with the backend's name patched): the flagged ids ascending, with `first` those where it
    holds ahead of the rest, padded with `fill` when fewer than `size` and cut to `size` when
    more; jitted and vmapped; none flagged and all flagged included."""
    monkeypatch.setattr(_compact.jax, "default_backend", lambda: backend)
    m = 1000
    batch = rng.random((4, m)) < np.array([[0.0], [0.02], [0.5], [1.0]])
    first = rng.random((4, m)) < 0.5 if grouped else None
    for size in (1, 37, 600, 2 * m):
        call = jax.jit(lambda f, g, size=size: flagged_ids(f, size, m, g))
        got = np.asarray(jax.vmap(call)(jnp.asarray(batch), None if first is None else jnp.asarray(first)))
        for b in range(len(batch)):
            want = expected(batch[b], size, m, None if first is None else first[b])
            np.testing.assert_array_equal(got[b], want)
            one = call(jnp.asarray(batch[b]), None if first is None else jnp.asarray(first[b]))
            np.testing.assert_array_equal(np.asarray(one), want)


def test_flagged_ids_run_on_the_host_on_the_cpu_only(monkeypatch):
    """The CPU backend's program calls back to numpy; other backends' use XLA's nonzero."""
    for backend, callback in (("cpu", True), ("gpu", False)):
        monkeypatch.setattr(_compact.jax, "default_backend", lambda backend=backend: backend)
        traced = str(jax.make_jaxpr(lambda f: flagged_ids(f, 8, 100))(jnp.zeros(100, bool)))
        assert ("callback" in traced) == callback
