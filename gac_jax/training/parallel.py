"""Data parallelism with ``jax.jit`` over a one-axis device mesh (no pmap).

The same code runs on 1 CPU, N local devices and N processes (hosts):
parameters are replicated, every batch array is sharded along its leading
axis over the mesh axis ``'data'``, and XLA inserts the collectives. Losses
computed on the global (sharded) batch are therefore identical to a
single-device run on the same global batch. Starting, coordinating and
supervising several processes is :mod:`gac_jax.training.multiprocess`.
"""

from __future__ import annotations

from collections.abc import Mapping

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

DATA_AXIS = "data"


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh with axis ``'data'`` over all (global) devices, grouped by process."""
    if devices is None:
        devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
    return Mesh(np.asarray(devices), (DATA_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P())


def data_sharded(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, P(DATA_AXIS))


def check_batch_size(global_batch_size: int, mesh: Mesh) -> int:
    """Validates the global batch size and returns this process's share of it."""
    n_dev, n_proc = mesh.devices.size, jax.process_count()
    if global_batch_size % n_dev:
        raise ValueError(
            f"global batch size {global_batch_size} is not divisible by the {n_dev} mesh devices"
        )
    return global_batch_size // n_proc


def process_shard(mesh: Mesh) -> tuple[int, int]:
    """``(shard_index, num_shards)`` of this process's rows of every global batch.

    :func:`to_global` places a process's local batch at the rows of its devices
    in the mesh, so the loader must read shard ``k`` of ``n`` where ``k`` is the
    position of this process's (contiguous) block of devices along ``'data'``.
    """
    owners = [d.process_index for d in mesh.devices.flat]
    n = jax.process_count()
    block = len(owners) // n
    if block * n != len(owners) or any(
        owners[i] != owners[i - i % block] for i in range(len(owners))
    ):
        raise ValueError(
            f"the mesh devices of each process must form equal contiguous blocks, got owners "
            f"{owners}; build the mesh with gac_jax.training.parallel.make_mesh()"
        )
    starts = [i for i in range(0, len(owners), block) if owners[i] == jax.process_index()]
    if len(starts) != 1:
        raise ValueError(f"process {jax.process_index()} owns {len(starts)} blocks of {owners}")
    return starts[0] // block, n


def to_global(batch: Mapping[str, np.ndarray], mesh: Mesh) -> dict[str, jax.Array]:
    """Builds globally sharded arrays from this process's slice of the batch.

    Non-numeric entries (frame ids) stay on the host and are dropped here.
    """
    sharding = data_sharded(mesh)
    out = {}
    for key, value in batch.items():
        arr = np.asarray(value)
        if arr.dtype.kind in "biuf":
            out[key] = jax.make_array_from_process_local_data(sharding, arr)
    return out


def to_host(tree):
    """Fetches (fully addressable or replicated) arrays to numpy."""
    return jax.tree.map(lambda x: np.asarray(jax.device_get(x)), tree)
