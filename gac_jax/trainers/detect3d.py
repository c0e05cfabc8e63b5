"""Trainer of the GAC monocular 3D detector: ``python train.py --task detect3d``.

Top to bottom: config -> mesh -> data -> anchors and priors -> model/optimizer
-> restore -> jitted step -> evaluator -> loop. One ``jax.jit`` train step over
a ``Mesh(('data',))`` (batch sharded, parameters replicated); the same code on
one CPU, several devices or several processes.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from gac_jax import multiprocess, parallel
from gac_jax.anchor_filter import ground_mask_from_constants
from gac_jax.anchor_priors import (
    load_or_compute_priors,
    make_detection_constants,
    prior_frame_from_objects,
)
from gac_jax.anchors import AnchorLayout, generate_anchors
from gac_jax.checkpointing import Checkpoints
from gac_jax.config import save_config
from gac_jax.data import transforms
from gac_jax.data.loader import DetectionArrays, Loader
from gac_jax.data.sources import open_object_source
from gac_jax.detection_loss import DetectionLossConfig, detection_loss
from gac_jax.evaluation.detection_pictures import save_evaluation_pictures
from gac_jax.evaluation.detector_evaluator import DetectionEvaluator
from gac_jax.evaluation.kitti_object import format_table
from gac_jax.inference import PostprocessConfig
from gac_jax.metrics_writer import MetricsWriter, Progress
from gac_jax.models.detector import Detector
from gac_jax.train_state import (
    TrainState,
    apply_gradients_guarded,
    learning_rate_schedule,
    make_optimizer,
)
from gac_jax.trainers.common import (
    NonFiniteLossError,  # noqa: F401 - re-exported: callers catch detect3d.NonFiniteLossError
    check_finite,
    create_train_state,
    host_variables,
    prepare_dataset,
    restore_latest,
)

# ----------------------------------------------------------------------------- pieces


def anchor_layout(config: ml_collections.ConfigDict) -> AnchorLayout:
    a = config.anchors
    scales = tuple(2.0 ** (i * a.scale_step) for i in range(a.num_scales))
    return AnchorLayout(
        image_size=(config.data.height, config.data.width),
        stride=a.stride,
        base_size=a.base_size,
        ratios=tuple(a.ratios),
        scales=scales,
    )


def eval_transform(config: ml_collections.ConfigDict, normalize: bool = True) -> transforms.Compose:
    """Deterministic chain: crop top, resize to the input height, crop/pad the width."""
    d = config.data
    ops = [
        transforms.CropTop(d.crop_top),
        transforms.Resize(d.height),
        transforms.CropOrPadWidth(d.width),
    ]
    if normalize:
        ops.append(transforms.Normalize())
    return transforms.Compose(ops)


def train_transform(config: ml_collections.ConfigDict) -> transforms.Compose:
    d = config.data
    ops = [
        transforms.FilterObjects(
            tuple(d.classes), max_occlusion=d.max_occlusion, min_depth=d.min_depth
        )
    ]
    ops += [
        transforms.CropTop(d.crop_top),
        transforms.Resize(d.height),
        transforms.CropOrPadWidth(d.width),
    ]
    if d.photometric:
        ops.append(transforms.PhotometricDistort())
    if d.flip_prob > 0:
        ops.append(transforms.RandomHorizontalFlip(d.flip_prob))
    if d.reproject_boxes:
        ops.append(transforms.ReprojectBoxes())
    ops.append(transforms.Normalize())
    return transforms.Compose(ops)


def build_model(config: ml_collections.ConfigDict, num_anchors: int) -> Detector:
    m = config.model
    return Detector(
        depth=m.backbone_depth,
        width=m.backbone_width,
        num_classes=len(config.data.classes),
        num_anchors=num_anchors,
        cls_features=m.cls_features,
        reg_features=m.reg_features,
        dropout_rate=m.dropout_rate,
        regression_block=m.regression_block,
        baseline=m.gac.baseline,
        camera_height=m.gac.camera_height,
        object_height=m.gac.object_height,
        offset_formula=m.gac.offset_formula,
    )


def loss_config(config: ml_collections.ConfigDict) -> DetectionLossConfig:
    lc = config.loss
    return DetectionLossConfig(
        balance_weights=tuple(lc.balance_weights),
        gamma=lc.gamma,
        focal_min_loss=lc.focal_min_loss,
        smooth_l1_beta=lc.smooth_l1_beta,
        smooth_l1_min_residual=lc.smooth_l1_min_residual,
        regression_weights=tuple(lc.regression_weights),
        pos_iou=lc.pos_iou,
        neg_iou=lc.neg_iou,
        match_low_quality=lc.get("match_low_quality", False),  # absent in older workdirs
        normalize_by=lc.normalize_by,
    )


def sign_axis(config: ml_collections.ConfigDict) -> float:
    """Direction of the alpha-sign bit (0 = reference; absent in older workdirs' configs)."""
    return float(config.anchors.get("sign_axis", 0.0))


def filter_options(config: ml_collections.ConfigDict) -> dict:
    return {
        "mode": config.anchors.filter_mode,
        "x_focal": config.anchors.filter_x_focal,
        "camera_height": config.model.gac.camera_height,
    }


@dataclasses.dataclass(frozen=True)
class PriorFrameArrays:
    """Picklable ``sample -> padded prior frame`` for the loader workers.

    The transforms already mapped the annotated boxes to network-input pixels.
    """

    class_names: tuple[str, ...]
    max_objects: int

    def __call__(self, sample: dict) -> dict[str, np.ndarray]:
        frame = prior_frame_from_objects(sample["objects"], self.class_names)
        n = min(len(frame["classes"]), self.max_objects)
        out = {}
        for key, value in frame.items():
            padded = np.full((self.max_objects,) + value.shape[1:], -1 if key == "classes" else 0)
            padded = padded.astype(value.dtype)
            padded[:n] = value[:n]
            out[key] = padded
        return out


def compute_priors(config, root: Path, layout: AnchorLayout, workdir: Path):
    """Per-anchor priors from the training split (left images, test-time geometry), cached."""
    d = config.data
    classes = tuple(d.classes)

    def frames():
        source = open_object_source(root, d.train_split, use_right_image=False)
        transform = transforms.Compose(
            [
                transforms.FilterObjects(
                    classes, max_occlusion=d.max_occlusion, min_depth=d.min_depth
                )
            ]
            + list(eval_transform(config, normalize=False).transforms)
        )
        loader = Loader(
            source,
            transform,
            PriorFrameArrays(classes, d.max_objects),
            batch_size=8,
            shuffle=False,
            drop_remainder=False,
            num_epochs=1,
            worker_count=d.num_workers,
        )
        for batch in loader.iterate():
            for b in range(len(batch["classes"])):
                yield {k: v[b] for k, v in batch.items()}

    return load_or_compute_priors(
        workdir / "anchor_priors.npz",
        frames,
        layout,
        classes,
        angle_mode=config.anchors.angle_mode,
        iou_threshold=config.anchors.prior_iou,
        min_count=config.anchors.prior_min_count,
    )


def make_evaluator(config, model, constants, root: Path, worker_count: int) -> DetectionEvaluator:
    e = config.eval
    source = open_object_source(root, config.data.val_split, use_right_image=False)
    return DetectionEvaluator(
        model,
        constants,
        source,
        eval_transform(config),
        tuple(config.data.classes),
        PostprocessConfig(
            score_threshold=e.score_threshold,
            nms_iou=e.nms_iou,
            class_agnostic_nms=e.class_agnostic_nms,
            hill_climbing=e.hill_climbing,
        ),
        batch_size=config.data.eval_batch_size,
        top_k=e.top_k,
        filter_options=filter_options(config),
        use_ground_filter=config.anchors.filter,
        worker_count=worker_count,
    )


def init_variables(model: Detector, config, seed: int) -> dict:
    d = config.data
    images = jnp.zeros((1, d.height, d.width, 3), jnp.float32)
    P2 = jnp.asarray(
        [[[700.0, 0, d.width / 2, 0], [0, 700.0, d.height / 4, 0], [0, 0, 1, 0]]], jnp.float32
    )
    key = jax.random.key(seed)
    variables = jax.jit(functools.partial(model.init, train=False))(
        {"params": key, "dropout": key}, images, P2
    )
    if config.model.pretrained_backbone:
        from gac_jax.pretrained import init_backbone

        variables = init_backbone(variables, config.model.pretrained_backbone)
    return {"params": variables["params"], "batch_stats": variables.get("batch_stats", {})}


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
                rngs={"dropout": state.step_key("dropout")},
                mutable=["batch_stats"],
            )
            mask = (
                ground_mask_from_constants(constants, batch["P2"], **fopts) if use_filter else None
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
    """Trains (resuming from ``workdir`` if it holds checkpoints) and evaluates on val."""
    workdir = Path(workdir)
    is_main = jax.process_index() == 0
    if is_main:
        workdir.mkdir(parents=True, exist_ok=True)
        save_config(config, workdir)
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
        DetectionArrays(classes, config.data.max_objects, truncate=True),
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
    checkpoints = Checkpoints(workdir, config.train.keep_checkpoints)
    state, start_step, _ = restore_latest(checkpoints, state, announce=is_main)

    # Step and evaluator.
    train_step = make_train_step(
        model, tx, constants, loss_config(config), config, mesh, state_sharding
    )
    evaluator = make_evaluator(config, model, constants, root, config.data.num_workers)
    writer = MetricsWriter(workdir, enabled=is_main, resume_step=start_step)
    progress = Progress(total_steps, start_step, config.data.batch_size, enabled=is_main)

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
            with open(workdir / "results" / f"step_{step}" / "metrics.json", "w") as f:
                json.dump(out, f, indent=2)
            save_evaluation_pictures(
                evaluator.source, result_dir, config.eval.num_pictures, classes
            )
        return out

    # Loop. In a multi-process run the watchdog stops a process whose peers hang.
    hint = f"Restart all processes to resume from the last checkpoint in {checkpoints.directory}."
    watchdog = multiprocess.ProgressWatchdog(hint=hint)
    compile_t0 = time.perf_counter()
    step = start_step
    try:
        for batch in loader.iterate(start_step, total_steps - start_step):
            state, metrics = train_step(state, parallel.to_global(batch, mesh))
            step += 1
            watchdog.step(step, metrics)
            if step == start_step + 1:
                jax.block_until_ready(metrics)
                writer.write(step, kind="compile", compile_s=time.perf_counter() - compile_t0)
            if step % config.train.log_every == 0 or step == total_steps:
                m = parallel.to_host(metrics)
                check_finite(state, step, checkpoints, loss=m["loss"])
                lr = float(schedule(step - 1))
                stats = progress.update(
                    step,
                    float(m["loss"]),
                    {"cls": float(m["cls_loss"]), "reg": float(m["reg_loss"])},
                )
                writer.write(step, lr=lr, **{k: float(v) for k, v in m.items()}, **stats)
            if multiprocess.preemption_requested(step):  # SIGTERM to any process: all stop here
                save(step)
                raise multiprocess.PreemptedError(
                    f"stopped at step {step} on a preemption notice (SIGTERM); checkpoint saved "
                    f"in {checkpoints.directory}. Run the same command again to resume."
                )
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
        raise
    finally:
        watchdog.close()
        progress.close()
    result = None
    if config.train.eval_at_end:
        result = multiprocess.run_on_main(functools.partial(run_evaluation, step), "eval_final")
    checkpoints.close()
    return result or {}
