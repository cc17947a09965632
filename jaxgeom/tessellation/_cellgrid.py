"""A jittable cell list (2D) that adapts to the density of a swarm: candidate neighbours
for the device Voronoi cells.

The walkers are sorted once by the row of their cell in a uniform G x G grid over their
bounding box and then by x, so that the walkers of a run of cells in one grid row are
contiguous and ordered along the row: a cell has no capacity to overflow. Each walker
searches the block of (2 rho + 1)^2 cells around it, with rho = 1 ... `MAX_REACH` chosen
from the density around it (the smallest block holding `BLOCK_TARGET` walkers), and takes
from each block row the `per_row` walkers nearest to it along x. The radius within which
this finds every walker is returned with the list: rho cell sides, less where a block row
held more than `per_row` walkers (then the x-extent of the window taken). The Voronoi
certificate decides whether that was enough.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

MAX_REACH = 4  # at most a 9 x 9 block of cells
BLOCK_TARGET = 40  # walkers wanted in a block (about 25 within the radius it guarantees)
GRID_FACTOR = 1.0  # cells per side over sqrt(N): a walker per cell on the bounding box


def grid_side(n: int) -> int:
    """Cells per side of the grid (`GRID_FACTOR` sqrt(N))."""
    return int(max(4, math.ceil(GRID_FACTOR * math.sqrt(n))))


class Grid(eqx.Module):
    """The cell list of one set of positions."""

    order: Int[Array, " N"]  # walkers sorted by (cell row, cell column)
    cell: Int[Array, "N 2"]  # (column, row) of each walker's cell
    start: Int[Array, " G2"]  # first position in `order` of cell row * G + column
    count: Int[Array, " G2"]  # walkers per cell
    side: Float[Array, ""]  # cell side
    lower: Float[Array, " 2"]  # lower left corner of the grid
    cells: int = eqx.field(static=True)  # G


def build_grid(points: Float[Array, "N 2"], cells: int) -> Grid:
    """The cell list of `points` (non-finite walkers fall in a corner cell; their cells are
    never certified)."""
    finite = jnp.all(jnp.isfinite(points), axis=1, keepdims=True)
    lo = jnp.min(jnp.where(finite, points, jnp.inf), axis=0)
    extent = jnp.max(jnp.max(jnp.where(finite, points, -jnp.inf), axis=0) - lo)
    side = jnp.where(extent > 0, extent, 1.0) / cells
    cell = jnp.clip(jnp.floor((jnp.where(finite, points, lo) - lo) / side), 0, cells - 1).astype(jnp.int32)
    key = cell[:, 1] * cells + cell[:, 0]
    x = jnp.where(finite[:, 0], points[:, 0], lo[0])
    _, _, order = jax.lax.sort((cell[:, 1], x, jnp.arange(points.shape[0], dtype=jnp.int32)), num_keys=2)
    count = jnp.zeros((cells * cells,), jnp.int32).at[key].add(1)
    return Grid(order, cell, jnp.cumsum(count) - count, count, side, lo, cells)


def _cell_count(grid: Grid, column, row):
    inside = (column >= 0) & (column < grid.cells) & (row >= 0) & (row < grid.cells)
    return jnp.where(
        inside, grid.count[jnp.clip(row, 0, grid.cells - 1) * grid.cells + jnp.clip(column, 0, grid.cells - 1)], 0
    )


def walker_reach(grid: Grid, rows) -> Int[Array, " M"]:
    """Per walker, the smallest rho whose (2 rho + 1)^2 block holds `BLOCK_TARGET` walkers
    (`MAX_REACH` at most), from the block totals along its own row and column."""
    column, row = grid.cell[rows, 0], grid.cell[rows, 1]
    reach = jnp.full(rows.shape, MAX_REACH, jnp.int32)
    total = jnp.zeros(rows.shape, jnp.int32)
    ring_total = [total]
    for rho in range(1, MAX_REACH + 1):  # add the ring of cells at Chebyshev distance rho
        ring = jnp.zeros(rows.shape, jnp.int32)
        for t in range(-rho, rho + 1):
            ring += _cell_count(grid, column + t, row - rho) + _cell_count(grid, column + t, row + rho)
        for t in range(-rho + 1, rho):
            ring += _cell_count(grid, column - rho, row + t) + _cell_count(grid, column + rho, row + t)
        ring_total.append(ring_total[-1] + ring)
    centre = _cell_count(grid, column, row)
    for rho in reversed(range(1, MAX_REACH + 1)):
        reach = jnp.where(centre + ring_total[rho] >= BLOCK_TARGET, rho, reach)
    return reach


def block_walkers(points, grid: Grid, rows, reach, *, per_row: int = 16):
    """The walkers in the block of cells around each walker `rows`.

    **Returns:** `(ids (M, (2 MAX_REACH + 1) per_row), d2, r2 (M,), complete (M,))`: the
    block's walkers other than the walker itself (padding N), their squared distances (inf
    on padding), the squared radius r^2 = (rho cell sides)^2 within which every walker is in
    the block, and whether every block row fitted in `per_row` slots."""
    n = points.shape[0]
    g = grid.cells
    safe = jnp.clip(rows, 0, n - 1)
    column, row = grid.cell[safe, 0], grid.cell[safe, 1]
    lo_col = jnp.maximum(column - reach, 0)
    hi_col = jnp.minimum(column + reach, g - 1)
    dy = jnp.arange(-MAX_REACH, MAX_REACH + 1, dtype=jnp.int32)
    block_row = row[:, None] + dy
    live_row = (jnp.abs(dy) <= reach[:, None]) & (block_row >= 0) & (block_row < g)
    base = jnp.clip(block_row, 0, g - 1) * g
    begin = grid.start[base + lo_col[:, None]]
    end = grid.start[base + hi_col[:, None]] + grid.count[base + hi_col[:, None]]
    length = jnp.where(live_row, end - begin, 0)
    # The per_row slots centred on the walker's x (rows are sorted by x: a binary search).
    middle = _search_x(points, grid, points[safe, 0][:, None], begin, end)
    first = jnp.clip(middle - per_row // 2, begin, jnp.maximum(end - per_row, begin))
    t = jnp.arange(per_row, dtype=jnp.int32)
    position = first[..., None] + t
    taken = live_row[..., None] & (position < end[..., None])
    ids = jnp.where(taken, grid.order[jnp.clip(position, 0, n - 1)], n)
    radius = jnp.minimum(
        _block_radius(points, grid, safe, reach),
        _window_radius(points, grid, safe, first, end, begin, per_row, live_row),
    )
    ids = ids.reshape(rows.shape[0], -1)
    centre = points.at[rows].get(mode="fill", fill_value=jnp.nan)
    d2 = jnp.sum((points.at[ids].get(mode="fill", fill_value=jnp.inf) - centre[:, None, :]) ** 2, axis=-1)
    d2 = jnp.where((ids == rows[:, None]) | (ids >= n) | jnp.isnan(d2), jnp.inf, d2)
    return jnp.where(jnp.isfinite(d2), ids, n), d2, radius**2, jnp.all(length <= per_row, axis=1)


def _search_x(points, grid: Grid, x, begin, end):
    """First position in [begin, end) of `grid.order` whose walker has x-coordinate >= x."""

    def halve(_, bounds):
        lo, hi = bounds
        mid = (lo + hi) // 2
        left = (mid < hi) & (points[grid.order[jnp.clip(mid, 0, points.shape[0] - 1)], 0] < x)
        return jnp.where(left, mid + 1, lo), jnp.where(left, hi, mid)

    steps = max(1, math.ceil(math.log2(points.shape[0] + 1)))
    return jax.lax.fori_loop(0, steps, halve, (begin, end))[0]


def _block_radius(points, grid: Grid, rows, reach):
    """Distance from each walker to the edge of its block (no edge where the block reaches
    the grid's edge: no walker lies beyond)."""
    cell = grid.cell[rows]
    lo_cell, hi_cell = cell - reach[:, None], cell + reach[:, None] + 1
    lo_edge = grid.lower + lo_cell.astype(points.dtype) * grid.side
    hi_edge = grid.lower + hi_cell.astype(points.dtype) * grid.side
    x = points[rows]
    to_lo = jnp.where(lo_cell > 0, x - lo_edge, jnp.inf)
    to_hi = jnp.where(hi_cell < grid.cells, hi_edge - x, jnp.inf)
    return jnp.minimum(jnp.min(to_lo, axis=1), jnp.min(to_hi, axis=1))


def _window_radius(points, grid: Grid, rows, first, end, begin, per_row: int, live_row):
    """Per walker, the smallest horizontal distance from it to the edge of a window that cut
    its block row short (inf where no row was cut)."""
    x = points[rows, 0][:, None]
    last = first + per_row - 1
    x_first = points[grid.order[jnp.clip(first, 0, points.shape[0] - 1)], 0]
    x_last = points[grid.order[jnp.clip(last, 0, points.shape[0] - 1)], 0]
    cut_left = live_row & (first > begin)
    cut_right = live_row & (last < end - 1)
    gap = jnp.minimum(jnp.where(cut_left, x - x_first, jnp.inf), jnp.where(cut_right, x_last - x, jnp.inf))
    return jnp.min(jnp.maximum(gap, 0.0), axis=1)


def within(ids, d2, lo2, hi2, width: int, n: int) -> tuple[Int[Array, "M w"], Bool[Array, " M"]]:
    """The entries with lo2 <= d2 < hi2 (per row) packed into `width` slots in their order
    (padding n); and whether they all fitted."""
    take = (d2 >= lo2[:, None]) & (d2 < hi2[:, None])
    slot = jnp.cumsum(take, axis=1, dtype=jnp.int32) - 1
    m = ids.shape[0]
    out = jnp.full((m, width + 1), n, ids.dtype)
    out = out.at[jnp.arange(m, dtype=jnp.int32)[:, None], jnp.where(take & (slot < width), slot, width)].set(ids)
    return out[:, :width], jnp.sum(take, axis=1, dtype=jnp.int32) <= width
