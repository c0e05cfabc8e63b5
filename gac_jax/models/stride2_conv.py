"""A stride-2 convolution written as a stride-1 convolution over a space-to-depth input.

The ResNet stem (7x7, stride 2, 3 input channels) is the costliest single convolution of a
small trunk on XLA:CPU, mostly its weight gradient: with 3 channels the contraction is
tiny and strided. Folding each 2x2 block of pixels into channels gives the same sum as a
4x4, stride-1 convolution over 12 channels (the 7x7 kernel padded with one zero row and
column to 8x8 and folded the same way), which XLA:CPU runs faster forward and backward:

    y[o] = sum_{d=0..6} x_pad[2o + d] k[d]            (per spatial dim)
         = sum_{a=0..3, b=0..1} xs[o + a, b] k8[2a + b],   xs[p, b] = x_pad[2p + b]

Same mathematics, different summation order (float32 rounding differs at the 1e-7 relative
level). :func:`conv_general_dilated` is a drop-in for ``lax.conv_general_dilated`` as
``flax.linen.Conv(conv_general_dilated=...)`` calls it, so parameters keep their names and
shapes; any other configuration falls through to ``lax.conv_general_dilated``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

_NHWC = ("NHWC", "HWIO", "NHWC")


def _is_nhwc(dimension_numbers) -> bool:
    if dimension_numbers is None:
        return False
    if isinstance(dimension_numbers, tuple) and all(isinstance(d, str) for d in dimension_numbers):
        return tuple(dimension_numbers) == _NHWC
    return dimension_numbers == lax.conv_dimension_numbers((1, 1, 1, 1), (1, 1, 1, 1), _NHWC)


def space_to_depth_conv(x: jax.Array, kernel: jax.Array, padding) -> jax.Array:
    """Stride-2 conv of ``x`` (B, H, W, C) with ``kernel`` (kh, kw, C, F), explicit padding.

    Returns (B, Ho, Wo, F) with ``Ho = (H + lo + hi - kh) // 2 + 1`` (likewise W), exactly the
    shape of ``lax.conv_general_dilated(x, kernel, (2, 2), padding, NHWC/HWIO/NHWC)``.
    """
    b, h, w, c = x.shape
    kh, kw, _, f = kernel.shape
    (top, bottom), (left, right) = padding
    ho = (h + top + bottom - kh) // 2 + 1
    wo = (w + left + right - kw) // 2 + 1
    th, tw = (kh + 1) // 2, (kw + 1) // 2  # taps of the folded kernel
    # pad/crop so that the padded input has exactly 2 (Ho + th - 1) rows (the extra rows
    # only meet the folded kernel's zero taps), then fold 2x2 pixel blocks into channels
    hp, wp = 2 * (ho + th - 1), 2 * (wo + tw - 1)
    x = lax.pad(
        x, jnp.zeros((), x.dtype), [(0, 0, 0), (top, hp - h - top, 0), (left, wp - w - left, 0),
                                    (0, 0, 0)],
    )  # fmt: skip
    xs = x.reshape(b, hp // 2, 2, wp // 2, 2, c).transpose(0, 1, 3, 2, 4, 5)
    xs = xs.reshape(b, hp // 2, wp // 2, 4 * c)
    k8 = jnp.pad(kernel, ((0, 2 * th - kh), (0, 2 * tw - kw), (0, 0), (0, 0)))
    k8 = k8.reshape(th, 2, tw, 2, c, f).transpose(0, 2, 1, 3, 4, 5).reshape(th, tw, 4 * c, f)
    return lax.conv_general_dilated(xs, k8, (1, 1), "VALID", dimension_numbers=_NHWC)


def conv_general_dilated(
    lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
    dimension_numbers=None, feature_group_count=1, precision=None, **kwargs,
):  # fmt: skip
    """``lax.conv_general_dilated``, via :func:`space_to_depth_conv` for plain stride-2 NHWC."""
    plain_dilation = all(d == 1 for d in (lhs_dilation or (1, 1))) and all(
        d == 1 for d in (rhs_dilation or (1, 1))
    )
    if (
        tuple(window_strides) == (2, 2)
        and plain_dilation
        and feature_group_count == 1
        and not isinstance(padding, str)
        and lhs.ndim == 4
        and _is_nhwc(dimension_numbers)
        and not kwargs
    ):
        return space_to_depth_conv(lhs, rhs, tuple(tuple(p) for p in padding))
    return lax.conv_general_dilated(
        lhs, rhs, window_strides, padding, lhs_dilation=lhs_dilation, rhs_dilation=rhs_dilation,
        dimension_numbers=dimension_numbers, feature_group_count=feature_group_count,
        precision=precision, **kwargs,
    )  # fmt: skip
