"""Trainer of the ground-aware depth U-Net: ``python train.py --task depth``.

Top to bottom: config -> mesh -> data -> prior mean -> model/optimizer -> restore ->
jitted step -> evaluator -> loop. One ``jax.jit`` train step over a ``Mesh(('data',))``
(batch sharded, parameters replicated), as the detection trainer.

Data: a KITTI-depth root (``data_depth_annotated/{train,val}`` + ``raw``; ``data.source =
'kitti'``) or the embedded generated scenes (``'synthetic'``: ``ROOT/depth`` of the dataset
:func:`~gac_jax.builders.datasets.prepare_dataset` generates, the detector's cache).
Training views: cameras 2 and 3, either both as items (``data.train_views='both'``) or one
random view per frame and epoch (``'random'``, the reference; :mod:`gac_jax.data.view_sampling`).
Transforms: keep the bottom ``crop_height`` rows, resize to ``height`` rows when smaller
(aspect kept; sparse GT resampled without mixing values), a random ``width``-column crop,
photometric distortion, horizontal flip (P mirrored) in training; the left ``eval_width``
columns (zero-padded when narrower) at test time.

The network regresses log depth around a constant ``prior_mean``: the mean log GT depth of
the training split (:func:`~gac_jax.models.depth_unet.mean_log_depth`), computed once and
kept in ``WORKDIR/prior_mean.json`` so a resumed run and ``evaluate.py`` use the same value.

Multi-process runs (docs/multihost.md) as the detection trainer: each process loads its rows of
every global batch, process 0 generates the data and computes the prior mean while the others
wait, evaluation runs on process 0 alone, a lost or hung peer stops the others
(:class:`~gac_jax.training.multiprocess.PeerLostError`) and SIGTERM stops all at the same step
after a checkpoint.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import ml_collections
import numpy as np

from gac_jax.builders.datasets import record_cache
from gac_jax.builders.depth import (
    PRIOR_FILE,
    build_model,
    depth_root,
    eval_source,
    init_variables,
    loss_options,
    make_evaluator,
    read_prior_mean,
    train_source,
    train_transform,
)
from gac_jax.config import save_config
from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.data.loader import DepthArrays, Loader
from gac_jax.data.view_sampling import RandomViewLoader, view_groups
from gac_jax.depth.depth_loss import depth_loss
from gac_jax.evaluation.depth_evaluator import NetworkPredictor, ground_truth_depth
from gac_jax.evaluation.depth_metrics import format_depth_table
from gac_jax.models.depth_unet import mean_log_depth
from gac_jax.trainers.common import (
    NonFiniteLossError,  # noqa: F401 - re-exported: callers catch depth.NonFiniteLossError
    check_finite,
    create_train_state,
    host_variables,
    restore_latest,
    step_telemetry,
    training_run,
)
from gac_jax.training import multiprocess, parallel, step_watchdog, stopping
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.training.compute_dtype import compute_dtype, training_model
from gac_jax.training.metrics_writer import MetricsWriter
from gac_jax.training.step_profiler import profile_range
from gac_jax.training.train_state import (
    TrainState,
    apply_gradients_guarded,
    learning_rate_schedule,
    make_optimizer,
)


def make_train_loader(config, source, per_process_batch: int, mesh) -> Loader:
    """This process's rows of every global batch (its block of ``mesh``, see
    :func:`gac_jax.training.parallel.process_shard`)."""
    d = config.data
    shard_index, num_shards = parallel.process_shard(mesh)
    arrays = DepthArrays(config.model.gac.camera_height)
    kwargs = dict(
        batch_size=per_process_batch,
        seed=config.seed,
        shard_index=shard_index,
        num_shards=num_shards,
        worker_count=d.num_workers,
    )
    if d.train_views == "random":
        frames = getattr(source, "frames", None)
        if frames is None:
            raise KittiFormatError(
                "<config>",
                "data.train_views='random' needs a KITTI-depth folder (a prepared TFDS dataset "
                "lists no frames); use data.train_views='both'",
            )
        return RandomViewLoader(
            source, view_groups(frames), train_transform(config), arrays, **kwargs
        )
    if d.train_views != "both":
        raise ValueError(f"data.train_views must be 'both' or 'random', got {d.train_views!r}")
    return Loader(source, train_transform(config), arrays, **kwargs)


def load_or_compute_prior_mean(config, source, workdir: Path) -> float:
    """``prior_mean`` from ``WORKDIR/prior_mean.json``, or computed from the training GT.

    Uses up to ``model.prior_max_frames`` items spread evenly over the split (0 = all) and
    the loss's depth range. In a multi-process run process 0 computes and writes while the
    others wait (with a timeout), then they read its file.
    """
    path = workdir / PRIOR_FILE
    with multiprocess.main_process_first("prior_mean"):
        if not path.exists() and multiprocess.is_main_process():
            n, limit = len(source), config.model.prior_max_frames
            index = np.arange(n) if not limit or limit >= n else np.linspace(0, n - 1, limit)
            picked = np.unique(index.round().astype(np.int64))
            maps = (ground_truth_depth(source, int(i)) for i in picked)
            value = mean_log_depth(maps, config.loss.min_depth, config.loss.max_depth)
            record = {"prior_mean": value, "num_items": len(picked)}
            with atomic_write(path) as f:
                json.dump(record, f, indent=2)
        return read_prior_mean(workdir)


def optimizer(config, total_steps: int, steps_per_epoch: int):
    """``(schedule, tx)``: Adam(W) with clipping on the configured (per-epoch) cosine."""
    t = config.train
    schedule = learning_rate_schedule(
        t.learning_rate,
        t.final_learning_rate,
        total_steps,
        steps_per_epoch if t.per_epoch_schedule else None,
        t.warmup_steps,
    )
    return schedule, make_optimizer(schedule, t.clip_norm, t.weight_decay)


def make_train_step(model, tx, loss_opts: dict, mesh, state_sharding):
    def train_step(state: TrainState, batch: dict):
        def loss_fn(params):
            outputs, mutated = model.apply(
                {"params": params, "batch_stats": state.batch_stats},
                batch["image"],
                batch["P2"],
                train=True,
                plane=batch.get("plane"),
                mutable=["batch_stats"],
            )
            loss, parts = depth_loss(
                outputs["log_depth"], batch["depth"], batch["image"], **loss_opts
            )
            return loss, (parts, mutated["batch_stats"])

        (loss, (parts, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params
        )
        new_state, grad_norm = apply_gradients_guarded(state, tx, grads, batch_stats, loss)
        return new_state, dict(parts, loss=loss, grad_norm=grad_norm)

    return jax.jit(
        train_step,
        in_shardings=(state_sharding, parallel.data_sharded(mesh)),
        out_shardings=(state_sharding, parallel.replicated(mesh)),
        donate_argnums=(0,),
    )


# ----------------------------------------------------------------------------- main


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str | Path) -> dict:
    """Trains (resuming from ``workdir`` if it holds checkpoints) and evaluates on val.

    The run holds ``workdir`` (its lock, details file and disk-failure report:
    :func:`~gac_jax.trainers.common.training_run`) from start to end.
    """
    workdir = Path(workdir)
    with training_run(workdir):
        return _train_and_evaluate(config, workdir)


def _train_and_evaluate(config: ml_collections.ConfigDict, workdir: Path) -> dict:
    is_main = jax.process_index() == 0
    compute_dtype(config)  # bad train.compute_dtype / profile_steps: one line, before any work
    profile_range(config.train.get("profile_steps"))
    train_transform(config)  # bad augmentation shares: one line, too
    if is_main:
        workdir.mkdir(parents=True, exist_ok=True)
        save_config(config, workdir)
        record_cache(workdir)  # int8 calibration later reads the same dataset
    multiprocess.check_shared_directory(workdir)

    # Mesh.
    mesh = parallel.make_mesh()
    per_process_batch = parallel.check_batch_size(config.data.batch_size, mesh)

    # Data.
    root = depth_root(config.data)
    source = train_source(config, root)
    loader = make_train_loader(config, source, per_process_batch, mesh)
    steps_per_epoch = loader.steps_per_epoch
    total_steps = config.train.num_steps or config.train.num_epochs * steps_per_epoch

    # Prior mean (numpy, once; a constant of the compiled graph; process 0 computes it).
    prior_mean = load_or_compute_prior_mean(config, source, workdir)

    # Model and optimizer.
    model = build_model(config, prior_mean)
    schedule, tx = optimizer(config, total_steps, steps_per_epoch)
    state, state_sharding = create_train_state(
        init_variables(model, config, config.seed), tx, config.seed, mesh
    )

    # Restore.
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints, writer=True)
    state, start_step, _ = restore_latest(checkpoints, state, announce=is_main)

    # Step and evaluator.
    train_step = make_train_step(  # the model in train.compute_dtype; evaluation in float32
        training_model(model, config), tx, loss_options(config), mesh, state_sharding
    )
    evaluator = make_evaluator(config, eval_source(config, root)) if is_main else None
    writer = MetricsWriter(
        workdir, is_main, resume_step=start_step, tensorboard=config.log.tensorboard
    )
    progress, steps = step_telemetry(config, train_step, mesh, workdir, total_steps, start_step)

    def save(step: int) -> None:
        check_finite(state, step, checkpoints)
        meta = {"task": "depth", "epoch": step // steps_per_epoch, "prior_mean": prior_mean}
        checkpoints.save(step, state, meta)

    def run_evaluation(step: int) -> dict:
        out_dir = workdir / "results" / f"step_{step}"
        out = evaluator.evaluate(
            NetworkPredictor(model, host_variables(state)),
            out_dir / "depth",
            out_dir / "pictures",
            resume=True,
            max_batches=config.train.eval_max_batches or None,
        )
        out.pop("per_image")  # the guard's input; the run folder keeps the mean
        if out["metrics"]:
            print(format_depth_table(out["metrics"], out["num_scored"]), end="", flush=True)
        writer.write(step, kind="eval", **out)
        writer.pictures(step, (out_dir / "pictures").glob("*.png"))
        with atomic_write(out_dir / "metrics.json") as f:
            json.dump(out, f, indent=2)
        return out

    # Loop. In a multi-process run the watchdog stops a process whose peers hang.
    hint = f"Restart all processes to resume from the last checkpoint in {checkpoints.directory}."
    multiprocess.settings.peer_lost_hint = hint  # also for losses seen outside a step
    watchdog = step_watchdog.ProgressWatchdog(hint=hint)
    step = start_step
    try:
        for batch in steps.batches(loader.iterate(start_step, total_steps - start_step)):
            step += 1
            state, metrics = steps(state, batch, step)  # the first call compiles
            watchdog.step(step, metrics)
            if step == start_step + 1:
                progress.restart(start_step)  # throughput windows start after the compile
                writer.write(step, kind="compile", **steps.compile_record())
            if step % config.train.log_every == 0 or step == total_steps:
                m = parallel.to_host(metrics)
                check_finite(state, step, checkpoints, loss=m["loss"])
                stats = progress.update(
                    step,
                    float(m["loss"]),
                    {"si_1": float(m["si/scale_1"])},
                    data_wait_s=steps.take_data_wait(),
                )
                lr = float(schedule(step - 1))
                writer.write(step, lr=lr, **{k: float(v) for k, v in m.items()}, **stats)
            if stopping.preemption_requested(step):  # SIGTERM/SIGINT: all stop here
                save(step)
                raise multiprocess.PreemptedError(step)
            if step % config.train.checkpoint_every == 0 and step < total_steps:
                save(step)
            every = config.train.eval_every
            if every and step % every == 0 and step < total_steps:
                # Evaluation runs on process 0 alone; the others wait at a barrier.
                multiprocess.run_on_main(
                    functools.partial(run_evaluation, step), f"eval_{step}", watchdog
                )
        if step > start_step or checkpoints.latest_step() != step:
            save(step)
        checkpoints.wait()
    except Exception as e:
        multiprocess.raise_if_peer_failure(e, hint)  # a clear PeerLostError instead of a gloo error
        steps.raise_if_out_of_memory(e)  # one line naming data.batch_size
        raise
    finally:
        steps.close()
        watchdog.close()
        progress.close()
        writer.flush()
    result = None
    if config.train.eval_at_end:
        result = multiprocess.run_on_main(functools.partial(run_evaluation, step), "eval_final")
    checkpoints.close()
    writer.close()
    return result or {}
