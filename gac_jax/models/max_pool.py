"""Max-pooling with a cheap custom gradient (same values and gradient as ``flax.linen.max_pool``).

JAX differentiates ``lax.reduce_window`` (max) through ``select_and_scatter_add``, which
XLA:CPU lowers to an index-tracking window reduction plus a scatter over the padded input:
for the ResNet stem pool of the default detector (batch 8, 80x360x32) that gradient costs
about ten times the forward pass. :func:`max_pool` computes the same forward (one
``reduce_window``) and writes the gradient as elementwise compares and strided pads that
XLA fuses into a few loops.

Gradient semantics (identical to flax/JAX's ``select_and_scatter_add`` with ``ge``): the
input is padded with ``-inf``; every output element sends its cotangent to the *first*
window position, in row-major window order, whose value equals the window maximum. Ties
therefore go to the top-most, then left-most element of the window. If that first position
is padding (only possible when the whole window is ``-inf``), the cotangent is dropped,
exactly as flax does. NaN inputs give NaN outputs and no gradient for that window.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from functools import partial

import jax
import jax.numpy as jnp
from jax import lax


def _config(x: jax.Array, window, strides, padding):
    nd = len(window)
    if x.ndim != nd + 2:
        raise ValueError(f"max_pool expects (B, *spatial{nd}, C) input, got shape {x.shape}")
    if len(strides) != nd or len(padding) != nd:
        raise ValueError("window, strides and padding must have one entry per spatial dim")
    window = (1, *window, 1)
    strides = (1, *strides, 1)
    padding = ((0, 0), *(tuple(p) for p in padding), (0, 0))
    return window, strides, padding


def _forward(x, window, strides, padding):
    return lax.reduce_window(x, -jnp.inf, lax.max, window, strides, padding)


@partial(jax.custom_vjp, nondiff_argnums=(1, 2, 3))
def _max_pool(x, window, strides, padding):
    return _forward(x, window, strides, padding)


def _max_pool_fwd(x, window, strides, padding):
    y = _forward(x, window, strides, padding)
    return y, (x, y)


def _first_hits(x_pad, y, window, strides):
    """{window offset: mask} where the offset is the first in row-major order equal to y.

    The index of the first hit is computed once (one small fusion over the output) and put
    behind an optimization barrier, so that the scatter below reads one int8 per output
    element instead of XLA re-deriving the compare chain for every input element.
    """
    offsets = list(itertools.product(*(range(w) for w in window)))
    first = jnp.full(y.shape, len(offsets), jnp.int8)
    for k in reversed(range(len(offsets))):
        offset = offsets[k]
        limit = [o + (n - 1) * s + 1 for o, n, s in zip(offset, y.shape, strides, strict=True)]
        first = jnp.where(lax.slice(x_pad, offset, limit, strides) == y, jnp.int8(k), first)
    first = lax.optimization_barrier(first)
    return {offset: first == k for k, offset in enumerate(offsets)}


def _scatter_generic(masks, g, padded_shape, strides):
    """Sums each offset's masked cotangent into the padded input (interior-padded copies)."""
    zero = jnp.zeros((), g.dtype)
    dx_pad = None
    for offset, first in masks.items():
        config = [
            (o, p - (o + (n - 1) * s + 1), s - 1)
            for o, n, s, p in zip(offset, g.shape, strides, padded_shape, strict=True)
        ]
        part = lax.pad(jnp.where(first, g, zero), zero, config)
        dx_pad = part if dx_pad is None else dx_pad + part
    return dx_pad


def _scatter_3x3_stride2(masks, g, padded_shape):
    """The same sum for a 3x3 window with stride 2 over (B, H, W, C), written per parity.

    Padded row ``p = 2q + 1`` only receives from output row ``q`` (window row 1); row
    ``p = 2q`` from output row ``q`` (window row 0) and ``q - 1`` (window row 2). Likewise for
    columns. The four (row parity, column parity) planes are interleaved by a reshape.
    """
    zero = jnp.zeros((), g.dtype)
    b, ho, wo, c = g.shape
    part = {k: jnp.where(m, g, zero) for k, m in masks.items()}

    def shift(a, rows: int, cols: int):
        # a: (B, Ho, Wo, C) -> (B, Ho + 1, Wo + 1, C) placed at offset (rows, cols)
        return lax.pad(a, zero, [(0, 0, 0), (rows, 1 - rows, 0), (cols, 1 - cols, 0), (0, 0, 0)])

    def plane(row_terms, col_terms):
        total = None
        for dr, sr in row_terms:
            for dc, sc in col_terms:
                t = shift(part[(0, dr, dc, 0)], sr, sc)
                total = t if total is None else total + t
        return total

    even, odd = ((0, 0), (2, 1)), ((1, 0),)
    planes = [[plane(r, cc) for cc in (even, odd)] for r in (even, odd)]
    # (B, Ho+1, 2, Wo+1, 2, C) -> (B, 2Ho+2, 2Wo+2, C)
    rows = [jnp.stack(pr, axis=3) for pr in planes]  # (B, Ho+1, Wo+1, 2, C)
    full = jnp.stack(rows, axis=2).reshape(b, 2 * ho + 2, 2 * wo + 2, c)
    return full[:, : padded_shape[1], : padded_shape[2]]


def _max_pool_bwd(window, strides, padding, residuals, g):
    x, y = residuals
    x_pad = lax.pad(x, jnp.array(-jnp.inf, x.dtype), [(lo, hi, 0) for lo, hi in padding])
    masks = _first_hits(x_pad, y, window, strides)
    if window == (1, 3, 3, 1) and strides == (1, 2, 2, 1):
        dx_pad = _scatter_3x3_stride2(masks, g, x_pad.shape)
    else:
        dx_pad = _scatter_generic(masks, g, x_pad.shape, strides)
    starts = [lo for lo, _ in padding]
    limits = [lo + n for (lo, _), n in zip(padding, x.shape, strict=True)]
    return (lax.slice(dx_pad, starts, limits),)


_max_pool.defvjp(_max_pool_fwd, _max_pool_bwd)


def max_pool(
    x: jax.Array,
    window_shape: Sequence[int],
    strides: Sequence[int],
    padding: Sequence[tuple[int, int]],
) -> jax.Array:
    """Max-pool over the spatial dims of ``x`` (B, *spatial, C), ``-inf`` padding.

    Same arguments and values as ``flax.linen.max_pool`` with explicit ``(lo, hi)`` padding
    pairs; the gradient is flax's too (ties: first position in row-major window order; see the
    module docstring) but costs a few fused elementwise loops instead of a scatter.
    """
    window, strides, padding = _config(x, tuple(window_shape), tuple(strides), padding)
    return _max_pool(x, window, strides, padding)
