"""Losses of the depth network (paper Sec. "Network Architecture for Monocular Depth
Prediction"): per output scale ``l``, ``L = sum_l w_l (L_SI + alpha * L_smooth)``. Pure jnp.

* :func:`scale_invariant_loss` - ``L_SI = (1/n) sum d^2 - (lambda/n^2) (sum d)^2`` with
  ``d = log z - log z*`` on the valid GT pixels (``min_depth < z* < max_depth``), ``n`` counted
  over the *whole batch* (so the value does not depend on how a jitted batch is sharded),
  residuals ``|d| <= residual_clip`` zeroed (the paper's clipping of tiny losses; ``n`` still
  counts them), no square root and no x10 (as the reference).
* :func:`edge_aware_smoothness` - ``L_smooth = (1/N) sum |dx z| e^{-s |dx I|} + |dy z|
  e^{-s |dy I|}`` over all N pixels of the batch on the predicted log-depth map ``z`` (whose
  gradients equal those of the residual: they differ by the constant prior mean), forward
  differences with replicate padding (0 at the last column / row), ``|dI|`` the mean over
  channels of the absolute image difference (monodepth's edge weight, the paper's
  ``||dI||``), ``I`` the (normalised) network input average-pooled to the scale.
* :func:`downsample_depth` - GT at a coarser scale: adaptive max-pooling of inverse depth, so
  each cell keeps its nearest valid point; cells without one are 0 (invalid).
* :func:`depth_loss` - the sum over scales.

Defaults follow the paper (``lambda = 0.3``, ``alpha = 0.3``, edge weight ``e^{-|dI|}``, all
scales weight 1). The reference code differs for the smoothness term: its edge weight is
``exp(-20 |dI|)`` and its weight 0.003 (code default) or 0.0 (the released config, i.e. no
smoothness); the paper's "alpha = 0.3" matches no smoothness constant of the code (0.3 is the
SI lambda there). :data:`REFERENCE_LOSS_OPTIONS` reproduces the released configuration,
:data:`PAPER_LOSS_OPTIONS` the defaults. Masks without valid pixels give 0 (finite gradients).
"""

from __future__ import annotations

import types
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

DEFAULT_SCALE_WEIGHTS = types.MappingProxyType({"scale_1": 1.0, "scale_4": 1.0, "scale_8": 1.0})

PAPER_LOSS_OPTIONS = types.MappingProxyType(
    {
        "si_lambda": 0.3,
        "min_depth": 0.1,
        "max_depth": 100.0,
        "residual_clip": 1e-3,
        "smooth_weight": 0.3,
        "edge_sharpness": 1.0,
        "scale_weights": DEFAULT_SCALE_WEIGHTS,
    }
)
# config/MonoDepth_example: smooth_loss_weight 0.0 (code default 0.003), minor_weight 1.0.
REFERENCE_LOSS_OPTIONS = types.MappingProxyType(
    {**PAPER_LOSS_OPTIONS, "smooth_weight": 0.0, "edge_sharpness": 20.0}
)


def _adaptive_bins(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray]:
    """PyTorch adaptive-pool bins ``[floor(i n_in / n_out), ceil((i+1) n_in / n_out))`` as
    (n_out, L) indices (padded by repeating the last index) and a (n_out, L) validity mask."""
    i = np.arange(n_out)
    start = (i * n_in) // n_out
    end = -((-(i + 1) * n_in) // n_out)
    length = int((end - start).max())
    index = start[:, None] + np.arange(length)[None, :]
    valid = index < end[:, None]
    return np.minimum(index, end[:, None] - 1), valid


def adaptive_pool(x: jax.Array, size: tuple[int, int], reduce: str) -> jax.Array:
    """Adaptive max / average pooling over axes 1 and 2 (PyTorch's bins).

    Args:
      x: (B, H, W, ...) array.
      size: (h, w) with ``h <= H``, ``w <= W``.
      reduce: ``'max'`` or ``'mean'``.
    Returns:
      (B, h, w, ...): cell ``(i, j)`` reduces rows ``[floor(iH/h), ceil((i+1)H/h))`` and
      columns ``[floor(jW/w), ceil((j+1)W/w))`` (plain k x k pooling when divisible).
    """
    if reduce not in ("max", "mean"):
        raise ValueError(f"reduce must be 'max' or 'mean', got {reduce!r}")
    if x.ndim < 3:
        raise ValueError(f"expected (B, H, W, ...) input, got shape {x.shape}")
    for axis, n_out in ((1, size[0]), (2, size[1])):
        n_in = x.shape[axis]
        if not 1 <= n_out <= n_in:
            raise ValueError(f"cannot pool an axis of length {n_in} to {n_out}")
        if n_in == n_out:
            continue
        if n_in % n_out == 0:
            x = x.reshape(*x.shape[:axis], n_out, n_in // n_out, *x.shape[axis + 1 :])
            x = x.max(axis=axis + 1) if reduce == "max" else x.mean(axis=axis + 1)
            continue
        index, valid = _adaptive_bins(n_in, n_out)
        g = jnp.take(x, jnp.asarray(index.reshape(-1)), axis=axis)
        g = g.reshape(*x.shape[:axis], *index.shape, *x.shape[axis + 1 :])
        if reduce == "max":  # repeated indices do not change a max
            x = g.max(axis=axis + 1)
        else:
            shape = [1] * g.ndim
            shape[axis], shape[axis + 1] = index.shape
            w = valid / valid.sum(axis=1, keepdims=True)
            x = (g * jnp.asarray(w.reshape(shape), g.dtype)).sum(axis=axis + 1)
    return x


def valid_depth(depth: jax.Array, min_depth: float = 0.1, max_depth: float = 100.0) -> jax.Array:
    """Boolean mask of usable GT pixels: ``min_depth < depth < max_depth`` (0 = no point)."""
    return (depth > min_depth) & (depth < max_depth)


def downsample_depth(depth: jax.Array, size: tuple[int, int], min_depth: float = 0.1) -> jax.Array:
    """Sparse GT depth (B,H,W) metres -> (B,h,w) keeping, per adaptive-pool cell, the nearest
    point deeper than ``min_depth`` (max-pool of inverse depth); cells without one are 0."""
    depth = jnp.asarray(depth, jnp.float32)
    point = depth > min_depth
    inverse = jnp.where(point, 1.0 / jnp.where(point, depth, 1.0), 0.0)
    pooled = adaptive_pool(inverse, size, "max")
    has_point = pooled > 0.0
    return jnp.where(has_point, 1.0 / jnp.where(has_point, pooled, 1.0), 0.0)


def scale_invariant_loss(
    log_depth: jax.Array,
    gt_depth: jax.Array,
    si_lambda: float = 0.3,
    min_depth: float = 0.1,
    max_depth: float = 100.0,
    residual_clip: float = 1e-3,
) -> tuple[jax.Array, jax.Array]:
    """Batch-pooled scale-invariant log loss.

    Args:
      log_depth: (B, h, w) predicted natural-log depth.
      gt_depth: (B, h, w) GT depth in metres at the same scale (0 = invalid).
    Returns:
      ``(loss, n)``: ``sum d^2 / n - si_lambda (sum d / n)^2`` (0 when ``n = 0``) and the
      number of valid pixels ``n`` (float32), both scalars.
    """
    if log_depth.shape != gt_depth.shape:
        raise ValueError(f"prediction {log_depth.shape} and GT {gt_depth.shape} shapes differ")
    log_depth = jnp.asarray(log_depth, jnp.float32)
    valid = valid_depth(gt_depth, min_depth, max_depth)
    d = log_depth - jnp.log(jnp.where(valid, gt_depth, 1.0).astype(jnp.float32))
    d = jnp.where(valid & (jnp.abs(d) > residual_clip), d, 0.0)
    n = valid.sum().astype(jnp.float32)
    n_safe = jnp.maximum(n, 1.0)
    loss = jnp.sum(d * d) / n_safe - si_lambda * jnp.square(jnp.sum(d) / n_safe)
    return loss, n


def edge_aware_smoothness(
    log_depth: jax.Array, image: jax.Array, edge_sharpness: float = 1.0
) -> jax.Array:
    """Mean over all pixels of ``|dx z| exp(-s |dx I|) + |dy z| exp(-s |dy I|)``.

    Args:
      log_depth: (B, h, w) predicted log depth (or residual).
      image: (B, h, w, C) image at the same scale.
      edge_sharpness: s (paper 1, reference 20).
    Returns:
      Scalar; the last column's x-difference and last row's y-difference are 0 (replicate
      padding) and the mean is over all ``B h w`` pixels.
    """
    if image.shape[:3] != log_depth.shape:
        raise ValueError(f"image {image.shape} does not match the depth map {log_depth.shape}")
    z = jnp.asarray(log_depth, jnp.float32)
    image = jnp.asarray(image, jnp.float32)
    dzx = jnp.abs(z[:, :, 1:] - z[:, :, :-1])
    dzy = jnp.abs(z[:, 1:, :] - z[:, :-1, :])
    dix = jnp.abs(image[:, :, 1:] - image[:, :, :-1]).mean(axis=-1)
    diy = jnp.abs(image[:, 1:, :] - image[:, :-1, :]).mean(axis=-1)
    total = jnp.sum(dzx * jnp.exp(-edge_sharpness * dix))
    total = total + jnp.sum(dzy * jnp.exp(-edge_sharpness * diy))
    return total / z.size


def depth_loss(
    log_depth: Mapping[str, jax.Array],
    gt_depth: jax.Array,
    image: jax.Array,
    *,
    si_lambda: float = 0.3,
    min_depth: float = 0.1,
    max_depth: float = 100.0,
    residual_clip: float = 1e-3,
    smooth_weight: float = 0.3,
    edge_sharpness: float = 1.0,
    scale_weights: Mapping[str, float] | None = None,
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Total depth loss ``sum_l w_l (L_SI + smooth_weight * L_smooth)`` over output scales.

    Args:
      log_depth: ``{scale: (B, h_l, w_l)}`` predicted log depth (``DepthUNet``'s
        ``out['log_depth']``); each scale in ``scale_weights`` must be present.
      gt_depth: (B, H, W) full-resolution GT depth in metres (0 = invalid); coarser scales
        use :func:`downsample_depth`.
      image: (B, H, W, C) network input, average-pooled to each scale for the edge weights.
      si_lambda, min_depth, max_depth, residual_clip: see :func:`scale_invariant_loss`.
      smooth_weight: alpha (0 skips the term); edge_sharpness: see
        :func:`edge_aware_smoothness`.
      scale_weights: ``{scale: weight}``, default :data:`DEFAULT_SCALE_WEIGHTS` (all 1);
        weight 0 skips a scale.
    Returns:
      ``(total, parts)`` with scalar float32 ``parts['si/<scale>']``,
      ``parts['smooth/<scale>']`` and ``parts['valid/<scale>']`` (valid GT pixel count).
    """
    gt_depth = jnp.asarray(gt_depth, jnp.float32)
    if gt_depth.ndim != 3 or image.shape[:3] != gt_depth.shape:
        raise ValueError(
            f"expected GT (B,H,W) and image (B,H,W,C) of one size, got {gt_depth.shape} "
            f"and {image.shape}"
        )
    weights = DEFAULT_SCALE_WEIGHTS if scale_weights is None else scale_weights
    total = jnp.zeros((), jnp.float32)
    parts: dict[str, jax.Array] = {}
    for scale, weight in weights.items():
        if weight == 0:
            continue
        if scale not in log_depth:
            raise ValueError(f"scale {scale!r} has a loss weight but no prediction")
        pred = log_depth[scale]
        size = tuple(pred.shape[1:3])
        gt = gt_depth if size == gt_depth.shape[1:] else downsample_depth(gt_depth, size, min_depth)
        si, n = scale_invariant_loss(pred, gt, si_lambda, min_depth, max_depth, residual_clip)
        parts[f"si/{scale}"] = si
        parts[f"valid/{scale}"] = n
        term = si
        if smooth_weight:
            pooled = adaptive_pool(jnp.asarray(image, jnp.float32), size, "mean")
            smooth = edge_aware_smoothness(pred, pooled, edge_sharpness)
            parts[f"smooth/{scale}"] = smooth
            term = term + smooth_weight * smooth
        total = total + weight * term
    return total, parts
