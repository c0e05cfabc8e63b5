"""Trainer of the GAC monocular 3D detector: ``python train.py --task detect3d``.

Top to bottom: config -> mesh -> data -> anchors and priors -> model/optimizer
-> restore -> jitted step -> evaluator -> loop. One ``jax.jit`` train step over
a ``Mesh(('data',))`` (batch sharded, parameters replicated); the same code on
one CPU, several devices or several processes.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import ml_collections

from gac_jax.builders.datasets import prepare_dataset, record_cache
from gac_jax.builders.detect3d import (
    anchor_layout,
    build_model,
    compute_priors,
    filter_options,
    init_variables,
    loss_config,
    make_evaluator,
    sign_axis,
    train_transform,
)
from gac_jax.config import save_config
from gac_jax.data.files import atomic_write
from gac_jax.data.loader import DetectionArrays, Loader
from gac_jax.data.sources import open_object_source
from gac_jax.detection.anchor_filter import ground_mask_from_constants
from gac_jax.detection.anchor_priors import make_detection_constants
from gac_jax.detection.anchors import generate_anchors
from gac_jax.detection.detection_loss import detection_loss
from gac_jax.drawing.detection_pictures import save_evaluation_pictures
from gac_jax.evaluation.ap_table import format_table
from gac_jax.evaluation.operating_point import check_beta, describe
from gac_jax.trained.fingerprint import weights_sha256
from gac_jax.trained.operating_point import write_operating_point
from gac_jax.trainers.common import (
    NonFiniteLossError,  # noqa: F401 - re-exported: callers catch detect3d.NonFiniteLossError
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


def make_train_step(model, tx, constants, loss_cfg, config, mesh, state_sharding):
    use_filter = config.anchors.filter
    fopts = filter_options(config)

    def train_step(state: TrainState, batch: dict):
        def loss_fn(params):
            outputs, mutated = model.apply(
                {"params": params, "batch_stats": state.batch_stats},
                batch["image"],
                batch["P2"],
                train=True,
                plane=batch.get("plane"),
                rngs={"dropout": state.step_key("dropout")},
                mutable=["batch_stats"],
            )
            mask = None
            if use_filter:
                mask = ground_mask_from_constants(
                    constants, batch["P2"], batch.get("plane"), **fopts
                )
            loss, metrics = detection_loss(outputs, batch, constants, mask, loss_cfg)
            return loss, (metrics, mutated["batch_stats"])

        (loss, (metrics, batch_stats)), grads = jax.value_and_grad(loss_fn, has_aux=True)(
            state.params
        )
        new_state, grad_norm = apply_gradients_guarded(state, tx, grads, batch_stats, loss)
        metrics = dict(metrics, grad_norm=grad_norm)
        return new_state, metrics

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
    check_beta(config.eval.get("operating_point_beta", 1.0))  # and a bad operating point rule
    if is_main:
        workdir.mkdir(parents=True, exist_ok=True)
        save_config(config, workdir)
        record_cache(workdir)  # int8 calibration later reads the same dataset
    multiprocess.check_shared_directory(workdir)

    # Mesh.
    mesh = parallel.make_mesh()
    per_process_batch = parallel.check_batch_size(config.data.batch_size, mesh)

    # Data.
    root = prepare_dataset(config.data)
    classes = tuple(config.data.classes)
    train_source = open_object_source(
        root, config.data.train_split, use_right_image=config.data.use_right_image
    )
    shard_index, num_shards = parallel.process_shard(mesh)  # this process's rows of each batch
    loader = Loader(
        train_source,
        train_transform(config),
        DetectionArrays(classes, config.data.max_objects, True, config.model.gac.camera_height),
        batch_size=per_process_batch,
        seed=config.seed,
        shard_index=shard_index,
        num_shards=num_shards,
        worker_count=config.data.num_workers,
    )
    steps_per_epoch = loader.steps_per_epoch
    total_steps = config.train.num_steps or config.train.num_epochs * steps_per_epoch

    # Anchors and priors (numpy, once; constants of the compiled graph).
    layout = anchor_layout(config)
    anchors = generate_anchors(layout)
    with multiprocess.main_process_first("anchor_priors"):  # the others read process 0's cache
        priors = compute_priors(config, root, layout, workdir)
    constants = make_detection_constants(anchors, priors, sign_axis(config))

    # Model and optimizer.
    model = build_model(config, layout.anchors_per_cell)
    schedule = learning_rate_schedule(
        config.train.learning_rate,
        config.train.final_learning_rate,
        total_steps,
        steps_per_epoch if config.train.per_epoch_schedule else None,
        config.train.warmup_steps,
    )
    tx = make_optimizer(schedule, config.train.clip_norm, config.train.weight_decay)
    variables = init_variables(model, config, config.seed)
    state, state_sharding = create_train_state(variables, tx, config.seed, mesh)
    del variables

    # Restore.
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints, writer=True)
    state, start_step, _ = restore_latest(checkpoints, state, announce=is_main)

    # Step and evaluator.
    train_step = make_train_step(  # the model in train.compute_dtype; evaluation in float32
        training_model(model, config),
        tx,
        constants,
        loss_config(config),
        config,
        mesh,
        state_sharding,
    )
    evaluator = make_evaluator(config, model, constants, root, config.data.num_workers)
    writer = MetricsWriter(
        workdir, is_main, resume_step=start_step, tensorboard=config.log.tensorboard
    )
    progress, steps = step_telemetry(config, train_step, mesh, workdir, total_steps, start_step)

    def save(step: int) -> None:
        check_finite(state, step, checkpoints)
        checkpoints.save(step, state, {"task": "detect3d", "epoch": step // steps_per_epoch})

    def run_evaluation(step: int) -> dict:
        # Local copies of the replicated weights: evaluation runs on this process alone.
        variables = host_variables(state)
        max_batches = config.train.eval_max_batches or None
        result_dir = workdir / "results" / f"step_{step}" / "data"
        out = evaluator.evaluate(variables, result_dir, resume=True, max_batches=max_batches)
        if is_main:
            print(format_table(out["metrics"]), flush=True)
            writer.write(step, kind="eval", **out)
            with atomic_write(workdir / "results" / f"step_{step}" / "metrics.json") as f:
                json.dump(out, f, indent=2)
            record = out["operating_point"]
            write_operating_point(
                result_dir.parent, record, step, weights_sha256(variables), config.data.val_split
            )
            print(describe(record), flush=True)
            pictures = save_evaluation_pictures(
                evaluator.source, result_dir, config.eval.num_pictures, classes
            )
            writer.pictures(step, pictures)
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
                lr = float(schedule(step - 1))
                stats = progress.update(
                    step,
                    float(m["loss"]),
                    {"cls": float(m["cls_loss"]), "reg": float(m["reg_loss"])},
                    data_wait_s=steps.take_data_wait(),
                )
                writer.write(step, lr=lr, **{k: float(v) for k, v in m.items()}, **stats)
            if stopping.preemption_requested(step):  # SIGTERM/SIGINT: all stop here
                save(step)
                raise multiprocess.PreemptedError(step)
            if step % config.train.checkpoint_every == 0 and step < total_steps:
                save(step)
            if (
                config.train.eval_every
                and step % config.train.eval_every == 0
                and step < total_steps
            ):
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
