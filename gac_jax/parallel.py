"""Data parallelism with ``jax.jit`` over a one-axis device mesh (no pmap).

The same code runs on 1 CPU, N local devices and N processes: parameters are
replicated, every batch array is sharded along its leading axis over the mesh
axis ``'data'``, and XLA inserts the collectives. Losses computed on the
global (sharded) batch are therefore identical to a single-device run on the
same global batch.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

DATA_AXIS = "data"


def initialize_distributed(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    initialization_timeout: int = 300,
) -> bool:
    """Starts the multi-process runtime when asked to; returns True if it did.

    Arguments fall back to the environment variables that cluster launchers
    set (``GAC_COORDINATOR``/``JAX_COORDINATOR_ADDRESS``, ``GAC_NUM_PROCESSES``/
    ``JAX_NUM_PROCESSES``, ``GAC_PROCESS_ID``/``JAX_PROCESS_ID``). Must run
    before anything touches a device. On CPU, cross-process collectives use gloo.
    """
    env = os.environ
    coordinator = coordinator or env.get("GAC_COORDINATOR") or env.get("JAX_COORDINATOR_ADDRESS")
    if num_processes is None:
        value = env.get("GAC_NUM_PROCESSES") or env.get("JAX_NUM_PROCESSES")
        num_processes = int(value) if value else None
    if process_id is None:
        value = env.get("GAC_PROCESS_ID") or env.get("JAX_PROCESS_ID")
        process_id = int(value) if value else None
    if coordinator is None and num_processes is None and process_id is None:
        return False
    if coordinator is None or num_processes is None or process_id is None:
        raise ValueError(
            "multi-process training needs all of --coordinator, --num-processes and --process-id "
            f"(got {coordinator=}, {num_processes=}, {process_id=})"
        )
    if num_processes == 1:
        return False
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=initialization_timeout,
    )
    return True


def make_mesh(devices=None) -> Mesh:
    """A 1-D mesh with axis ``'data'`` over all (global) devices."""
    devices = jax.devices() if devices is None else devices
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
