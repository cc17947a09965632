"""The cheap check of a 2D triangulation, jitted, for a backend whose triangles stay on the device
(CuPy's gDel2D): the same conditions as the host's `check_triangulation`, on device arrays.

- every index in range and every walker a vertex (a walker left out is a failed build);
- every triangle positively oriented (twice its signed area above the rounding of its terms);
- Euler's formula for a triangulation of the convex hull: S = 2N - b - 2, b the boundary edges
  (edges of exactly one triangle), and no edge in more than two triangles.

The edges are counted by one sort of their (min, max) keys: O(S log S) on the device, no host
sync but the status read by the caller.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

OK, OUT_OF_RANGE, LEFT_OUT, FLAT, EULER = 0, 1, 2, 3, 4
REASONS = {OUT_OF_RANGE: "a vertex index out of range", LEFT_OUT: "a walker left out",
           FLAT: "triangles flat or negatively oriented", EULER: "Euler's formula fails (or an edge has three "
           "triangles)"}


@jax.jit
def planar_triangulation_status(points, simplices):
    """(status, flat triangles): `OK` (0) when `simplices` (S, 3) int is a positively oriented
    triangulation of the convex hull of `points` (N, 2), else the first failed condition's code
    (`REASONS`). Float64 arithmetic for the orientation where JAX has it."""
    n = points.shape[0]
    s = simplices.astype(jnp.int32)
    in_range = jnp.all((s >= 0) & (s < n))
    safe = jnp.clip(s, 0, n - 1)
    used = jnp.zeros(n, bool).at[safe.ravel()].set(True)
    x = points.astype(jnp.float64 if jax.config.jax_enable_x64 else points.dtype)
    a, b, c = x[safe[:, 0]], x[safe[:, 1]], x[safe[:, 2]]
    ab, ac = b - a, c - a
    twice_area = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    size = jnp.abs(ab[:, 0] * ac[:, 1]) + jnp.abs(ab[:, 1] * ac[:, 0])
    flat = twice_area <= 8 * jnp.finfo(x.dtype).eps * size
    lo = jnp.minimum(safe, jnp.roll(safe, -1, axis=1)).ravel()
    hi = jnp.maximum(safe, jnp.roll(safe, -1, axis=1)).ravel()
    boundary, crowded = _edge_multiplicities(lo, hi)
    euler = (s.shape[0] == 2 * n - boundary - 2) & ~crowded
    status = jnp.where(~in_range, OUT_OF_RANGE, jnp.where(~jnp.all(used), LEFT_OUT,
                       jnp.where(jnp.any(flat), FLAT, jnp.where(~euler, EULER, OK))))
    return status.astype(jnp.int32), jnp.sum(flat)


def _edge_multiplicities(lo, hi):
    """(edges in exactly one triangle, whether an edge is in three or more) of the edges (lo, hi),
    after one lexicographic sort (no 64-bit keys needed)."""
    lo, hi = jax.lax.sort((lo, hi), num_keys=2)
    same = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1])
    starts = jnp.concatenate([jnp.ones(1, bool), ~same])
    group = jnp.cumsum(starts) - 1
    counts = jnp.zeros(lo.shape[0], jnp.int32).at[group].add(1)
    real = jnp.arange(lo.shape[0]) < jnp.sum(starts)
    return jnp.sum(real & (counts == 1)), jnp.any(counts > 2)
