"""A trained depth network of a run folder: config, model and checkpoint weights."""

from __future__ import annotations

from pathlib import Path

import jax

from gac_jax.data.files import KittiFormatError
from gac_jax.trained.run_config import load_workdir_config
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.training.train_state import TrainState, learning_rate_schedule, make_optimizer


def restore_depth_model(workdir: str | Path, step: int | None = None):
    """``(config, model, variables, step)`` of a depth workdir's checkpoint (default: latest).

    The train state is restored into a template built with ``jax.eval_shape`` (nothing is
    initialised); only ``params`` and ``batch_stats`` are returned, as host arrays.
    """
    from gac_jax.builders import depth as builders

    workdir = Path(workdir)
    config = load_workdir_config(workdir)
    try:
        prior_mean = builders.read_prior_mean(workdir)
    except FileNotFoundError as e:
        raise KittiFormatError(workdir / builders.PRIOR_FILE, str(e)) from None
    model = builders.build_model(config, prior_mean)
    # The optimizer only shapes the template's opt_state: any schedule of the same kind.
    tx = make_optimizer(
        learning_rate_schedule(1.0, 1.0, 1), config.train.clip_norm, config.train.weight_decay
    )
    abstract = jax.eval_shape(
        lambda: TrainState.create(**builders.init_variables(model, config, 0), tx=tx, seed=0)
    )
    step = checkpoint_step(workdir, step)
    with Checkpoints(workdir) as checkpoints:
        state, meta = checkpoints.restore(abstract, step)
    variables = jax.tree.map(
        jax.device_get, {"params": state.params, "batch_stats": state.batch_stats}
    )
    return config, model, variables, int(meta["step"])


def checkpoint_step(workdir: str | Path, step: int | None = None) -> int:
    """The checkpoint ``step`` of a workdir (default: the latest), checked to exist; reads no
    weights.

    Raises:
      KittiFormatError: no checkpoint, or none at ``step`` (listing those there are).
    """
    with Checkpoints(Path(workdir)) as checkpoints:
        available = checkpoints.all_steps()
        if not available or (step is not None and step not in available):
            raise KittiFormatError(
                checkpoints.directory,
                f"no checkpoint {'at step ' + str(step) if step is not None else ''} "
                f"(have {available})",
            )
    return step if step is not None else max(available)
