"""Pieces both trainers share: the train-state plumbing (create replicated, resume, copy to
the host, the NaN stop). Where the data is: :mod:`gac_jax.builders.datasets`."""

from __future__ import annotations

import jax
import numpy as np
import optax

from gac_jax.training import parallel
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.training.train_state import TrainState


class NonFiniteLossError(RuntimeError):
    """Training produced NaN/inf; the last good checkpoint is kept."""


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
