"""Modulated deformable convolution (DCNv2, Zhu et al. 2019), NHWC, stride 1, "same" padding.

The reference depth U-Net (and the reference ``Yolo3D`` detector variant) uses mmdetection's
``ModulatedDeformConvPack``: a plain conv ``conv_offset`` (k x k, C -> 3 k^2, zero-initialised)
predicts, per output pixel, a (dy, dx) offset and a mask logit for each of the ``K = k^2``
kernel taps; the main kernel then convolves the bilinearly resampled, mask-weighted taps.

Channel layout of ``conv_offset`` (as in mmdetection: ``o1, o2, m = chunk(out, 3)``,
``offset = cat(o1, o2)``, ``mask = sigmoid(m)``): channels ``[2k, 2k+1]`` are ``(dy_k, dx_k)``
for tap ``k = i * k_w + j`` (row-major over the kernel window, i = kernel row), channels
``2K + k`` are the mask logits.

Sampling: output pixel ``(h, w)``, tap ``(i, j)`` reads the input at the fractional position
``(h - p + i + dy_k, w - p + j + dx_k)`` (``p = k // 2``) by bilinear interpolation with zero
padding (corners outside the map contribute 0, like the CUDA kernel). Implemented as four
gathers over the K taps followed by one matmul ``(K*C) -> F``; memory is ``O(B H W K C)``.

At initialisation the offsets are 0 and the masks ``sigmoid(0) = 0.5``, so the layer equals
``0.5 * conv_kxk(x) + bias`` (the bias is not modulated).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from gac_jax.models.initializers import torch_conv_kernel_init


def deformable_sample(x: jax.Array, offsets: jax.Array, kernel_size: int) -> jax.Array:
    """Bilinearly samples the ``kernel_size**2`` displaced taps of every output pixel.

    Args:
      x: (B, H, W, C) input features.
      offsets: (B, H, W, K, 2) per-tap ``(dy, dx)`` displacements in pixels, ``K = k*k``,
        taps in row-major kernel order.
      kernel_size: k (odd).
    Returns:
      (B, H, W, K, C): tap ``(i, j)`` of pixel ``(h, w)`` sampled at
      ``(h - k//2 + i + dy, w - k//2 + j + dx)``, zero outside the map.
    """
    if x.ndim != 4:
        raise ValueError(f"expected NHWC features (B,H,W,C), got shape {x.shape}")
    B, H, W, C = x.shape
    K = kernel_size * kernel_size
    if kernel_size % 2 != 1:
        raise ValueError(f"kernel_size must be odd, got {kernel_size}")
    if offsets.shape != (B, H, W, K, 2):
        raise ValueError(f"offsets must have shape {(B, H, W, K, 2)}, got {offsets.shape}")
    pad = kernel_size // 2
    taps = jnp.arange(kernel_size, dtype=jnp.float32) - pad
    tap_y = jnp.repeat(taps, kernel_size)  # (K,) row offsets, row-major
    tap_x = jnp.tile(taps, kernel_size)  # (K,) column offsets
    offsets = offsets.astype(jnp.float32)
    py = jnp.arange(H, dtype=jnp.float32)[None, :, None, None] + tap_y + offsets[..., 0]
    px = jnp.arange(W, dtype=jnp.float32)[None, None, :, None] + tap_x + offsets[..., 1]
    y0 = jnp.floor(py)
    x0 = jnp.floor(px)
    wy1 = py - y0
    wx1 = px - x0
    flat = x.reshape(B, H * W, C)
    out = jnp.zeros((B, H * W * K, C), x.dtype)
    for dy, wy in ((0, 1.0 - wy1), (1, wy1)):
        for dx, wx in ((0, 1.0 - wx1), (1, wx1)):
            yy = y0 + dy
            xx = x0 + dx
            inside = (yy >= 0) & (yy <= H - 1) & (xx >= 0) & (xx <= W - 1)
            weight = jnp.where(inside, wy * wx, 0.0).reshape(B, H * W * K, 1)
            index = (jnp.clip(yy, 0, H - 1) * W + jnp.clip(xx, 0, W - 1)).astype(jnp.int32)
            gathered = jnp.take_along_axis(flat, index.reshape(B, H * W * K, 1), axis=1)
            out = out + weight.astype(x.dtype) * gathered
    return out.reshape(B, H, W, K, C)


def modulated_deform_conv(
    x: jax.Array,
    offsets: jax.Array,
    mask: jax.Array,
    kernel: jax.Array,
    bias: jax.Array | None = None,
) -> jax.Array:
    """DCNv2 with given offsets and masks (stride 1, "same" padding).

    Args:
      x: (B, H, W, C).
      offsets: (B, H, W, K, 2) per-tap ``(dy, dx)`` in pixels.
      mask: (B, H, W, K) modulation (already through the sigmoid).
      kernel: (k, k, C, F) HWIO weights.
      bias: optional (F,), added unmodulated.
    Returns:
      (B, H, W, F) = ``sum_{k, c} mask_k * sample_k(x)[c] * kernel[k, c, :] + bias``.
    """
    kh, kw, C, F = kernel.shape
    if kh != kw:
        raise ValueError(f"kernel must be square, got shape {kernel.shape}")
    sampled = deformable_sample(x, offsets, kh) * mask[..., None].astype(x.dtype)
    out = jnp.einsum("bhwkc,kcf->bhwf", sampled, kernel.reshape(kh * kw, C, F).astype(x.dtype))
    if bias is not None:
        out = out + bias.astype(out.dtype)
    return out


class ModulatedDeformConv(nn.Module):
    """DCNv2 layer (reference ``ModulatedDeformConvPack``). (B,H,W,C) -> (B,H,W,features).

    Parameters: ``kernel`` (k,k,C,F) ~ U(+-1/sqrt(k*k*C)) and ``bias`` (F,) = 0 (mmdetection's
    init), and the sub-module ``conv_offset`` (conv k x k, C -> 3 k^2, weights and bias 0).
    """

    features: int
    kernel_size: int = 3
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        if x.ndim != 4:
            raise ValueError(f"expected NHWC features (B,H,W,C), got shape {x.shape}")
        B, H, W, C = x.shape
        k = self.kernel_size
        K = k * k
        pad = k // 2
        x = x.astype(self.dtype)
        raw = nn.Conv(
            3 * K,
            (k, k),
            padding=((pad, pad), (pad, pad)),
            kernel_init=nn.initializers.zeros,
            bias_init=nn.initializers.zeros,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="conv_offset",
        )(x).astype(jnp.float32)
        offsets = raw[..., : 2 * K].reshape(B, H, W, K, 2)  # [dy_0, dx_0, dy_1, dx_1, ...]
        mask = jax.nn.sigmoid(raw[..., 2 * K :])
        kernel = self.param(
            "kernel", torch_conv_kernel_init, (k, k, C, self.features), self.param_dtype
        )
        bias = self.param("bias", nn.initializers.zeros, (self.features,), self.param_dtype)
        return modulated_deform_conv(
            x, offsets, mask, kernel.astype(self.dtype), bias.astype(self.dtype)
        )
