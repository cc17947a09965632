"""Work split over devices with `jax.shard_map`, two ways.

- Ensembles: a leading batch axis (swarms, seeds) split over a 1-D mesh named "batch". Each
  device runs its own lanes under `vmap`, so a lane's work, Qhull callbacks included, never
  leaves its device, and the results equal the unsharded `vmap` (bitwise on CPU: each lane
  runs the same program).
- One large swarm: the walker axis split over a 1-D mesh named "walkers". The per-walker
  arrays of the state live split over the devices; the device rebuild's per-cell work (each
  cell clipped from the gathered positions) runs for each device's own rows (`split_rows`),
  and XLA's partitioner splits the step's per-walker kernels, gathering neighbours' rows and
  reducing the swarm-wide sums across devices."""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"
WALKER_AXIS = "walkers"


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named "batch" over `devices` (default: every device of the default backend,
    every process's in a multi-host run)."""
    return Mesh(np.array(_device_list(devices)), (BATCH_AXIS,))


def walker_mesh(devices=None) -> Mesh:
    """A 1-D mesh named "walkers" over `devices` (default: every device of the default
    backend), to split one swarm's walkers (`simulate(..., mesh=walker_mesh())`)."""
    return Mesh(np.array(_device_list(devices)), (WALKER_AXIS,))


def _device_list(devices) -> list:
    """`devices` (None: jax.devices()) as a non-empty list of distinct JAX devices."""
    if devices is None:
        return jax.devices()
    if isinstance(devices, (str, bytes)) or not hasattr(devices, "__iter__"):
        raise TypeError(
            f"`devices` must be a sequence of JAX devices (e.g. jax.devices()[:2]) or None; got "
            f"{devices!r}. For a platform's devices use jax.devices('cpu')."
        )
    devices = list(devices)
    if not devices:
        raise ValueError("`devices` is empty; give at least one device (jax.devices()).")
    strange = [d for d in devices if not isinstance(d, jax.Device)]
    if strange:
        raise TypeError(f"`devices` must hold JAX devices (jax.devices()); got {strange[0]!r}.")
    if len({id(d) for d in devices}) < len(devices):
        raise ValueError(
            f"`devices` lists a device more than once ({devices}); each device can hold one part of the mesh."
        )
    return devices


def check_mesh(mesh, batch: int | None, what: str, axis: str = BATCH_AXIS) -> None:
    """Refuse a mesh that is not a `jax.sharding.Mesh` with an axis `axis` dividing `batch`
    (any length when `batch` is None)."""
    if mesh is None:
        return
    maker = "jaxgeom.batch_mesh()" if axis == BATCH_AXIS else "jaxgeom.walker_mesh()"
    if not isinstance(mesh, Mesh):
        raise TypeError(f"`mesh` must be a jax.sharding.Mesh ({maker}) or None; got {type(mesh).__name__}.")
    if axis not in mesh.axis_names:
        raise ValueError(f"`mesh` must have an axis named {axis!r} ({maker}); got {mesh.axis_names}.")
    size = mesh.shape[axis]
    if batch is not None and batch % size:
        raise ValueError(
            f"{what} = {batch} must be a multiple of the mesh's {size} devices along {axis!r}; "
            f"use {size * -(-batch // size)} or a mesh over fewer devices."
        )


def over_batch(fn, mesh: Mesh | None):
    """g(batched, shared) = fn over the leading axis of every leaf of `batched` (vmap), `shared`
    the same for every lane; split over `mesh`'s batch axis when a mesh is given."""
    lanes = jax.vmap(fn, in_axes=(0, None))
    if mesh is None:
        return lanes
    return jax.shard_map(
        lanes,
        mesh=mesh,
        in_specs=(PartitionSpec(BATCH_AXIS), PartitionSpec()),
        out_specs=PartitionSpec(BATCH_AXIS),
        check_vma=False,
    )


def shard_batch(tree, mesh: Mesh):
    """Place every array of `tree` with its leading axis split over the mesh's batch axis. In a
    multi-process run every process passes the same whole batch (built from the same seeds) and
    keeps the lanes of its own devices."""
    leaves = jax.tree_util.tree_leaves(tree)
    check_mesh(mesh, int(np.shape(leaves[0])[0]) if leaves and np.ndim(leaves[0]) else None, "the batch size B")
    if mesh is None:
        raise TypeError("`mesh` must be a jax.sharding.Mesh (jaxgeom.batch_mesh()); got None.")
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(place, tree)


def shard_walkers(tree, mesh: Mesh, n: int):
    """Place every array of `tree` whose leading axis has length `n` (the walkers) split over
    the mesh's "walkers" axis, every other array (simplices, scalars, keys) whole on each device."""
    split, whole = NamedSharding(mesh, PartitionSpec(WALKER_AXIS)), NamedSharding(mesh, PartitionSpec())

    def place(leaf):
        if not isinstance(leaf, jax.Array):
            return leaf
        return jax.device_put(leaf, split if leaf.ndim and leaf.shape[0] == n else whole)

    return jax.tree_util.tree_map(place, tree)


def split_rows(fn, mesh: Mesh | None, rows, n: int, *shared):
    """`fn(rows, *shared)`, a computation whose outputs have one row per entry of `rows` (padding
    `n`), with the rows dealt round-robin over the mesh's "walkers" axis (so a list whose live
    rows come first still spreads them evenly) and `shared` whole on every device. Each output
    row is computed from the same inputs as without a mesh."""
    if mesh is None:
        return fn(rows, *shared)
    devices, m = mesh.shape[WALKER_AXIS], rows.shape[0]
    per_device = -(-m // devices)
    padded = jax.numpy.pad(rows, (0, per_device * devices - m), constant_values=n)
    dealt = padded.reshape(per_device, devices).T.reshape(-1)  # device d: rows d, d + D, ...
    out = jax.shard_map(
        fn,
        mesh=mesh,
        in_specs=(PartitionSpec(WALKER_AXIS),) + (PartitionSpec(),) * len(shared),
        out_specs=PartitionSpec(WALKER_AXIS),
        check_vma=False,
    )(dealt, *shared)

    def undeal(a):
        a = a.reshape((devices, per_device) + a.shape[1:]).swapaxes(0, 1)
        return a.reshape((per_device * devices,) + a.shape[2:])[:m]

    return jax.tree_util.tree_map(undeal, out)
