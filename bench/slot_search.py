"""The 3D dual's neighbour-slot search on the CPU (issue 62): where each simplex edge sits in its
walker's neighbour row, for rows of random walkers (random ids, as a user's swarm has them).

Compares the binary search `jaxgeom.geometry._dual._find_slots` does (log2 K gathers per edge),
over all edges at once and in blocks of simplices as `_in_blocks` runs it, with comparing each
edge against its whole row. Medians of warm calls; the arrays are arguments (as constants XLA
would fold the searches). Writes bench/results/slot_search.json. Run alone:
    .venv/bin/python bench/slot_search.py [--n 1000000]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary, timed

K = 40  # the neighbour capacity of a uniform 3D periodic graph
EDGES_PER_WALKER = 42  # simplex edges, counted once per side: ~6.8 simplices x 6 edges per walker


def binary(keys, rows, wanted):
    """The first place in each row whose key is >= the wanted one (`_find_slots`' search)."""
    base = rows * K
    lower, upper = jnp.zeros_like(base), jnp.full_like(base, K)
    for _ in range(K.bit_length()):
        middle = (lower + upper) // 2
        below = keys[base + jnp.minimum(middle, K - 1)] < wanted
        lower, upper = jnp.where(below, middle + 1, lower), jnp.where(below, upper, middle)
    return lower


def whole_row(keys, rows, wanted):
    """The same place, from comparing each edge with its whole row."""
    return jnp.sum(keys.reshape(-1, K)[rows] < wanted[:, None], axis=1, dtype=jnp.int32)


def in_blocks(search, size: int):
    """`search` over blocks of `size` edges (`lax.map`), as the dual's blocks of simplices run it."""

    def run(keys, rows, wanted):
        blocks = rows.shape[0] // size
        cut = lambda a: a[: blocks * size].reshape(blocks, size)  # noqa: E731
        return jax.lax.map(lambda part: search(keys, *part), (cut(rows), cut(wanted))).ravel()

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=1_000_000, help="walkers")
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    keys = np.sort(rng.integers(0, 27 * args.n, (args.n, K)).astype(np.int32), axis=1)
    edges = EDGES_PER_WALKER * args.n
    rows = rng.integers(0, args.n, edges).astype(np.int32)
    wanted = keys[rows, rng.integers(0, 30, edges)]
    arrays = (jnp.asarray(keys.ravel()), jnp.asarray(rows), jnp.asarray(wanted))
    print(f"N = {args.n}, K = {K}, {edges} edge ends; sorted rows {keys.nbytes / 2**20:.0f} MiB")
    cases = {
        "binary search, all edges at once": binary,
        "binary search, blocks of 8192 simplices": in_blocks(binary, 8192 * 6),
        "binary search, blocks of 32768 simplices": in_blocks(binary, 32768 * 6),
        "whole row, all edges at once": whole_row,
    }
    expected, rows_out = None, {}
    for name, fn in cases.items():
        jitted = jax.jit(fn)
        call = lambda: jitted(*arrays)  # noqa: E731
        found = np.asarray(call())
        expected = found if expected is None else expected
        assert np.array_equal(found[: len(expected)], expected[: len(found)]), name
        s = summary([timed(call) for _ in range(args.repeat)])
        rows_out[name] = s
        print(f"{name:<42} {s['median']:.3f} s ({s['min']:.3f}-{s['max']:.3f})")
    result = {
        "n": args.n,
        "k": K,
        "edge_ends": edges,
        "seconds": rows_out,
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d"),
    }
    out = Path(__file__).parent / "results" / "slot_search.json"
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
