"""IoU-based assignment of anchors to padded ground truth (jnp, static shapes, batched).

Reference rule (visualDet3D, ``fg 0.5 / bg 0.4``, no low-quality matching):

* each anchor takes the GT of maximum 2D IoU (valid GT only);
* max IoU ``>= pos_iou`` (0.5) -> positive, ``< neg_iou`` (0.4) -> negative,
  in between -> ignored; no best-anchor-per-GT forcing unless
  ``match_low_quality=True``;
* anchors outside the per-image ground mask are ignored (the reference removes
  them before assignment);
* positives whose bin has no valid prior for the matched GT's class are turned
  into ignores (neither positive nor negative);
* an image without valid GT has no positives *and no negatives* (all ignored).

The reference's quirk of keeping the invalid-bin positives when *all*
positives of an image are invalid is not reproduced (they are ignored too).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

POSITIVE, NEGATIVE, IGNORE = 1, 0, -1


def box_iou(boxes_a: jax.Array, boxes_b: jax.Array) -> jax.Array:
    """IoU of xyxy boxes ``(..., N, 4)`` x ``(..., M, 4)`` -> ``(..., N, M)``.

    Leading dimensions broadcast.

    Areas are ``(x2 - x1) * (y2 - y1)`` (no +1 pixel convention); the union is
    clamped to >= 1e-8.
    """
    a = boxes_a[..., :, None, :]
    b = boxes_b[..., None, :, :]
    iw = jnp.clip(jnp.minimum(a[..., 2], b[..., 2]) - jnp.maximum(a[..., 0], b[..., 0]), 0.0)
    ih = jnp.clip(jnp.minimum(a[..., 3], b[..., 3]) - jnp.maximum(a[..., 1], b[..., 1]), 0.0)
    inter = iw * ih
    area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
    area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    return inter / jnp.maximum(area_a + area_b - inter, 1e-8)


class Assignment(NamedTuple):
    """Result of :func:`assign_anchors` for ``B`` images and ``N`` anchors.

    Attributes:
      labels: (B, N) int32: 1 positive, 0 negative, -1 ignored.
      matched_gt: (B, N) int32 index into the GT axis M (meaningful where labels == 1).
      matched_class: (B, N) int32 class of the matched GT where positive, else -1.
      max_iou: (B, N) float32 max IoU over the image's valid GT (0 without GT).
    """

    labels: jax.Array
    matched_gt: jax.Array
    matched_class: jax.Array
    max_iou: jax.Array

    @property
    def positive(self) -> jax.Array:
        return self.labels == POSITIVE

    @property
    def negative(self) -> jax.Array:
        return self.labels == NEGATIVE


def first_argmax(x: jax.Array, x_max: jax.Array) -> jax.Array:
    """``jnp.argmax(x, axis=-1)`` (the first index of the maximum) given ``x_max = x.max(-1)``.

    ``x`` (..., M) float, ``x_max`` (...) -> (...) int32. Written as "the smallest index whose
    value equals the maximum": two plain reductions over the short last axis, which XLA:CPU
    vectorises, where ``jnp.argmax`` is one variadic (value, index) reduction it emits as a
    scalar loop: 2.5x faster for the (8, 14400, 32) IoU matrix of the default detector
    (docs/performance.md, "Findings"). Rows without a maximum (NaN) give ``M - 1``.
    """
    m = x.shape[-1]
    index = jnp.arange(m, dtype=jnp.int32)
    first = jnp.min(jnp.where(x == x_max[..., None], index, m), axis=-1)
    return jnp.minimum(first, m - 1).astype(jnp.int32)


def assign_anchors(
    anchor_boxes: jax.Array,
    gt_boxes: jax.Array,
    gt_mask: jax.Array,
    gt_class: jax.Array,
    *,
    ground_mask: jax.Array | None = None,
    prior_valid: jax.Array | None = None,
    pos_iou: float = 0.5,
    neg_iou: float = 0.4,
    match_low_quality: bool = False,
    low_quality_min_iou: float = 0.0,
) -> Assignment:
    """Assigns every anchor of every image (see module docstring).

    Args:
      anchor_boxes: (N, 4) xyxy anchors (network-input pixels).
      gt_boxes: (B, M, 4) xyxy GT 2D boxes, padded.
      gt_mask: (B, M) bool, True for real GT (entries with ``gt_class < 0`` are
        treated as padding as well).
      gt_class: (B, M) int class index (-1 padding).
      ground_mask: (B, N) bool anchors kept by the ground filter (None: all).
      prior_valid: (K, N) bool per-class prior validity of each anchor's bin
        (None: all valid).
      pos_iou, neg_iou: thresholds (positive ``>=``, negative ``<``).
      match_low_quality: also make each GT's best anchor(s) (those whose IoU
        equals the GT's maximum over ground-kept anchors, if ``> low_quality_min_iou``)
        positive for it; an anchor that is best for several GT takes the one of
        highest IoU. Off in the reference.

    Returns:
      :class:`Assignment`.
    """
    gt_boxes = jnp.asarray(gt_boxes, jnp.float32)
    gt_class = jnp.asarray(gt_class, jnp.int32)
    valid_gt = jnp.asarray(gt_mask, bool) & (gt_class >= 0)  # (B, M)
    batch, num_anchors = gt_boxes.shape[0], anchor_boxes.shape[0]
    if ground_mask is None:
        ground_mask = jnp.ones((batch, num_anchors), bool)
    ground_mask = jnp.asarray(ground_mask, bool)

    iou = box_iou(jnp.asarray(anchor_boxes, jnp.float32)[None], gt_boxes)  # (B, N, M)
    iou = jnp.where(valid_gt[:, None, :], iou, -1.0)
    max_iou = jnp.max(iou, axis=-1)
    matched_gt = first_argmax(iou, max_iou)  # (B, N)
    has_gt = valid_gt.any(axis=-1)[:, None]  # (B, 1)
    max_iou = jnp.where(has_gt, max_iou, 0.0)

    positive = max_iou >= pos_iou
    negative = max_iou < neg_iou
    if match_low_quality:
        kept_iou = jnp.where(ground_mask[:, :, None], iou, -1.0)
        gt_best = jnp.max(kept_iou, axis=1, keepdims=True)  # (B, 1, M)
        is_best = (kept_iou == gt_best) & (gt_best > low_quality_min_iou) & valid_gt[:, None, :]
        forced = is_best.any(axis=-1)
        best_iou = jnp.where(is_best, iou, -2.0)
        forced_gt = first_argmax(best_iou, jnp.max(best_iou, axis=-1))
        matched_gt = jnp.where(forced, forced_gt, matched_gt)
        positive = positive | forced
        negative = negative & ~forced

    matched_class = jnp.take_along_axis(gt_class, matched_gt, axis=1)  # (B, N)
    usable = ground_mask & has_gt
    positive = positive & usable
    negative = negative & usable & ~positive
    if prior_valid is not None:
        prior_valid = jnp.asarray(prior_valid, bool)
        bin_ok = prior_valid[jnp.clip(matched_class, 0), jnp.arange(num_anchors)[None, :]]
        positive = positive & bin_ok
    labels = jnp.where(positive, POSITIVE, jnp.where(negative, NEGATIVE, IGNORE)).astype(jnp.int32)
    return Assignment(
        labels=labels,
        matched_gt=matched_gt,
        matched_class=jnp.where(positive, matched_class, -1).astype(jnp.int32),
        max_iou=max_iou.astype(jnp.float32),
    )
