"""Pieces both trainers share: the run folder of a run (lock, details file, disk failures),
the train-state plumbing (create replicated, resume, copy to the host, the NaN stop). Where
the data is: :mod:`gac_jax.builders.datasets`."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import jax
import numpy as np
import optax

from gac_jax.data.io_errors import DiskWriteError, describe, disk_failure
from gac_jax.training import parallel, run_log, workdir_lock
from gac_jax.training.checkpointing import Checkpoints, complete_steps
from gac_jax.training.metrics_writer import Progress
from gac_jax.training.step_runner import StepRunner
from gac_jax.training.train_state import TrainState


class NonFiniteLossError(RuntimeError):
    """Training produced NaN/inf; the last good checkpoint is kept."""


@contextlib.contextmanager
def training_run(workdir: Path) -> Iterator[None]:
    """The run folder during a training run.

    * Process 0 (the owner of the folder) holds its lock
      (:mod:`gac_jax.training.workdir_lock`): a second writer stops at once.
    * Library diagnostics go to ``WORKDIR/details.log`` (:mod:`gac_jax.training.run_log`).
    * A disk failure anywhere (checkpoint, metrics, event files, result files) ends the run
      with one :class:`~gac_jax.data.io_errors.DiskWriteError`: the path, the reason, the
      free space, the last complete checkpoint (which a rerun resumes from) and the details
      file, where the traceback is.
    """
    index = jax.process_index()
    lock = workdir_lock.hold(workdir) if index == 0 else contextlib.nullcontext()
    with lock, run_log.library_logs_to(run_log.details_path(workdir, index)) as details:
        try:
            yield
        except Exception as e:
            failure = disk_failure(e)
            if failure is None:
                raise
            run_log.record_exception(e)
            what = failure.message or describe(failure, failure.path or workdir)
            steps = complete_steps(workdir / "checkpoints")
            kept = (
                f"kept checkpoint {steps[-1]} in {workdir / 'checkpoints'}"
                if steps
                else "no checkpoint was complete yet"
            )
            raise DiskWriteError(
                failure.errno, failure.path or workdir, f"{what}; {kept} (details in {details})"
            ) from e


def create_train_state(
    variables: dict, tx: optax.GradientTransformation, seed: int, mesh
) -> tuple[TrainState, TrainState]:
    """A fresh :class:`TrainState` replicated over ``mesh`` and its sharding pytree.

    Args:
      variables: ``{'params', 'batch_stats'}`` of the freshly initialised model.
    Returns:
      ``(state, state_sharding)``; the sharding tree is what the jitted step takes as
      ``in_shardings`` / ``out_shardings`` for the state.
    """
    replicated = parallel.replicated(mesh)
    state = jax.jit(
        lambda v: TrainState.create(v["params"], v["batch_stats"], tx, seed),
        out_shardings=replicated,
    )(variables)
    return state, jax.tree.map(lambda _: replicated, state)


def step_telemetry(
    config, train_step, mesh, workdir: Path, total_steps: int, start_step: int
) -> tuple[Progress, StepRunner]:
    """The progress line (loss, images/s, the device's wait for data, ETA) and the
    :class:`~gac_jax.training.step_runner.StepRunner` of ``train_step`` (compiled ahead of
    time with its memory line, ``train.profile_steps``, out-of-memory as one line)."""
    is_main = jax.process_index() == 0
    progress = Progress(
        total_steps,
        start_step,
        config.data.batch_size,
        enabled=is_main,
        num_workers=config.data.num_workers,
    )
    steps = StepRunner(
        train_step,
        mesh,
        batch_size=config.data.batch_size,
        profile_steps=config.train.get("profile_steps"),
        tensorboard_dir=workdir / "tensorboard",
        announce=is_main,
    )
    return progress, steps


def restore_latest(
    checkpoints: Checkpoints, state: TrainState, announce: bool = True
) -> tuple[TrainState, int, dict]:
    """Resumes from the latest checkpoint if there is one: ``(state, start_step, meta)``.

    ``state`` is the freshly created state whose shapes and shardings the restore follows;
    it is returned unchanged (with step 0 and empty meta) when the workdir holds none.
    """
    if checkpoints.latest_step() is None:
        return state, 0, {}
    state, meta = checkpoints.restore(state)
    start_step = int(meta["step"])
    if announce:
        print(f"resumed from {checkpoints.directory} at step {start_step}", flush=True)
    return state, start_step, meta


def host_variables(state: TrainState) -> dict:
    """Numpy copies of the (replicated) ``params`` and ``batch_stats`` of this process."""
    return jax.tree.map(
        lambda x: np.asarray(x.addressable_data(0)),
        {"params": state.params, "batch_stats": state.batch_stats},
    )


def check_finite(state: TrainState, step: int, checkpoints: Checkpoints, loss=None) -> None:
    """Raises :class:`NonFiniteLossError` when a step so far (or ``loss``) was NaN/inf.

    The message names the step and the last good checkpoint, which stays on disk.
    """
    bad_loss = loss is not None and not np.isfinite(loss)
    if bool(jax.device_get(state.nonfinite)) or bad_loss:
        what = (
            f"non-finite loss at step {step} (loss={loss})"
            if loss is not None
            else (f"non-finite loss or gradient before step {step}")
        )
        raise NonFiniteLossError(
            f"{what}; training stopped. The last good checkpoint (step "
            f"{checkpoints.latest_step()}) in {checkpoints.directory} is kept."
        )
