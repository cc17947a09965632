"""XLA's CPU sort by operand count (issue 62: the 3D vertex counts' sort).

Sorts M random (cell, projection) entries as the 3D vertex counts need them: the (int32 cell,
float projection, int32 entry) triple by two keys, as before; a packed uint32 key with the
entry as payload; one uint32 operand alone (each radix pass of
`jaxgeom.geometry._dual._order_by_cell_and_projection` off the CPU); that operand by numpy
through a callback and by numpy alone; the packed key's stable order by numpy in one uint64
(`jaxgeom.geometry._dual._order_by_key`, what the CPU backend runs); and the whole order.
Medians of warm calls. Run alone:
    .venv/bin/python bench/xla_sorts.py [--m 2900000] [--n 100000]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from _timing import summary, timed

from jaxgeom.geometry._dual import _order_by_cell_and_projection, _order_by_key


def numpy_sorted(values):
    """`lax.sort` of one operand by numpy through a callback."""
    return jax.pure_callback(np.sort, jax.ShapeDtypeStruct(values.shape, values.dtype), values)


def pack(cells, projection):
    """(cell, projection in [-1, 1] cut into 2^15 quanta) in one uint32."""
    return (cells.astype(jnp.uint32) << 15) | jnp.floor((projection + 1) * 16383.5).astype(jnp.uint32)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--m", type=int, default=2_900_000, help="entries (4 per tetrahedron)")
    parser.add_argument("--n", type=int, default=100_000, help="cells")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    cells = jnp.asarray(rng.integers(0, args.n, args.m), jnp.int32)
    projection = jnp.asarray(rng.uniform(-1, 1, args.m), jnp.float32)
    entry = jnp.arange(args.m, dtype=jnp.int32)
    cases = {
        "(cell, projection, entry), 2 keys": lambda c, p, e: jax.lax.sort((c, p, e), num_keys=2),
        "(packed uint32, entry), 1 key": lambda c, p, e: jax.lax.sort((pack(c, p), e), num_keys=1),
        "one uint32 operand": lambda c, p, e: jax.lax.sort(pack(c, p)),
        "one uint32 operand, numpy callback": lambda c, p, e: numpy_sorted(pack(c, p)),
        "packed key's order, _order_by_key": lambda c, p, e: _order_by_key(pack(c, p)),
        "the vertex counts' order": lambda c, p, e: _order_by_cell_and_projection(c, p, jnp.ones_like(p), args.n)[0],
    }
    for name, fn in cases.items():  # the arrays are arguments: as constants XLA would fold the sorts
        jitted = jax.jit(fn)
        call = lambda: jitted(cells, projection, entry)  # noqa: E731
        timed(call)
        s = summary([timed(call) for _ in range(args.repeat)])
        print(f"{name:<36} {s['median']:.3f} s ({s['min']:.3f}-{s['max']:.3f})")
    packed = np.asarray(pack(cells, projection))
    s = summary([timed(lambda: np.sort(packed)) for _ in range(args.repeat)])
    print(f"{'one uint32 operand, numpy alone':<36} {s['median']:.3f} s ({s['min']:.3f}-{s['max']:.3f})")


if __name__ == "__main__":
    main()
