"""Cell proxies: volume distortion, shape distortion, Raychaudhuri expansion."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..base._checks import check_positive, check_walker_mask, walker_values
from ..base._simplex import simplex_circumradius
from ..tessellation._graph import (
    Tessellation,
    nearest_neighbor_distances,
    simplex_coords,
    takes_tessellation,
)
from ._volumes import voronoi_volumes


@takes_tessellation
@eqx.filter_jit
def volume_distortion(tess: Tessellation, volumes=None) -> Float[Array, ""]:
    """Var(V_i / <V>) over tier-2 walkers with finite volume: 0 for equal cells.

    Pass `volumes=riemannian_volumes(tess, metric)` for the Riemannian form.
    """
    vol = voronoi_volumes(tess, clip=False) if volumes is None else volumes  # tier 2: inside any box
    ok = tess.interior & jnp.isfinite(vol)
    vol = jnp.where(ok, vol, 0.0)  # NaN volumes out before they meet `mean`: its gradient would be NaN
    count = jnp.sum(ok).astype(vol.dtype)
    mean = jnp.sum(vol) / count
    ratio = jnp.where(ok, vol / mean, 0.0)
    return jnp.sum(jnp.where(ok, (ratio - 1.0) ** 2, 0.0)) / count


def _incident_circumradii(tess: Tessellation):
    """(S,) circumradius of every simplex, the distance from each of its vertices to
    its circumcentre (a Voronoi vertex of each vertex's cell)."""
    radius = jax.vmap(simplex_circumradius)(simplex_coords(tess))
    return jnp.where(tess.simplex_mask, radius, 0.0)


@takes_tessellation
@eqx.filter_jit
def shape_distortion(tess: Tessellation) -> Float[Array, " N"]:
    """Inradius / circumradius of every Voronoi cell about its generator: 1 for a regular
    cell, towards 0 for an elongated one.

    r_in = half the distance to the nearest neighbour (the nearest facet) and
    r_circ = the largest circumradius of the walker's simplices (the farthest
    cell vertex); rho = r_in / r_circ in (0, 1]. A rectangular lattice with
    spacings a <= b gives a / sqrt(a^2 + b^2), a hexagonal lattice sqrt(3)/2.
    Tier 0 (unbounded or box-touching cells) is NaN.
    """
    r_in = 0.5 * nearest_neighbor_distances(tess)
    radius = _incident_circumradii(tess)
    spread = jnp.broadcast_to(radius[:, None], tess.simplices.shape)
    r_circ = jax.ops.segment_max(spread.ravel(), tess.simplices.ravel(), num_segments=tess.n_points)
    return jnp.where(tess.tier == 0, jnp.nan, r_in / r_circ)


@takes_tessellation
@eqx.filter_jit
def vertex_distance_variance(tess: Tessellation) -> Float[Array, " N"]:
    """Variance of the distances from x_i to its Voronoi cell's vertices: 0 when
    all lie on one sphere about x_i.

    Each simplex around i contributes its circumcentre once. Tier 0 is NaN.
    """
    n = tess.n_points
    radius = _incident_circumradii(tess)
    ids = tess.simplices.ravel()
    spread = jnp.broadcast_to(radius[:, None], tess.simplices.shape).ravel()
    count = jax.ops.segment_sum(jnp.ones_like(spread), ids, num_segments=n)
    mean = jax.ops.segment_sum(spread, ids, num_segments=n) / jnp.maximum(count, 1)
    mean_pad = jnp.concatenate([mean, jnp.zeros((1,), mean.dtype)])
    dev = spread - mean_pad[ids]
    var = jax.ops.segment_sum(dev * dev, ids, num_segments=n) / jnp.maximum(count, 1)
    return jnp.where(tess.tier == 0, jnp.nan, var)


def raychaudhuri_expansion(volumes_before, volumes_after, dt, *, valid=None) -> Float[Array, " N"]:
    r"""Discrete expansion $\theta_i = \dfrac{V_i(t + dt) - V_i(t)}{V_i(t) \, dt}$, the
    discrete Raychaudhuri expansion (the divergence of the flow for a smooth flow).

    **Arguments:**

    - `volumes_before`, `volumes_after`: (N,) cell volumes of the same walkers.
    - `dt`: time step > 0.
    - `valid`: (N,) bool; pass `tier == 2` at both times and not cloned
      (a cell that changed tier or a clone that split it changes volume for reasons
      other than the flow). Invalid walkers, and non-finite or non-positive volumes, get NaN.

    **Returns:**

    (N,) theta, NaN where undefined. Under $x \to s x$, $\theta = (s^d - 1) / dt$ exactly.
    """
    check_positive(dt, "dt")
    before = walker_values(volumes_before, "volumes_before", nonnegative=True)
    after = walker_values(volumes_after, "volumes_after", nonnegative=True)
    if before.shape != after.shape:
        raise ValueError(f"volume arrays differ in shape: {before.shape} vs {after.shape}; both must be (N,).")
    check_walker_mask(valid, "valid", before.shape)
    ok = jnp.isfinite(before) & jnp.isfinite(after) & (before > 0)
    if valid is not None:
        ok = ok & valid
    theta = (after - before) / (jnp.where(ok, before, 1.0) * dt)
    return jnp.where(ok, theta, jnp.nan)


def mean_curvature_estimate(theta) -> Float[Array, ""]:
    """-<theta> over walkers with a defined expansion (NaN entries are excluded, not zero)."""
    theta = walker_values(theta, "theta")
    ok = jnp.isfinite(theta)
    return -jnp.sum(jnp.where(ok, theta, 0.0)) / jnp.sum(ok).astype(theta.dtype)
