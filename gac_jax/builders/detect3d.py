"""Config -> detector pieces: anchor layout, transforms, model, loss settings, anchor priors,
evaluator, initial variables. Shared by the trainer, ``evaluate.py``, ``gac_jax.cli.predict`` and
the exporter, so that nothing but ``train.py`` imports a trainer."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from gac_jax.builders.datasets import appearance_ops, plane_ops
from gac_jax.data import transforms
from gac_jax.data.loader import Loader
from gac_jax.data.sources import open_object_source
from gac_jax.detection.anchor_priors import load_or_compute_priors, prior_frame_from_objects
from gac_jax.detection.anchors import AnchorLayout
from gac_jax.detection.detection_loss import DetectionLossConfig
from gac_jax.detection.inference import PostprocessConfig
from gac_jax.evaluation.detector_evaluator import DetectionEvaluator
from gac_jax.models.detector import Detector
from gac_jax.progress import Progress, say


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
    """Deterministic chain: crop top, resize to the input height, crop/pad the width (and
    forget the frames' ground planes with ``data.use_planes = False``)."""
    d = config.data
    ops = plane_ops(d) + [
        transforms.CropTop(d.crop_top),
        transforms.Resize(d.height, calibration=d.get("resize_calibration", "grid")),
        transforms.CropOrPadWidth(d.width),
    ]
    if normalize:
        ops.append(transforms.Normalize())
    return transforms.Compose(ops)


def train_transform(config: ml_collections.ConfigDict) -> transforms.Compose:
    d = config.data
    ops = plane_ops(d) + [
        transforms.FilterObjects(
            tuple(d.classes), max_occlusion=d.max_occlusion, min_depth=d.min_depth
        )
    ]
    ops += [
        transforms.CropTop(d.crop_top),
        transforms.Resize(d.height, calibration=d.get("resize_calibration", "grid")),
        transforms.CropOrPadWidth(d.width),
    ]
    ops += appearance_ops(d)
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
        ohem_drop_fraction=lc.get("ohem_drop_fraction", 0.0),  # absent in older workdirs
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
        say(
            f"computing anchor priors from the {len(source)} frames of split {d.train_split!r} "
            f"into {workdir / 'anchor_priors.npz'} (once per run folder)"
        )
        with Progress(len(source), "anchor priors", "frame") as bar:
            for batch in loader.iterate():
                for b in range(len(batch["classes"])):
                    yield {k: v[b] for k, v in batch.items()}
                bar.update(len(batch["classes"]))

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
        camera_height=config.model.gac.camera_height,
        operating_point_beta=config.eval.get("operating_point_beta", 1.0),
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
        from gac_jax.weights.pretrained import init_backbone

        variables = init_backbone(variables, config.model.pretrained_backbone)
    return {"params": variables["params"], "batch_stats": variables.get("batch_stats", {})}
