"""Ensembles over devices: a leading batch axis (swarms, seeds) split over a 1-D device mesh
with `jax.shard_map`. Each device runs its own lanes under `vmap`, so a lane's work, Qhull
callbacks included, never leaves its device, and the results equal the unsharded `vmap`
(bitwise on CPU: each lane runs the same program)."""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

BATCH_AXIS = "batch"


def batch_mesh(devices=None) -> Mesh:
    """A 1-D mesh named "batch" over `devices` (default: every device of the default backend,
    every process's in a multi-host run)."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("`devices` is empty; give at least one device (jax.devices()).")
    return Mesh(np.array(devices), (BATCH_AXIS,))


def check_mesh(mesh, batch: int, what: str) -> None:
    """Refuse a mesh that is not a `jax.sharding.Mesh` with a "batch" axis dividing `batch`."""
    if mesh is None:
        return
    if not isinstance(mesh, Mesh):
        raise TypeError(f"`mesh` must be a jax.sharding.Mesh (jaxgeom.batch_mesh()) or None; got {type(mesh).__name__}.")
    if BATCH_AXIS not in mesh.axis_names:
        raise ValueError(f"`mesh` must have an axis named {BATCH_AXIS!r} (jaxgeom.batch_mesh()); got {mesh.axis_names}.")
    size = mesh.shape[BATCH_AXIS]
    if batch % size:
        raise ValueError(f"{what} = {batch} must be a multiple of the mesh's {size} devices along {BATCH_AXIS!r}; "
                         f"use {size * -(-batch // size)} or a mesh over fewer devices.")


def over_batch(fn, mesh: Mesh | None):
    """g(batched, shared) = fn over the leading axis of every leaf of `batched` (vmap), `shared`
    the same for every lane; split over `mesh`'s batch axis when a mesh is given."""
    lanes = jax.vmap(fn, in_axes=(0, None))
    if mesh is None:
        return lanes
    return jax.shard_map(lanes, mesh=mesh, in_specs=(PartitionSpec(BATCH_AXIS), PartitionSpec()),
                         out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)


def shard_batch(tree, mesh: Mesh):
    """Place every array of `tree` with its leading axis split over the mesh's batch axis. In a
    multi-process run every process passes the same whole batch (built from the same seeds) and
    keeps the lanes of its own devices."""
    sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))

    def place(leaf):
        host = np.asarray(leaf)
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree_util.tree_map(place, tree)
