"""A trained detector of a run folder (or converted weights), loaded and ready to run.

:func:`load_detector` rebuilds model, anchors and priors from the config and restores the
weights (a training checkpoint or converted weights, :func:`load_variables`);
:func:`evaluator_for` wraps it in a :class:`DetectionEvaluator`. Shared by ``evaluate.py
--task detect3d --workdir`` (:mod:`gac_jax.cli.evaluate_detector`), ``python -m
gac_jax.cli.predict``, the export (:mod:`gac_jax.deploy.export.sources`) and the runtimes
(:mod:`gac_jax.deploy.runtime_choice`).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np

from gac_jax.builders.datasets import prepare_dataset
from gac_jax.builders.detect3d import (
    anchor_layout,
    build_model,
    compute_priors,
    eval_transform,
    filter_options,
    sign_axis,
)
from gac_jax.data.files import KittiFormatError
from gac_jax.detection.anchor_priors import (
    DetectionConstants,
    PriorsMismatchError,
    load_priors,
    make_detection_constants,
)
from gac_jax.detection.anchors import generate_anchors
from gac_jax.detection.inference import PostprocessConfig
from gac_jax.evaluation.detector_evaluator import DetectionEvaluator
from gac_jax.models.detector import Detector
from gac_jax.trained.fingerprint import weights_sha256
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.weights import pretrained

PRIORS_FILE = "anchor_priors.npz"


@dataclasses.dataclass
class LoadedDetector:
    """Everything needed to run a detector (see :func:`load_detector`).

    Attributes:
      config: the run config; model: the Detector (compute ``dtype`` as asked);
      constants: anchors + priors; variables: ``{'params', 'batch_stats'}`` numpy;
      weights: where the weights came from (human-readable); tag: short name of
        the weights for folder names (``step<N>`` or the converted folder's name);
      step: the workdir checkpoint's step (None for converted weights).
      weights_sha256: the identity of ``variables``
        (:func:`gac_jax.trained.fingerprint.weights_sha256`, computed on first use).
    """

    config: ml_collections.ConfigDict
    model: Detector
    constants: DetectionConstants
    variables: dict[str, Any]
    weights: str
    tag: str
    step: int | None = None

    @functools.cached_property
    def weights_sha256(self) -> str:
        return weights_sha256(self.variables)


def postprocess_config(config: ml_collections.ConfigDict) -> PostprocessConfig:
    e = config.eval
    return PostprocessConfig(
        score_threshold=e.score_threshold,
        nms_iou=e.nms_iou,
        class_agnostic_nms=e.class_agnostic_nms,
        hill_climbing=e.hill_climbing,
    )


def variables_template(model: Detector, config) -> dict:
    d = config.data
    images = jax.ShapeDtypeStruct((1, d.height, d.width, 3), jnp.float32)
    P2 = jax.ShapeDtypeStruct((1, 3, 4), jnp.float32)
    key = jax.random.key(0)
    init = functools.partial(model.init, train=False)
    shapes = jax.eval_shape(init, {"params": key, "dropout": key}, images, P2)
    return {"params": shapes["params"], "batch_stats": shapes.get("batch_stats", {})}


def _load_priors(config, workdir: Path, layout, converted: bool):
    path = workdir / PRIORS_FILE
    classes = tuple(config.data.classes)
    if path.exists():
        try:
            return load_priors(path, layout, classes, config.anchors.angle_mode)
        except PriorsMismatchError as e:
            raise KittiFormatError(path, str(e).removeprefix(f"{path}: ")) from None
        except ValueError as e:
            raise KittiFormatError(path, str(e).removeprefix(f"{path}: ")) from None
    if not converted:
        raise KittiFormatError(
            path,
            "anchor priors not found: the trainer computes them from the training split on its "
            f"first run (python train.py --task detect3d --workdir {workdir}); with converted "
            "weights (--checkpoint) they are computed here from the config's training split",
        )
    root = prepare_dataset(config.data)
    print(
        f"computing anchor priors from split {config.data.train_split!r} of {root} "
        f"(cached in {path})",
        flush=True,
    )
    workdir.mkdir(parents=True, exist_ok=True)
    return compute_priors(config, root, layout, workdir)


def restore_workdir_weights(workdir: Path, step: int | None, template) -> tuple[dict, int]:
    directory = workdir / "checkpoints"
    how = (
        f"train first (python train.py --task detect3d --workdir {workdir}) or pass "
        "--checkpoint DIR with converted weights"
    )
    if not directory.is_dir():
        raise KittiFormatError(directory, f"no checkpoints folder: {how}")
    with Checkpoints(workdir) as ckpts:
        if ckpts.latest_step() is None:
            raise KittiFormatError(directory, f"no checkpoint in this folder: {how}")
        step = ckpts.latest_step() if step is None else step
        if step not in ckpts.all_steps():
            raise KittiFormatError(
                directory, f"no checkpoint step {step} (have {ckpts.all_steps()})"
            )
        variables = ckpts.restore_variables(step)
    problems = pretrained.compare_shapes(
        pretrained.flat_shapes(template), pretrained.flat_shapes(variables)
    )
    if problems:
        shown = "; ".join(problems[:3]) + (
            f"; ... {len(problems) - 3} more" if len(problems) > 3 else ""
        )
        raise KittiFormatError(
            directory / str(step),
            f"checkpoint does not fit the model of the config ({len(problems)} problems: {shown})",
        )
    cast = jax.tree.map(lambda v, t: np.asarray(v, t.dtype), variables, template)
    return cast, step


def load_variables(
    workdir: str | os.PathLike | None,
    template,
    *,
    step: int | None = None,
    checkpoint: str | os.PathLike | None = None,
) -> tuple[dict, int | None]:
    """``(variables, step)``: converted weights (``checkpoint``; step None) or the workdir's
    checkpoint ``step`` (default: the latest), checked against and cast to ``template``.

    Raises:
      KittiFormatError: missing weights or weights that do not fit, naming the file.
    """
    if checkpoint is not None:
        try:
            return pretrained.load_converted_variables(checkpoint, template), None
        except pretrained.WeightsError as e:
            raise KittiFormatError(checkpoint, e.full_text(max_lines=10)) from None
    return restore_workdir_weights(Path(workdir), step, template)


def load_detector(
    workdir: str | os.PathLike,
    config: ml_collections.ConfigDict,
    *,
    step: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    dtype: Any = jnp.float32,
) -> LoadedDetector:
    """Model, anchors + priors and weights of a training workdir (or converted weights).

    Args:
      workdir: the training workdir (``anchor_priors.npz``, ``checkpoints/``).
      config: its config (:func:`gac_jax.trained.run_config.load_run_config`).
      step: checkpoint step (default: the latest).
      checkpoint: converted weights instead of the workdir's checkpoints; missing
        priors are then computed from the config's training split and cached.
      dtype: compute dtype of the model (parameters stay float32).

    Raises:
      KittiFormatError: missing or unfitting priors / checkpoints, naming the file.
    """
    workdir = Path(workdir)
    layout = anchor_layout(config)
    priors = _load_priors(config, workdir, layout, converted=checkpoint is not None)
    constants = make_detection_constants(generate_anchors(layout), priors, sign_axis(config))
    model = build_model(config, layout.anchors_per_cell).clone(dtype=dtype)
    template = variables_template(model, config)
    variables, step = load_variables(workdir, template, step=step, checkpoint=checkpoint)
    if checkpoint is not None:
        path = Path(checkpoint).resolve()
        name = path.parent.parent.name if path.parent.name == "checkpoints" else path.name
        return LoadedDetector(
            config, model, constants, variables, f"converted weights {path}", name
        )
    return LoadedDetector(
        config, model, constants, variables, f"step {step} of {workdir}", f"step{step}", step
    )


def evaluator_for(detector: LoadedDetector, source, batch_size: int) -> DetectionEvaluator:
    """The :class:`DetectionEvaluator` of ``detector`` over ``source`` (any frame source with
    images and ``P2``): the config's eval transform, classes, post-processing, ``top_k`` and
    ground filter."""
    config = detector.config
    return DetectionEvaluator(
        detector.model,
        detector.constants,
        source,
        eval_transform(config),
        tuple(config.data.classes),
        postprocess_config(config),
        batch_size=batch_size,
        top_k=config.eval.top_k,
        filter_options=filter_options(config),
        use_ground_filter=config.anchors.filter,
        camera_height=config.model.gac.camera_height,
        operating_point_beta=config.eval.get("operating_point_beta", 1.0),
    )
