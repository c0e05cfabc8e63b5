"""The GAC monocular 3D detector (reference ``GroundAwareYolo3D``): ResNet trunk + head.

``Detector`` = :class:`~gac_jax.models.resnet.ResNet` through layer3 (stride 16, Flax name
``backbone``) + :class:`~gac_jax.models.detection_head.DetectionHead` (Flax name ``head``).

Usage::

    model = Detector(depth=101, num_classes=1, num_anchors=32)
    variables = model.init({"params": key}, images, P2, train=False)
    out = model.apply(variables, images, P2, train=False)                  # inference
    out = model.apply(variables, images, P2, train=False, plane=plane)     # per-frame ground
    out, updates = model.apply(variables, images, P2, train=True,         # training
                               mutable=["batch_stats"], rngs={"dropout": key})
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from gac_jax.models.detection_head import DetectionHead
from gac_jax.models.ground_aware_conv import (
    DEFAULT_BASELINE,
    DEFAULT_CAMERA_HEIGHT,
    DEFAULT_OBJECT_HEIGHT,
)
from gac_jax.models.resnet import ResNet, layer_output_size, layer_stride

FEATURE_LAYER = 3  # the detector uses ResNet layer3
FEATURE_STRIDE = layer_stride(FEATURE_LAYER)  # 16


def feature_map_size(image_size: tuple[int, int]) -> tuple[int, int]:
    """(Hf, Wf) of the detector's stride-16 feature map for an input (H, W); 288x1280 -> 18x80."""
    height, width = image_size
    return layer_output_size(height, FEATURE_LAYER), layer_output_size(width, FEATURE_LAYER)


class Detector(nn.Module):
    """GAC detector. Attributes (plain values, no config object):

      depth: ResNet depth (18/34/50/101; the paper uses 101).
      width: ResNet base width (64; smaller for tiny test models).
      num_classes: K; num_anchors: A (32 in the paper configuration).
      cls_features / reg_features / dropout_rate / regression_block / offset_formula / GAC
        geometry constants: see :class:`DetectionHead` and
        :class:`~gac_jax.models.ground_aware_conv.GroundAwareConv`.
      dtype / param_dtype: computation / parameter dtypes (outputs are float32).

    ``__call__(images (B,H,W,3) float32 ImageNet-normalised RGB, P2 (B,3,4) projection of
    these images in their pixels, train: bool, plane (B,4) each frame's ground plane ``(a, b, c,
    d)``, unit upward normal, rectified camera frame; None = the level plane of
    ``camera_height``)`` returns

      * ``'cls_logits'`` (B,N,K), ``'sign_logits'`` (B,N) (logit of ``cos(alpha) > 0``),
      * ``'reg'`` (B,N,12) in the order of ``REGRESSION_COMPONENTS``
        ``[dx, dy, dw, dh, cdx, cdy, z, sin2a, cos2a, w3d, h3d, l3d]``,
      * ``'gac_offsets'`` (B,Hf,Wf) vertical sampling offsets in feature rows (only with
        ``regression_block='gac'``),

    with ``(Hf, Wf) = feature_map_size((H, W))``, N = Hf*Wf*A and anchor index
    ``(row*Wf + col)*A + a``.
    """

    depth: int = 101
    width: int = 64
    num_classes: int = 1
    num_anchors: int = 32
    cls_features: int = 512
    reg_features: int = 1024
    dropout_rate: float = 0.3
    regression_block: str = "gac"
    baseline: float = DEFAULT_BASELINE
    camera_height: float = DEFAULT_CAMERA_HEIGHT
    object_height: float = DEFAULT_OBJECT_HEIGHT
    offset_formula: str = "paper"
    offset_scale: float = 0.1
    offset_grad_scale: float = 0.05
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(
        self, images: jax.Array, P2: jax.Array, train: bool, plane: jax.Array | None = None
    ) -> dict[str, jax.Array]:
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"expected NHWC RGB images (B,H,W,3), got shape {images.shape}")
        layer = f"layer{FEATURE_LAYER}"
        features = ResNet(
            depth=self.depth,
            num_stages=FEATURE_LAYER,
            return_layers=(layer,),
            width=self.width,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="backbone",
        )(images, train)[layer]
        return DetectionHead(
            num_classes=self.num_classes,
            num_anchors=self.num_anchors,
            cls_features=self.cls_features,
            reg_features=self.reg_features,
            dropout_rate=self.dropout_rate,
            regression_block=self.regression_block,
            stride=FEATURE_STRIDE,
            baseline=self.baseline,
            camera_height=self.camera_height,
            object_height=self.object_height,
            offset_formula=self.offset_formula,
            offset_scale=self.offset_scale,
            offset_grad_scale=self.offset_grad_scale,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="head",
        )(features, P2, train, plane)
