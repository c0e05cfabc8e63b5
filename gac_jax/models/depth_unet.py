"""The ground-aware monocular depth network (paper Sec. "Network Architecture for Monocular
Depth Prediction"; reference ``MonoDepth`` / ``UNet_Core``), NHWC.

U-Net over a ResNet encoder (ResNet-34 in the paper; Flax name ``backbone``)::

    layer1 (stride 4)  layer2 (/8)  layer3 (/16)  layer4 (/32)
       |                  |             |             |
       |                  |             +---- up0 <---+        (GAC, stride 16)
       |                  +---------------- up1 <--+            (GAC, stride 8)  -> scale_8
       +----------------------------------- up2 <--+            (no GAC, /4)     -> scale_4
                                            bilinear up to the input size        -> scale_1

Decoder stage ``up{i}`` (:class:`UpStage`): bilinear x2 upsampling (``align_corners=True``)
of the coarser map -> zero-pad (or crop) to the skip size -> concatenate ``[skip, upsampled]``
-> optional :class:`~gac_jax.models.ground_aware_conv.GroundAwareConv` (``gac``) -> ``conv1``
5x5 in->in + ``bn1`` + ReLU -> ``conv2`` 3x3 in->out (plain conv, or DCNv2 with
``decoder_conv='deformable'`` as in the reference) + ``bn2`` + ReLU. Output channels
(``decoder_features``) default to ``(4w, w, w)`` = (256, 64, 64) for base width ``w = 64``.

Heads ``out_scale_8`` / ``out_scale_4`` / ``out_scale_1`` (conv 3x3 -> 1) predict a
log-depth *residual* ``f``; ``log_depth = prior + f`` and ``depth = exp(log_depth)``. The prior
(``output_prior``):

* ``'mean'`` (default, the reference): ``prior_mean``, the global mean log-depth of the
  training GT (:func:`mean_log_depth`), one number;
* ``'ground_plane'``: at every pixel of the output scale the log depth of the road seen there
  (:func:`ground_log_depth`: the frame's ground plane, or the level plane ``camera_height``
  below the camera, through its ``P``), ``prior_max_depth`` at and above the horizon: the
  per-pixel prior the reference's precompute builds before reducing it to one number. The
  residual is then 0 on the road however far it is, and the network learns what stands on it.

Calibration of the GAC stages (``intrinsics_mode``):

* ``'correct'`` (default): each GAC gets the input projection ``P`` and its map's true
  stride (16, 8), so its feature-map projection is ``P`` with rows 0-1 divided by 16 / 8.
* ``'reference'``: the reference's bug (reference_impl.md Sec. 7.2): ``P`` is replaced by
  ``[K | 0]`` (translation zeroed) with rows 0-1 pre-divided by 32 / 16, and the GAC divides
  by 16 again: effective divisors 512 / 256. Use it to run weights trained by the reference.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
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
from gac_jax.models.resnet import (
    ResNet,
    batch_norm_layer,
    layer_output_size,
    uses_plain_formulation,
)

INTRINSICS_MODES = ("correct", "reference")
OUTPUT_PRIORS = ("mean", "ground_plane")
DECODER_CONVS = ("plain", "deformable")
OUTPUT_SCALES = ("scale_1", "scale_4", "scale_8")
# decoder stage -> (skip layer, output stride, uses GAC when use_gac)
DECODER_STAGES = (
    ("up0", "layer3", 16, True),
    ("up1", "layer2", 8, True),
    ("up2", "layer1", 4, False),
)
REFERENCE_GAC_STRIDE = 16  # the reference's LookGround always divides by 16


def _linear_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """align_corners=True linear interpolation taps: (i0, i1, w1), each (n_out,)."""
    if n_out == 1 or n_in == 1:
        src = np.zeros(n_out)
    else:
        src = np.arange(n_out) * ((n_in - 1) / (n_out - 1))
    i0 = np.minimum(np.floor(src).astype(np.int32), n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, (src - i0).astype(np.float32)


def resize_bilinear_align_corners(x: jax.Array, size: tuple[int, int]) -> jax.Array:
    """Bilinear resize with PyTorch's ``align_corners=True`` (corner pixels map to corners).

    Output pixel ``o`` of an axis of length ``n_out`` reads input coordinate
    ``o * (n_in - 1) / (n_out - 1)``; separable linear interpolation (no antialiasing).

    Args:
      x: (B, H, W, C).
      size: (H_out, W_out).
    Returns:
      (B, H_out, W_out, C) in the dtype of ``x``.
    """
    if x.ndim != 4:
        raise ValueError(f"expected NHWC features (B,H,W,C), got shape {x.shape}")
    for axis, n_out in ((1, size[0]), (2, size[1])):
        i0, i1, w1 = _linear_taps(x.shape[axis], n_out)
        shape = [1, 1, 1, 1]
        shape[axis] = n_out
        w1 = jnp.asarray(w1.reshape(shape), x.dtype)
        x = jnp.take(x, i0, axis=axis) * (1 - w1) + jnp.take(x, i1, axis=axis) * w1
    return x


def pad_or_crop_to(x: jax.Array, size: tuple[int, int]) -> jax.Array:
    """Zero-pads (or crops, if larger) (B,H,W,C) to (B,*size,C), split ``diff // 2`` before and
    the rest after, like the reference's ``F.pad(x, [dX//2, dX - dX//2, dY//2, dY - dY//2])``."""
    dy, dx = size[0] - x.shape[1], size[1] - x.shape[2]
    config = [(0, 0, 0), (dy // 2, dy - dy // 2, 0), (dx // 2, dx - dx // 2, 0), (0, 0, 0)]
    return jax.lax.pad(x, jnp.zeros((), x.dtype), config)


def gac_projection(P: jax.Array, stride: int, intrinsics_mode: str) -> tuple[jax.Array, int]:
    """What a decoder GAC at map stride ``stride`` is given: ``(P_given, gac_stride)``.

    The GAC's feature-map projection is then ``feature_projection(P_given, gac_stride)``:

    * ``'correct'``: ``(P, stride)`` -> rows 0-1 of ``P`` divided by ``stride`` once.
    * ``'reference'``: ``([K | 0] with rows 0-1 / (2 * stride), 16)`` -> effective divisor
      ``32 * stride`` (512 at stride 16, 256 at stride 8), translation column zeroed.

    Args:
      P: (B, 3, 4) projection of the network input, in input pixels.
      stride: output stride of the decoder stage (16 or 8).
    """
    if intrinsics_mode not in INTRINSICS_MODES:
        raise ValueError(
            f"intrinsics_mode must be one of {INTRINSICS_MODES}, got {intrinsics_mode!r}"
        )
    if intrinsics_mode == "correct":
        return P, stride
    K0 = P.at[..., 3].set(0.0)
    pre = 2.0 * stride  # the reference passes scale=32 (up0) / 16 (up1) ...
    scale = jnp.asarray([1.0 / pre, 1.0 / pre, 1.0], K0.dtype)
    return K0 * scale[:, None], REFERENCE_GAC_STRIDE  # ... and LookGround divides by 16 again


def mean_log_depth(
    depth_maps: Iterable[np.ndarray], min_depth: float = 0.1, max_depth: float = 100.0
) -> float:
    """Global mean natural-log depth over the valid pixels of GT depth maps (``prior_mean``).

    Pixels count when ``min_depth < depth < max_depth`` (metres; 0 = no measurement).
    Accumulated in float64 over any number of maps of any shapes. (The reference also mixes a
    synthetic ground-plane prior map into these sums; this helper uses the GT only.)

    Raises:
      ValueError: no valid pixel in any map.
    """
    total, count = 0.0, 0
    for depth in depth_maps:
        depth = np.asarray(depth, np.float64)
        valid = (depth > min_depth) & (depth < max_depth)
        total += float(np.log(depth[valid]).sum())
        count += int(valid.sum())
    if count == 0:
        raise ValueError("mean_log_depth: no valid depth pixel in the given maps")
    return total / count


def _conv(features: int, kernel: int, fan_in: int, dtype: Any, pdt: Any, name: str) -> nn.Conv:
    pad = kernel // 2
    return nn.Conv(
        features,
        (kernel, kernel),
        padding=((pad, pad), (pad, pad)),
        kernel_init=torch_conv_kernel_init,
        bias_init=torch_conv_bias_init(fan_in * kernel * kernel),
        dtype=dtype,
        param_dtype=pdt,
        name=name,
    )


class ResizedConvHead(nn.Module):
    """``conv3x3(C -> 1)`` (zero padding 1, with bias) of ``x`` bilinearly resized to ``size``
    (``align_corners=True``): the full-resolution head ``out_scale_1``.

    ``__call__(x (B,h,w,C)) -> (B,H,W,1)``, the same variables as ``nn.Conv`` (``kernel``
    (3,3,C,1), ``bias`` (1,), same initialisers). Computed in the cheaper order: the 9 taps
    first, as a 1x1 conv C->9 on the small map, then the resize of those 9 channels, then the
    sum of the taps shifted into place (zero outside the image, like the conv's padding).
    Exact up to float32 rounding, because the resize mixes pixels channel by channel and so
    commutes with the per-pixel channel mixing. On XLA:CPU the plain order's gradient
    gathers and transposes the resized C-channel map (the largest tensor of the step); under
    :func:`gac_jax.models.resnet.plain_formulation` the plain order is used (tests compare).
    """

    size: tuple[int, int]
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        c = x.shape[-1]
        kernel = self.param("kernel", torch_conv_kernel_init, (3, 3, c, 1), self.param_dtype)
        bias = self.param("bias", torch_conv_bias_init(9 * c), (1,), self.param_dtype)
        kernel, bias = kernel.astype(self.dtype), bias.astype(self.dtype)
        x = x.astype(self.dtype)
        if uses_plain_formulation():
            full = resize_bilinear_align_corners(x, self.size)
            dn = ("NHWC", "HWIO", "NHWC")
            y = jax.lax.conv_general_dilated(full, kernel, (1, 1), ((1, 1), (1, 1)), None, None, dn)
            return y + bias
        taps = jnp.einsum("bhwc,kc->bhwk", x, kernel[..., 0].reshape(9, c))  # k = 3 * dy + dx
        taps = resize_bilinear_align_corners(taps, self.size)
        H, W = self.size
        padded = jnp.pad(taps, ((0, 0), (1, 1), (1, 1), (0, 0)))
        y = sum(
            padded[:, dy : dy + H, dx : dx + W, 3 * dy + dx] for dy in range(3) for dx in range(3)
        )
        return y[..., None] + bias


class UpStage(nn.Module):
    """One decoder stage (reference ``Up`` + ``DoubleConv``). See the module docstring.

    ``__call__(low (B,h,w,C1), skip (B,H,W,C2), P (B,3,4), train, plane (B,4) or None)`` returns
    ``(features (B,H,W,features), gac outputs dict or None)``; ``P`` is the input projection
    (used only when ``use_gac``), handed to the GAC via :func:`gac_projection`.
    """

    features: int
    stride: int
    use_gac: bool = False
    decoder_conv: str = "plain"
    intrinsics_mode: str = "correct"
    baseline: float = DEFAULT_BASELINE
    camera_height: float = DEFAULT_CAMERA_HEIGHT
    object_height: float = DEFAULT_OBJECT_HEIGHT
    offset_formula: str = "paper"
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(
        self,
        low: jax.Array,
        skip: jax.Array,
        P: jax.Array,
        train: bool,
        plane: jax.Array | None = None,
    ) -> tuple[jax.Array, dict[str, jax.Array] | None]:
        if self.decoder_conv not in DECODER_CONVS:
            raise ValueError(
                f"decoder_conv must be one of {DECODER_CONVS}, got {self.decoder_conv!r}"
            )
        dt, pdt = self.dtype, self.param_dtype
        up = resize_bilinear_align_corners(low.astype(dt), (2 * low.shape[1], 2 * low.shape[2]))
        up = pad_or_crop_to(up, skip.shape[1:3])
        x = jnp.concatenate([skip.astype(dt), up], axis=-1)
        channels = x.shape[-1]
        gac_out = None
        if self.use_gac:
            P_given, gac_stride = gac_projection(P, self.stride, self.intrinsics_mode)
            gac_out = GroundAwareConv(
                stride=gac_stride,
                baseline=self.baseline,
                camera_height=self.camera_height,
                object_height=self.object_height,
                offset_formula=self.offset_formula,
                dtype=dt,
                param_dtype=pdt,
                name="gac",
            )(x, P_given, plane)
            x = gac_out["features"]
        x = _conv(channels, 5, channels, dt, pdt, "conv1")(x)
        x = batch_norm_layer(train, dt, pdt, "bn1", relu=True)(x)
        if self.decoder_conv == "deformable":
            x = ModulatedDeformConv(self.features, 3, dtype=dt, param_dtype=pdt, name="conv2")(x)
        else:
            x = _conv(self.features, 3, channels, dt, pdt, "conv2")(x)
        x = batch_norm_layer(train, dt, pdt, "bn2", relu=True)(x)
        return x, gac_out


class DepthUNet(nn.Module):
    """Ground-aware depth U-Net. Attributes (plain values, no config object):

      depth: ResNet depth of the encoder (34 in the paper); width: its base width (64).
      use_gac: GAC in the stride-16 and stride-8 decoder stages (False = the "Base U-Net").
      decoder_conv: ``'plain'`` (paper: two plain convs) or ``'deformable'`` (the reference:
        the second conv is DCNv2; with ResNet-34 this has 43,258,456 parameters).
      intrinsics_mode: ``'correct'`` or ``'reference'`` (see the module docstring).
      decoder_features: output channels of up0, up1, up2; ``None`` -> ``(4w, w, w)``.
      prior_mean: constant added to every head output (global mean log-depth, metres).
      baseline / camera_height / object_height / offset_formula: GAC geometry, see
        :class:`~gac_jax.models.ground_aware_conv.GroundAwareConv`.
      dtype / param_dtype: computation / parameter dtypes (outputs are float32).

    ``__call__(images (B,H,W,3) ImageNet-normalised RGB, P (B,3,4) projection of these
    images in their pixels, train: bool, plane (B,4) each frame's ground plane (None: the level
    plane of camera_height), see :class:`~gac_jax.models.ground_aware_conv.GroundAwareConv`)``
    returns::

      {'log_depth': {'scale_1': (B,H,W), 'scale_4': (B,H4,W4), 'scale_8': (B,H8,W8)},
       'depth': (B,H,W) metres = exp(log_depth['scale_1']),
       'gac_offsets': {'up0': (B,H16,W16), 'up1': (B,H8,W8)}}   # only with use_gac

    where ``Hs = layer_output_size(H, layer)`` of the stride-s ResNet layer (``H/s`` when H is
    divisible by 32; :func:`output_sizes`) and ``gac_offsets`` are the GAC's vertical sampling
    offsets in rows of its map. ``train=True`` uses batch statistics (apply with
    ``mutable=['batch_stats']``).
    """

    depth: int = 34
    width: int = 64
    use_gac: bool = True
    decoder_conv: str = "plain"
    intrinsics_mode: str = "correct"
    decoder_features: Sequence[int] | None = None
    prior_mean: float = 0.0
    output_prior: str = "mean"
    prior_max_depth: float = 75.0
    baseline: float = DEFAULT_BASELINE
    camera_height: float = DEFAULT_CAMERA_HEIGHT
    object_height: float = DEFAULT_OBJECT_HEIGHT
    offset_formula: str = "paper"
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(
        self, images: jax.Array, P: jax.Array, train: bool, plane: jax.Array | None = None
    ) -> dict[str, Any]:
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"expected NHWC RGB images (B,H,W,3), got shape {images.shape}")
        B, H, W, _ = images.shape
        if P.shape != (B, 3, 4):
            raise ValueError(f"P must have shape (B,3,4) = {(B, 3, 4)}, got {P.shape}")
        if self.output_prior not in OUTPUT_PRIORS:
            raise ValueError(
                f"output_prior must be one of {OUTPUT_PRIORS}, got {self.output_prior!r}"
            )
        if self.intrinsics_mode not in INTRINSICS_MODES:
            raise ValueError(
                f"intrinsics_mode must be one of {INTRINSICS_MODES}, got {self.intrinsics_mode!r}"
            )
        features = self.decoder_features
        if features is None:
            features = (4 * self.width, self.width, self.width)
        if len(features) != len(DECODER_STAGES):
            raise ValueError(f"decoder_features needs 3 entries, got {features}")
        dt, pdt = self.dtype, self.param_dtype
        skips = ResNet(
            depth=self.depth,
            num_stages=4,
            width=self.width,
            dtype=dt,
            param_dtype=pdt,
            name="backbone",
        )(images, train)
        P = jnp.asarray(P, jnp.float32)

        x = skips["layer4"]
        decoded: dict[str, jax.Array] = {}
        offsets: dict[str, jax.Array] = {}
        for (name, skip, stride, gac), n_out in zip(DECODER_STAGES, features, strict=True):
            x, gac_out = UpStage(
                features=n_out,
                stride=stride,
                use_gac=self.use_gac and gac,
                decoder_conv=self.decoder_conv,
                intrinsics_mode=self.intrinsics_mode,
                baseline=self.baseline,
                camera_height=self.camera_height,
                object_height=self.object_height,
                offset_formula=self.offset_formula,
                dtype=dt,
                param_dtype=pdt,
                name=name,
            )(x, skips[skip], P, train, plane)
            decoded[name] = x
            if gac_out is not None:
                offsets[name] = gac_out["offset_rows"]

        heads = {"scale_8": decoded["up1"], "scale_4": decoded["up2"]}
        log_depth = {}
        for scale in OUTPUT_SCALES:
            if scale == "scale_1":  # the scale-4 features resized to the input size
                head = ResizedConvHead((H, W), dt, pdt, name=f"out_{scale}")
                f = head(decoded["up2"])
            else:
                f = _conv(1, 3, heads[scale].shape[-1], dt, pdt, f"out_{scale}")(heads[scale])
            if self.output_prior == "ground_plane":
                prior = ground_log_depth(
                    P, plane, f.shape[1:3], H / f.shape[1], self.camera_height,
                    self.prior_max_depth,
                )  # fmt: skip
            else:
                prior = self.prior_mean
            log_depth[scale] = prior + f[..., 0].astype(jnp.float32)
        out: dict[str, Any] = {
            "log_depth": log_depth,
            "depth": jnp.exp(log_depth["scale_1"]),
        }
        if offsets:
            out["gac_offsets"] = offsets
        return out


def ground_log_depth(
    P: jax.Array,
    plane: jax.Array | None,
    size: tuple[int, int],
    stride: float,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    max_depth: float = 75.0,
) -> jax.Array:
    """Log depth (m) of the road seen at every pixel of an (h, w) map of the input.

    Args:
      P: (B, 3, 4) projection of the network input (input pixels).
      plane: (B, 4) ground planes (:mod:`gac_jax.models.ground_plane`), or None for the level
        plane ``camera_height`` below the camera.
      size: (h, w) of the map; stride: input pixels per map pixel (rows 0-1 of ``P`` divided
        by it, as the GAC's feature maps).
      max_depth: the depth at and above the horizon, and the most the road gets.
    Returns:
      (B, h, w) float32 ``log(min(z_road, max_depth))``.
    """
    B = P.shape[0]
    Pf = feature_projection(jnp.asarray(P, jnp.float32), stride)
    planes = frame_planes(plane, B, camera_height, jnp.float32)
    # the GAC's virtual disparity fy * B / z for a baseline B = 1: fy / z
    _, _, disp = ground_maps(Pf, planes, size, DEFAULT_OBJECT_HEIGHT, 1.0, "paper")
    inverse = disp / jnp.abs(Pf[:, 1, 1])[:, None, None]
    return -jnp.log(jnp.maximum(inverse, 1.0 / max_depth))


def output_sizes(image_size: tuple[int, int]) -> dict[str, tuple[int, int]]:
    """(h, w) of every output scale for an input (H, W); 352x1216 -> scale_8 44x152,
    scale_4 88x304, scale_1 352x1216."""
    H, W = image_size
    return {
        "scale_1": (H, W),
        "scale_4": (layer_output_size(H, 1), layer_output_size(W, 1)),
        "scale_8": (layer_output_size(H, 2), layer_output_size(W, 2)),
    }
