"""Config -> depth-network pieces: data roots and sources, transforms, model, loss settings,
the prior mean, evaluator, initial variables. Shared by the trainer, ``evaluate.py`` and the
exporter, so that nothing but ``train.py`` imports a trainer."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import ml_collections

from gac_jax.builders.datasets import appearance_ops, plane_ops, prepare_dataset
from gac_jax.data import transforms
from gac_jax.data.kitti_depth import list_selection
from gac_jax.data.sources import KittiDepthSelectionSource, open_depth_source
from gac_jax.evaluation.depth_evaluator import DepthEvaluator
from gac_jax.models.depth_unet import DepthUNet

PRIOR_FILE = "prior_mean.json"


def depth_root(data: ml_collections.ConfigDict) -> Path:
    """The KITTI-depth root of the config's ``data`` block (generating the embedded one)."""
    root = prepare_dataset(data)
    return root / "depth" if data.source == "synthetic" else root


def _view_ops(d: ml_collections.ConfigDict) -> list:
    """Forget the frame's plane (``data.use_planes = False``), bottom rows, resize."""
    ops: list = plane_ops(d) + [transforms.CropBottomTo(d.crop_height)]
    if d.height != d.crop_height:
        ops.append(transforms.Resize(d.height))
    return ops


def train_transform(config: ml_collections.ConfigDict) -> transforms.Compose:
    d = config.data
    ops = _view_ops(d) + [transforms.RandomCropWidth(d.width)]
    ops += appearance_ops(d)
    if d.flip_prob > 0:
        ops.append(transforms.RandomHorizontalFlip(d.flip_prob))
    ops.append(transforms.Normalize())
    return transforms.Compose(ops)


def eval_transform(config: ml_collections.ConfigDict) -> transforms.Compose:
    """Deterministic: bottom rows, resize, the left ``eval_width`` columns, normalise (and
    forget the frames' ground planes with ``data.use_planes = False``)."""
    d = config.data
    return transforms.Compose(
        _view_ops(d) + [transforms.CropOrPadWidth(d.eval_width), transforms.Normalize()]
    )


def build_model(config: ml_collections.ConfigDict, prior_mean: float) -> DepthUNet:
    m = config.model
    return DepthUNet(
        depth=m.encoder_depth,
        width=m.encoder_width,
        use_gac=m.use_gac,
        decoder_conv=m.decoder_conv,
        intrinsics_mode=m.intrinsics_mode,
        decoder_features=tuple(m.decoder_features) if m.decoder_features else None,
        prior_mean=float(prior_mean),
        output_prior=m.get("output_prior", "mean"),
        prior_max_depth=float(m.get("prior_max_depth", 75.0)),
        baseline=m.gac.baseline,
        camera_height=m.gac.camera_height,
        object_height=m.gac.object_height,
        offset_formula=m.gac.offset_formula,
    )


def loss_options(config: ml_collections.ConfigDict) -> dict:
    """Keyword arguments of :func:`gac_jax.depth.depth_loss.depth_loss` (plain Python values)."""
    lc = config.loss
    return {
        "si_lambda": float(lc.si_lambda),
        "min_depth": float(lc.min_depth),
        "max_depth": float(lc.max_depth),
        "residual_clip": float(lc.residual_clip),
        "smooth_weight": float(lc.smooth_weight),
        "edge_sharpness": float(lc.edge_sharpness),
        "scale_weights": {k: float(v) for k, v in lc.scale_weights.items()},
    }


def train_source(config: ml_collections.ConfigDict, root: Path):
    return open_depth_source(root, config.data.train_split, tuple(config.data.train_cameras))


def eval_source(config: ml_collections.ConfigDict, root: Path, split: str | None = None):
    """The evaluation source: ``data.val_selection`` (a ``depth_selection`` folder) if set,
    else the ``split`` (default ``data.val_split``) folder of the KITTI-depth root."""
    d = config.data
    if split is None and d.get("val_selection"):
        return KittiDepthSelectionSource(d.val_selection)
    return open_eval_data(root, split or d.val_split, tuple(d.val_cameras))


def open_eval_data(path: Path, split: str, cameras: tuple[int, ...]):
    """A ``depth_selection`` folder (``image/`` + ``intrinsics/``) or a KITTI-depth root."""
    path = Path(path)
    if (path / "image").is_dir() and (path / "intrinsics").is_dir():
        list_selection(path)  # validates the folder, naming the bad file
        return KittiDepthSelectionSource(path)
    return open_depth_source(path, split, cameras)


def read_prior_mean(workdir: Path) -> float:
    path = Path(workdir) / PRIOR_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no prior mean (is this a depth training workdir?)")
    return float(json.loads(path.read_text())["prior_mean"])


def init_variables(model: DepthUNet, config, seed: int) -> dict:
    d = config.data
    images = jnp.zeros((1, d.height, d.width, 3), jnp.float32)
    f = 721.5 * d.height / d.crop_height
    P = jnp.asarray([[[f, 0, d.width / 2, 0], [0, f, d.height / 2, 0], [0, 0, 1, 0]]], jnp.float32)
    variables = jax.jit(lambda k: model.init(k, images, P, train=False))(jax.random.key(seed))
    variables = {"params": variables["params"], "batch_stats": variables.get("batch_stats", {})}
    if config.model.pretrained_backbone:
        from gac_jax.weights.pretrained import init_backbone

        variables = init_backbone(variables, config.model.pretrained_backbone)
    return variables


def make_evaluator(config, source) -> DepthEvaluator:
    return DepthEvaluator(
        source,
        eval_transform(config),
        batch_size=config.data.eval_batch_size,
        worker_count=config.data.num_workers,
        num_pictures=config.eval.num_pictures,
        max_depth=config.eval.picture_max_depth,
    )
