"""The history `simulate` returns: the observables' series, the spectral gaps, the counters."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import scipy.sparse.linalg

from ..base._checks import warn_at_caller
from ..geometry._spectral import bulk_spectral_gap, gap_rounding_level
from ..tessellation._graph import Tessellation


def _history(series: dict, gaps: list, reallocations, seconds: dict, state, diverged_step, n_fallbacks=0) -> dict:
    """The history `simulate` returns, with the same keys and JAX array types in both rebuild
    modes (the callback mode computes no spectral gaps and measures no wall-clock times: empty
    arrays and NaN)."""
    dtype = state.positions.dtype
    history = {name: jnp.asarray(values, dtype) for name, values in series.items()}
    with jax.debug_nans(False):  # the callback mode's NaN times are meant: not a NaN to report
        seconds = {name: jnp.asarray(value, dtype) for name, value in seconds.items()}
    history.update(
        spectral_gap_step=jnp.asarray([g[0] for g in gaps], jnp.int32).reshape(-1),
        spectral_gap=jnp.asarray([g[1] for g in gaps], dtype).reshape(-1),
        spectral_components=jnp.asarray([g[2] for g in gaps], jnp.int32).reshape(-1),
        spectral_gap_rounding=jnp.asarray([g[3] for g in gaps], bool).reshape(-1),
        n_reallocations=jnp.asarray(reallocations, jnp.int32),
        n_fallbacks=jnp.asarray(n_fallbacks, jnp.int32),
        seconds_rebuild=seconds["rebuild"],
        seconds_steps=seconds["steps"],
        n_separated=jnp.asarray(state.n_separated, jnp.int32),
        diverged_step=jnp.asarray(diverged_step, jnp.int32),
        n_triangulator_fallbacks=jnp.asarray(state.n_triangulator_fallbacks, jnp.int32),
    )
    return history


def _bulk_gap(tess: Tessellation) -> tuple[float, int, bool]:
    """(gap, components, whether the gap is at rounding level) of `bulk_spectral_gap`;
    a diagnostic never ends a run: a failure
    (no convergence) is NaN with a warning."""
    try:
        gap, n_comp, outside = bulk_spectral_gap(tess)
        return gap, n_comp, bool(gap < gap_rounding_level(tess.n_points - outside))
    except (ArithmeticError, RuntimeError, ValueError, scipy.sparse.linalg.ArpackError) as err:
        warn_at_caller(
            f"simulate: the spectral gap failed ({type(err).__name__}: {err}); recorded as NaN.", RuntimeWarning
        )
        return float("nan"), -1, False
