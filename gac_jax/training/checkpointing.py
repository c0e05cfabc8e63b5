"""Orbax checkpoints in ``WORKDIR/checkpoints``: keep the last N, resume from the latest.

Each checkpoint holds the train state pytree (``state``) and a small JSON
document (``meta``: step, task, config digest ...). Saving is collective: in a
multi-process run every process calls :meth:`Checkpoints.save` and orbax
writes one copy. Restoring uses the *current* shardings of an abstract state,
so a checkpoint written by N processes can be restored by M.

The trainer's instance is the *writer* (``writer=True``): it removes the temporary folders
(``N.orbax-checkpoint-tmp*``) that an interrupted or failed save left behind, checks before
each save that the disk has room for a checkpoint of the size of the last one, and turns a
failed write (a full disk, in orbax's background threads) into one
:class:`~gac_jax.data.io_errors.DiskWriteError` naming the checkpoint, after removing its
partial folder; the library noise of the failure goes to the run's details file
(:mod:`gac_jax.training.run_log`). Readers (evaluation, export, tests) never touch
temporary folders: a save may be in progress.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from pathlib import Path
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from gac_jax.data.io_errors import DiskWriteError, describe, disk_failure, free_bytes, megabytes
from gac_jax.training import multiprocess, run_log

VARIABLE_COLLECTIONS = ("params", "batch_stats")
TMP_MARKER = ".orbax-checkpoint-tmp"
SPACE_MARGIN = 1.05  # a save needs the size of the last checkpoint, plus this much headroom


def complete_steps(directory: str | os.PathLike) -> list[int]:
    """Steps of the finished checkpoints in ``directory`` (orbax renames a checkpoint's
    temporary folder to its step number when the save is complete)."""
    try:
        names = [p.name for p in Path(directory).iterdir() if p.is_dir()]
    except OSError:
        return []
    return sorted(int(n) for n in names if n.isdigit())


def folder_bytes(path: str | os.PathLike) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for name in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, name)).st_size
    return total


class Checkpoints:
    def __init__(self, workdir: str | os.PathLike, max_to_keep: int = 3, writer: bool = False):
        self.directory = Path(workdir).resolve() / "checkpoints"
        self.writer = writer
        self._size: tuple[int, int] | None = None  # (step, bytes) of the last complete one
        if writer:  # it holds the run folder: no other save can be in progress
            self._remove_partial(None)
        options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True)
        if jax.process_count() > 1:
            options.async_options = ocp.AsyncOptions(barrier_sync_fn=_barrier_or_exit())
        self._manager = ocp.CheckpointManager(self.directory, options=options)

    def latest_step(self) -> int | None:
        return self._manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self._manager.all_steps())

    def save(self, step: int, state: Any, meta: dict | None = None, wait: bool = True) -> None:
        args = ocp.args.Composite(
            state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(dict(meta or {}, step=step))
        )
        if self.writer:
            self._check_space(step)
        watch = multiprocess.watch_peers(f"while checkpoint {step} was saved")
        with watch, self._failed_write_as_error(step):
            self._manager.save(step, args=args, force=True)
            if wait:
                self._manager.wait_until_finished()

    def restore(self, abstract_state: Any, step: int | None = None) -> tuple[Any, dict]:
        """Restores ``step`` (default: latest) into the shardings of ``abstract_state``."""
        step = self._existing_step(step)
        target = jax.tree.map(_abstract, abstract_state)
        restored = self._manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target), meta=ocp.args.JsonRestore()
            ),
        )
        return restored.state, dict(restored.meta)

    def restore_local(self, step: int | None = None) -> tuple[dict, dict]:
        """Restores ``step`` (default: latest) as numpy arrays, whatever topology wrote it.

        A checkpoint records the shardings of the run that saved it (e.g. a mesh
        over two processes); this reads it onto this process's first device
        instead, e.g. to inspect or evaluate a multi-host run on one machine.
        Returns ``(state, meta)`` with ``state`` a nested dict of the train
        state's fields. For single-process use.
        """
        step = self.latest_step() if step is None else step
        if step is None or step not in self.all_steps():
            raise FileNotFoundError(f"checkpoint step {step} not found in {self.directory}")
        device = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        with ocp.StandardCheckpointer() as reader:
            stored = reader.metadata(self.directory / str(step) / "state").item_metadata
        target = jax.tree.map(
            lambda m: jax.ShapeDtypeStruct(m.shape, m.dtype, sharding=device), stored
        )
        restored = self._manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target), meta=ocp.args.JsonRestore()
            ),
        )
        return jax.tree.map(np.asarray, dict(restored.state)), dict(restored.meta)

    def restore_variables(self, step: int | None = None) -> dict[str, Any]:
        """The model variables ``{'params', 'batch_stats'}`` of ``step`` (default: latest).

        Reads only those two collections of the stored ``state`` (a training state or
        converted weights), as host numpy arrays with their stored dtypes; no template,
        optimizer or device is needed (inference, export).
        """
        step = self._existing_step(step)
        options = ocp.CheckpointManagerOptions(create=False)
        handlers = {"state": ocp.PyTreeCheckpointHandler(), "meta": ocp.JsonCheckpointHandler()}
        with ocp.CheckpointManager(self.directory, options=options, item_handlers=handlers) as m:
            tree = m.item_metadata(step)["state"].tree
            if "params" not in tree:
                raise KeyError(
                    f"checkpoint {step} in {self.directory} has no 'params' in its state"
                )
            subtree = {c: tree[c] for c in VARIABLE_COLLECTIONS if c in tree}
            item = jax.tree.map(lambda x: np.empty(x.shape, x.dtype), subtree)
            restore_args = jax.tree.map(lambda _: ocp.RestoreArgs(restore_type=np.ndarray), item)
            args = ocp.args.PyTreeRestore(
                item=item, restore_args=restore_args, partial_restore=True
            )
            composite = ocp.args.Composite(state=args, meta=ocp.args.JsonRestore())
            restored = m.restore(step, args=composite).state
        variables = {c: restored.get(c, {}) for c in VARIABLE_COLLECTIONS}
        return jax.tree.map(np.asarray, variables)

    def _existing_step(self, step: int | None) -> int:
        step = self.latest_step() if step is None else step
        if step is None:
            raise FileNotFoundError(f"no checkpoint found in {self.directory}")
        if step not in self.all_steps():
            raise FileNotFoundError(
                f"checkpoint step {step} not found in {self.directory} (have {self.all_steps()})"
            )
        return step

    def restore_meta(self, step: int | None = None) -> dict:
        step = self.latest_step() if step is None else step
        restored = self._manager.restore(step, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
        return dict(restored.meta)

    def wait(self) -> None:
        with self._failed_write_as_error(None):
            self._manager.wait_until_finished()

    def checkpoint_bytes(self) -> int | None:
        """Size of the latest complete checkpoint on disk (None when there is none)."""
        steps = complete_steps(self.directory)
        if not steps:
            return None
        if self._size is None or self._size[0] != steps[-1]:
            self._size = (steps[-1], folder_bytes(self.directory / str(steps[-1])))
        return self._size[1]

    def _check_space(self, step: int) -> None:
        """Refuses to start a save that cannot fit (the size of the last checkpoint, known
        from the disk, against the free space); the first save of a folder is not checked."""
        needed, free = self.checkpoint_bytes(), free_bytes(self.directory)
        if needed is None or free is None or free >= needed * SPACE_MARGIN:
            return
        path = self.directory / str(step)
        raise DiskWriteError(
            errno.ENOSPC,
            path,
            f"{path}: not enough space for checkpoint {step} ({megabytes(free)} free, a "
            f"checkpoint takes about {megabytes(needed)})",
        )

    @contextlib.contextmanager
    def _failed_write_as_error(self, step: int | None):
        """Inside: library noise goes to the run's details file; a disk failure of the save
        removes the partial checkpoint and raises one DiskWriteError naming it."""
        with run_log.capture_stderr():
            try:
                yield
            except Exception as e:
                failure = disk_failure(e)
                if failure is None or isinstance(e, DiskWriteError):
                    raise
                run_log.record_exception(e)
                with contextlib.suppress(Exception):
                    self._manager.close()  # let the background threads end, here
                run_log.settle()  # and the tracebacks of writes still in flight
                path = self.directory / str(step) if step is not None else self.directory
                message = describe(failure, path)  # the free space when it failed
                self._remove_partial(step)
                raise DiskWriteError(failure.errno, path, message) from e

    def _remove_partial(self, step: int | None) -> None:
        """Removes the temporary folder of the failed save of ``step`` (all when None)."""
        if jax.process_index() != 0:
            return  # process 0 owns the folder (orbax's primary host)
        pattern = f"{step}{TMP_MARKER}*" if step is not None else f"*{TMP_MARKER}*"
        for partial in self.directory.glob(pattern):
            shutil.rmtree(partial, ignore_errors=True)

    def close(self) -> None:
        self._manager.close()

    def __enter__(self) -> Checkpoints:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _barrier_or_exit():
    """orbax's cross-process barrier, ending the process cleanly when a peer is lost there.

    The asynchronous save waits at such barriers in a background thread; a peer that
    died meanwhile is noticed by :func:`gac_jax.training.multiprocess.watch_peers` (half the
    heartbeat timeout, before JAX's own detection aborts the process) or by the failed
    barrier, and reported in one line with the exit status of a peer lost during a step. The
    unfinished checkpoint stays a temporary folder that is never restored.
    """
    barrier = ocp.multihost.get_barrier_sync_fn()

    def barrier_sync_fn(*, key: str, timeout_ms: int) -> None:
        try:
            with multiprocess.watch_peers(f"at checkpoint barrier {key}"):
                barrier(key=key, timeout_ms=timeout_ms)
        except Exception as e:
            if multiprocess.is_peer_failure(e):
                multiprocess.exit_peer_lost(f"checkpoint barrier {key}: {e}")
            raise

    return barrier_sync_fn


def _abstract(x):
    if isinstance(x, jax.ShapeDtypeStruct):
        return x
    sharding = getattr(x, "sharding", None)
    return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding)
