"""Scutoids: each walker's Voronoi cell at t joined to its cell at t + dt.

The bottom of walker i's scutoid is the cell of its clone parent p(i) at t (its own cell when
it did not clone), the top its cell at t + dt. Its neighbour changes compare the bottom's
neighbours (walker ids at t) with the top's (walker ids at t + dt):
shared = |B ∩ T|, lost = |B \\ T|, gained = |T \\ B|.

Classes (`kind`): a prism keeps its neighbours (lost = gained = 0); a simple scutoid loses at
most one and gains at most one (one Delaunay flip: the two walkers of the removed edge lose one
neighbour each, the two of the new edge gain one, four simple scutoids); a complex scutoid loses
or gains two or more. The reference code (FragileTech/fragile, scutoids.py) classifies by
|B Δ T| = lost + gained: 0 prism (ours too), 2 simple (ours when lost = gained = 1; lost + gained
= 2 with two lost or two gained is complex here), > 2 complex (ours too), and puts |B Δ T| = 1,
one flip's own signature, among the complex ones (simple here).

Spacetime volume: the frustum between the bottom and the top cell,
V_ST = dt / (d + 1) sum_{k=0}^{d} V_b^(k/d) V_t^((d-k)/d), the (d+1)-volume swept when the
cell's linear size changes linearly in time. It is V dt for a prism of unchanged cross-section
and the exact integral of V(t) for a cell that scales uniformly (x -> s x: V_b dt (s^(d+1) - 1)
/ ((d + 1)(s - 1))); for a cell that changes shape it is the frustum of its two volumes.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..base._checks import check_positive, real_array
from ..tessellation._graph import Tessellation
from ._volumes import voronoi_volumes

PRISM, SIMPLE, COMPLEX = 0, 1, 2
KINDS = ("prism", "simple", "complex")


class ScutoidFractions(NamedTuple):
    """Fractions of the walkers whose cell is a prism (no neighbour lost or gained), a simple
    scutoid (at most one lost and one gained) or a complex scutoid (more); they add up to 1, or
    are all NaN where no walker was counted. A tuple: `np.asarray(fractions)` is the 3-vector."""

    prism: Float[Array, ""]
    simple: Float[Array, ""]
    complex: Float[Array, ""]


class Scutoids(eqx.Module):
    r"""What `scutoids` returns, per walker i (all (N,)).

    **Fields:**

    - `shared`, `lost`, `gained`: int32 neighbour counts of the bottom cell (its parent's at
      t) and the top cell (its own at t + dt).
    - `kind`: int8, `PRISM` (0), `SIMPLE` (1) or `COMPLEX` (2) (module docstring).
    - `parent`: int32 clone parent (i where the walker did not clone).
    - `bottom_volume`, `top_volume`: the two cells' volumes (NaN where unbounded);
      `spacetime_volume`: the frustum's (d+1)-volume (NaN where either cell is unbounded),
      $V_{ST} = \frac{dt}{d + 1} \sum_{k=0}^{d} V_b^{k/d} \, V_t^{(d-k)/d}$ for the bottom
      and top volumes $V_b$, $V_t$.
    - `hull`: the bottom or the top cell is on the convex hull (unbounded without a box): its
      neighbour changes include the hull's own; `interior`: both cells are tier 2.
    """

    shared: Int[Array, " N"]
    lost: Int[Array, " N"]
    gained: Int[Array, " N"]
    kind: Int[Array, " N"]
    parent: Int[Array, " N"]
    bottom_volume: Float[Array, " N"]
    top_volume: Float[Array, " N"]
    spacetime_volume: Float[Array, " N"]
    hull: Bool[Array, " N"]
    interior: Bool[Array, " N"]

    def fractions(self, mask=None) -> ScutoidFractions:
        """[`jaxgeom.ScutoidFractions`][]: the fractions of prisms, simple and complex scutoids
        among the walkers in `mask` (default: `interior`); NaN where the mask is empty."""
        mask = self.interior if mask is None else mask
        count = jnp.sum(mask)
        dtype = self.bottom_volume.dtype
        share = lambda k: jnp.where(  # noqa: E731
            count > 0, jnp.sum(mask & (self.kind == k)).astype(dtype) / jnp.maximum(count, 1).astype(dtype), jnp.nan
        )
        return ScutoidFractions(share(PRISM), share(SIMPLE), share(COMPLEX))


def scutoids(
    before: Tessellation, after: Tessellation, parents=None, *, dt=1.0, volumes_before=None, volumes_after=None
) -> Scutoids:
    """The scutoids of one step: each walker's cell at t (its clone parent's) joined to its
    cell at t + dt, its neighbour changes classified, its spacetime volume.

    **Arguments:**

    - `before`, `after`: Delaunay [`jaxgeom.Tessellation`][]s of the same N walkers (the same
      numbering) at t and t + dt.
    - `parents`: (N,) int clone parent of each walker (the walker itself where it did not
      clone), as `simulate` records them; None: no walker cloned.
    - `dt`: the time between the two graphs (> 0), for the spacetime volume.
    - `volumes_before`, `volumes_after`: the graphs' `voronoi_volumes` if already computed.

    **Returns:** a [`jaxgeom.Scutoids`][] (module docstring for the classes and the volume).
    O(N K^2), jittable; no host work.
    """
    for name, tess in (("before", before), ("after", after)):
        if not isinstance(tess, Tessellation) or tess.simplices is None:
            raise TypeError(
                f"`{name}` must be a Delaunay jaxgeom.Tessellation (jaxgeom.delaunay); scutoids join Voronoi cells."
            )
    if before.points.shape != after.points.shape:
        raise ValueError(
            f"`before` and `after` must hold the same walkers; got {before.points.shape[0]} and "
            f"{after.points.shape[0]} walkers of d = {before.points.shape[1]}, {after.points.shape[1]}."
        )
    n = before.n_points
    if parents is None:
        parents = jnp.arange(n, dtype=jnp.int32)
    elif not isinstance(parents, jax.core.Tracer):
        host = np.asarray(parents)
        if host.shape != (n,) or not np.issubdtype(host.dtype, np.integer):
            raise ValueError(
                f"`parents` must be an (N,) = ({n},) integer array (each walker's clone parent); got "
                f"{host.dtype} {host.shape}."
            )
        if host.size and (host.min() < 0 or host.max() >= n):
            raise ValueError(f"`parents` must hold walker ids in [0, {n}); got values in [{host.min()}, {host.max()}].")
    if not isinstance(dt, jax.core.Tracer):
        check_positive(dt, "dt")
    for name, value in (("volumes_before", volumes_before), ("volumes_after", volumes_after)):
        if value is not None and not isinstance(value, jax.core.Tracer):
            if real_array(value, name).shape != (n,):
                raise ValueError(f"`{name}` must have shape (N,) = ({n},).")
    return _scutoids(before, after, jnp.asarray(parents, jnp.int32), dt, volumes_before, volumes_after)


@eqx.filter_jit
def _scutoids(before, after, parents, dt, volumes_before, volumes_after) -> Scutoids:
    shared, lost, gained = neighbour_changes(before.neighbors[parents], after.neighbors, before.n_points)
    kind = jnp.where((lost == 0) & (gained == 0), PRISM, jnp.where((lost <= 1) & (gained <= 1), SIMPLE, COMPLEX))
    bottom = (voronoi_volumes(before) if volumes_before is None else jnp.asarray(volumes_before))[parents]
    top = voronoi_volumes(after) if volumes_after is None else jnp.asarray(volumes_after)
    return Scutoids(
        shared,
        lost,
        gained,
        kind.astype(jnp.int8),
        parents,
        bottom,
        top,
        frustum_volume(bottom, top, dt, before.dim),
        before.hull[parents] | after.hull,
        (before.tier[parents] == 2) & (after.tier == 2),
    )


def neighbour_changes(bottom, top, n: int):
    """(shared, lost, gained) int32 per row of two padded neighbour tables (padding `n`);
    each id counted once (a periodic walker may list two images of one neighbour)."""

    def distinct(rows):
        k = rows.shape[1]
        earlier = (rows[:, :, None] == rows[:, None, :]) & (jnp.arange(k)[None, :] < jnp.arange(k)[:, None])[None]
        return (rows < n) & ~jnp.any(earlier, axis=2)

    real_bottom, real_top = distinct(bottom), distinct(top)
    in_bottom = jnp.any((top[:, :, None] == bottom[:, None, :]) & real_bottom[:, None, :], axis=2)
    shared = jnp.sum(real_top & in_bottom, axis=1)
    return (
        shared.astype(jnp.int32),
        (jnp.sum(real_bottom, axis=1) - shared).astype(jnp.int32),
        jnp.sum(real_top & ~in_bottom, axis=1).astype(jnp.int32),
    )


def frustum_volume(bottom, top, dt, d: int):
    """dt / (d + 1) sum_k V_b^(k/d) V_t^((d-k)/d): NaN where either volume is not finite."""
    ok = jnp.isfinite(bottom) & jnp.isfinite(top) & (bottom >= 0) & (top >= 0)
    b, t = jnp.where(ok, bottom, 1.0), jnp.where(ok, top, 1.0)
    total = sum(b ** (k / d) * t ** ((d - k) / d) for k in range(d + 1))
    return jnp.where(ok, dt * total / (d + 1), jnp.nan)
