"""Greedy non-maximum suppression on 2D boxes (host side, numpy).

The reference implementation reads a misspelled config key and is therefore
always class-agnostic; here the choice is explicit (``class_agnostic``).
"""

from __future__ import annotations

import numpy as np


def _iou_rows(a: np.ndarray, area_a: np.ndarray, b: np.ndarray, area_b: np.ndarray) -> np.ndarray:
    """IoU (Na, Nb) of float64 xyxy boxes ``a``, ``b`` with their areas (clipped at 0)."""
    iw = np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0])
    ih = np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)


def _areas(boxes: np.ndarray) -> np.ndarray:
    return np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)


def box_iou_matrix(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """IoU (Na, Nb) of xyxy boxes (continuous coordinates: area = (x2-x1)*(y2-y1))."""
    a = np.asarray(boxes_a, np.float64).reshape(-1, 4)
    b = np.asarray(boxes_b, np.float64).reshape(-1, 4)
    return _iou_rows(a, _areas(a), b, _areas(b))


def nms(
    boxes: np.ndarray, scores: np.ndarray, iou_threshold: float, block: int = 256
) -> np.ndarray:
    """Indices of the boxes kept by greedy NMS, in descending score order.

    A box is suppressed when its IoU with an already kept, higher-scoring box
    is strictly greater than ``iou_threshold`` (torchvision's rule). Ties in
    score keep the lower index first (stable).

    The IoUs are computed a block of ``block`` boxes at a time (the next unsuppressed
    boxes against the unsuppressed rest), with the same per-pair arithmetic as
    :func:`box_iou_matrix`, so the decisions equal those of the full ``N x N``
    matrix while the memory and work follow the kept boxes.

    Args:
      boxes: (N, 4) xyxy.
      scores: (N,).
      block: boxes per IoU block.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    if order.size == 0:
        return order.astype(np.int64)
    boxes = boxes[order]
    areas = _areas(boxes)
    alive = np.arange(order.size)  # sorted positions not yet visited or suppressed
    keep = []
    while alive.size:
        head = alive[:block]
        iou = _iou_rows(boxes[head], areas[head], boxes[alive], areas[alive])
        suppressed = np.zeros(alive.size, bool)
        for j in range(head.size):
            if not suppressed[j]:
                keep.append(head[j])
                suppressed |= iou[j] > iou_threshold
        alive = alive[head.size :][~suppressed[head.size :]]
    return order[np.asarray(keep, np.int64)]


def batched_nms(
    boxes: np.ndarray,
    scores: np.ndarray,
    classes: np.ndarray,
    iou_threshold: float,
    class_agnostic: bool = False,
) -> np.ndarray:
    """NMS within each class (or across all when ``class_agnostic``).

    Returns the kept indices by descending score; equal scores keep the lower
    index first, across classes too (the same order as the agnostic path).

    Args:
      boxes: (N, 4) xyxy; scores: (N,); classes: (N,) integer labels.
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if class_agnostic:
        return nms(boxes, scores, iou_threshold)
    classes = np.asarray(classes).reshape(-1)
    keep = [
        np.flatnonzero(classes == c)[nms(boxes[classes == c], scores[classes == c], iou_threshold)]
        for c in np.unique(classes)
    ]
    if not keep:
        return np.zeros((0,), np.int64)
    keep = np.sort(np.concatenate(keep))
    return keep[np.argsort(-scores[keep], kind="stable")]
