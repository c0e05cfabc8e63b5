"""The GroundAwareYolo3D detection head: classification and regression branches, NHWC.

On backbone features F (B,Hf,Wf,C) (ResNet-101 layer3: C = 1024, stride 16):

* classification: [conv3x3 -> cls_features, Dropout2d(p), ReLU] x 2 -> conv3x3 to A*(K+1)
  (weight and bias zero-initialised, so every probability starts at 0.5; no prior bias);
* regression: block -> [conv3x3 -> reg_features, BatchNorm, ReLU] x 2 -> conv3x3 to A*12
  (zero-initialised, so every anchor starts at its prior). ``block`` is

  - ``'gac'``: :class:`GroundAwareConv` (the paper's model);
  - ``'conv'``: conv3x3 C->C + ReLU (the paper's ablation row "w Conv": GAC substituted by a
    basic convolution);
  - ``'disparity_conv'``: conv3x3 over [disparity prior ‖ F] (C+1 -> C) + ReLU (the ablation
    row "w DisparityConv": convolution with the depth prior as an extra feature map);
  - ``'deformable'``: modulated deformable conv v2 3x3 C->C + ReLU
    (:class:`~gac_jax.models.deformable_conv.ModulatedDeformConv`: per-pixel tap offsets and
    masks from a zero-initialised conv as in DCNv2, so it starts as half a plain conv; the
    ablation row "w Deformable Conv", the reference ``Yolo3D`` head).

Output layout: the NHWC conv output (B,Hf,Wf,A*D) reshapes to (B, Hf*Wf*A, D), anchor index
``(row*Wf + col)*A + a`` and PyTorch channel ``k = a*D + d`` -> anchor ``a``, component ``d``
(the reference permutes to NHWC before the same reshape, so converted weights line up).
Classification components: ``[class_0 .. class_{K-1}, alpha_sign]``; regression components
``REGRESSION_COMPONENTS``.

Flax names (see :mod:`gac_jax.models.naming` for the reference-key table): ``cls_conv1``,
``cls_conv2``, ``cls_out``, ``gac`` (or ``plain_conv`` / ``disparity_conv`` /
``deformable_conv`` with its ``conv_offset``), ``reg_conv1``,
``reg_bn1``, ``reg_conv2``, ``reg_bn2``, ``reg_out``. Layers the paper does not pin use
PyTorch's default initialisation.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from gac_jax.models.deformable_conv import ModulatedDeformConv
from gac_jax.models.ground_aware_conv import (
    DEFAULT_BASELINE,
    DEFAULT_CAMERA_HEIGHT,
    DEFAULT_OBJECT_HEIGHT,
    GroundAwareConv,
    feature_projection,
    frame_planes,
)
from gac_jax.models.ground_plane import ground_maps
from gac_jax.models.initializers import torch_conv_bias_init, torch_conv_kernel_init
from gac_jax.models.resnet import batch_norm_layer

REGRESSION_COMPONENTS = (
    "dx",
    "dy",
    "dw",
    "dh",
    "cdx",
    "cdy",
    "z",
    "sin2a",
    "cos2a",
    "w3d",
    "h3d",
    "l3d",
)
NUM_REGRESSION = len(REGRESSION_COMPONENTS)
REGRESSION_BLOCKS = ("gac", "conv", "disparity_conv", "deformable")


class DetectionHead(nn.Module):
    """Anchor-based mono-3D head of GAC (reference ``GroundAwareHead``).

    Attributes:
      num_classes: K (1 for Car-only).
      num_anchors: A anchors per feature cell (32 in the paper configuration).
      cls_features / reg_features: hidden widths of the two branches (512 / 1024).
      dropout_rate: channel-wise (Dropout2d) rate in the classification branch (0.3).
      regression_block: ``'gac'``, ``'conv'``, ``'disparity_conv'`` or ``'deformable'`` (see
        module docstring).
      stride: feature stride w.r.t. the input image (16), used to scale ``P2``.
      baseline, camera_height, object_height, offset_formula, offset_scale,
        offset_grad_scale: passed to :class:`GroundAwareConv`.
      dtype / param_dtype: computation / parameter dtypes.

    ``__call__(features (B,Hf,Wf,C), P2 (B,3,4) in input-image pixels, train, plane (B,4) the
    frame's ground plane or None for the level plane of camera_height)`` returns
    ``{'cls_logits': (B,N,K), 'sign_logits': (B,N), 'reg': (B,N,12)}`` with N = Hf*Wf*A,
    plus ``'gac_offsets'`` (B,Hf,Wf) (rows, see :class:`GroundAwareConv`) when
    ``regression_block == 'gac'``. ``train=True`` needs a ``'dropout'`` rng and
    ``mutable=['batch_stats']``.
    """

    num_classes: int = 1
    num_anchors: int = 32
    cls_features: int = 512
    reg_features: int = 1024
    dropout_rate: float = 0.3
    regression_block: str = "gac"
    stride: float = 16
    baseline: float = DEFAULT_BASELINE
    camera_height: float = DEFAULT_CAMERA_HEIGHT
    object_height: float = DEFAULT_OBJECT_HEIGHT
    offset_formula: str = "paper"
    offset_scale: float = 0.1
    offset_grad_scale: float = 0.05
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    def _conv(self, features: int, in_features: int, name: str, zero: bool = False) -> nn.Conv:
        fan_in = 9 * in_features
        return nn.Conv(
            features,
            (3, 3),
            padding=((1, 1), (1, 1)),
            kernel_init=nn.initializers.zeros if zero else torch_conv_kernel_init,
            bias_init=nn.initializers.zeros if zero else torch_conv_bias_init(fan_in),
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name=name,
        )

    @nn.compact
    def __call__(
        self, features: jax.Array, P2: jax.Array, train: bool, plane: jax.Array | None = None
    ) -> dict[str, jax.Array]:
        if self.regression_block not in REGRESSION_BLOCKS:
            block = self.regression_block
            raise ValueError(f"regression_block must be one of {REGRESSION_BLOCKS}, got {block!r}")
        if features.ndim != 4:
            raise ValueError(f"expected NHWC features (B,H,W,C), got shape {features.shape}")
        B, H, W, C = features.shape
        if P2.shape != (B, 3, 4):
            raise ValueError(f"P2 must have shape (B,3,4) = {(B, 3, 4)}, got {P2.shape}")
        A, K = self.num_anchors, self.num_classes
        x = features.astype(self.dtype)
        outputs: dict[str, jax.Array] = {}

        # Classification branch (Dropout2d = dropout broadcast over H and W).
        c = x
        for i, in_features in enumerate((C, self.cls_features), start=1):
            c = self._conv(self.cls_features, in_features, f"cls_conv{i}")(c)
            c = nn.Dropout(self.dropout_rate, broadcast_dims=(1, 2))(c, deterministic=not train)
            c = nn.relu(c)
        c = self._conv(A * (K + 1), self.cls_features, "cls_out", zero=True)(c)
        c = c.reshape(B, H * W * A, K + 1).astype(jnp.float32)
        outputs["cls_logits"] = c[..., :K]
        outputs["sign_logits"] = c[..., K]

        # Regression branch.
        if self.regression_block == "gac":
            gac = GroundAwareConv(
                stride=self.stride,
                baseline=self.baseline,
                camera_height=self.camera_height,
                object_height=self.object_height,
                offset_formula=self.offset_formula,
                offset_scale=self.offset_scale,
                offset_grad_scale=self.offset_grad_scale,
                dtype=self.dtype,
                param_dtype=self.param_dtype,
                name="gac",
            )(x, P2, plane)
            r = gac["features"]
            outputs["gac_offsets"] = gac["offset_rows"]
        elif self.regression_block == "conv":
            r = nn.relu(self._conv(C, C, "plain_conv")(x))
        elif self.regression_block == "deformable":
            dcn = ModulatedDeformConv(
                C, 3, dtype=self.dtype, param_dtype=self.param_dtype, name="deformable_conv"
            )
            r = nn.relu(dcn(x))
        else:
            Pf = feature_projection(jnp.asarray(P2, jnp.float32), self.stride)
            planes = frame_planes(plane, B, self.camera_height, jnp.float32)
            _, _, disp = ground_maps(Pf, planes, (H, W), self.object_height, self.baseline, "paper")
            r = jnp.concatenate([disp[..., None].astype(x.dtype), x], axis=-1)
            r = nn.relu(self._conv(C, C + 1, "disparity_conv")(r))
        for i, in_features in enumerate((C, self.reg_features), start=1):
            r = self._conv(self.reg_features, in_features, f"reg_conv{i}")(r)
            r = batch_norm_layer(train, self.dtype, self.param_dtype, f"reg_bn{i}", relu=True)(r)
        r = self._conv(A * NUM_REGRESSION, self.reg_features, "reg_out", zero=True)(r)
        outputs["reg"] = r.reshape(B, H * W * A, NUM_REGRESSION).astype(jnp.float32)
        return outputs
