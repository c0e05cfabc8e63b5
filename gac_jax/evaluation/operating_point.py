"""The operating point of a detector: the score threshold it should be deployed at.

AP needs every low-scoring box (``eval.score_threshold`` keeps them); a camera needs one
threshold that trades false boxes against missed objects. The operating point is the score
threshold of best F-beta on a labelled split (``eval.operating_point_beta``: 1 is F1, the
harmonic mean of precision and recall; 0.5 weighs precision twice as much as recall, for a
camera whose false boxes cost more than its misses):

* a **true** detection overlaps a labelled object of its class at 2D IoU >= 0.5 (each object
  taken once, the highest-scoring detection first);
* a detection is **excused** (neither true nor false) where KITTI's benchmark excuses it: it
  overlaps an object of the neighbouring class (Car: Van, Pedestrian: Person_sitting) at IoU
  >= 0.5, or lies at least half inside a DontCare region;
* every other detection is **false**;
* precision = (detections - false) / detections, recall = objects at least 25 px tall (KITTI's
  moderate height) found / objects at least 25 px tall, over all frames and classes pooled;
* F-beta = (1 + beta^2) precision recall / (beta^2 precision + recall).

Pure numpy on :class:`~gac_jax.data.kitti.KittiObjects` (boxes xyxy in pixels).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gac_jax.config import ConfigError
from gac_jax.data.kitti import KittiObjects
from gac_jax.detection.nms import box_iou_matrix

MIN_HEIGHT_PX = 25.0  # KITTI's moderate height limit: objects a detector should find
MATCH_IOU = 0.5
NEIGHBOURS = {"Car": ("Van",), "Pedestrian": ("Person_sitting",)}
GRID_STEP = 0.05
GRID_TOP = 0.95


def score_name(beta: float) -> str:
    """``'F1'``, ``'F0.5'``: the F-beta score's name."""
    return f"F{beta:g}"


def rule(beta: float = 1.0) -> str:
    """The operating point's rule in words (recorded with it)."""
    return (
        f"best {score_name(beta)} (pooled over classes; 2D IoU >= 0.5; objects >= 25 px tall; "
        "KITTI's Van / Person_sitting / DontCare excuses) on a grid from the evaluation's score "
        "threshold to 0.95 in steps of 0.05, the lowest threshold on a tie"
    )


def check_beta(beta) -> float:
    """``beta`` as a float; a ConfigError naming ``eval.operating_point_beta`` unless > 0."""
    try:
        value = float(beta)
    except (TypeError, ValueError):
        value = float("nan")
    if not value > 0 or value == float("inf"):
        raise ConfigError(f"eval.operating_point_beta must be a number > 0, got {beta!r}")
    return value


def f_beta(precision: float, recall: float, beta: float = 1.0) -> float:
    """(1 + beta^2) P R / (beta^2 P + R); 0 where both are 0."""
    b2 = beta * beta
    denominator = b2 * precision + recall
    return (1 + b2) * precision * recall / denominator if denominator else 0.0


def inside_share(box: np.ndarray, regions: np.ndarray) -> np.ndarray:
    """(R,) share of ``box``'s area (xyxy, KITTI's +1 pixel convention) inside each region."""
    iw = np.minimum(box[2], regions[:, 2]) - np.maximum(box[0], regions[:, 0]) + 1
    ih = np.minimum(box[3], regions[:, 3]) - np.maximum(box[1], regions[:, 1]) + 1
    area = (box[2] - box[0] + 1) * (box[3] - box[1] + 1)
    return np.clip(iw, 0, None) * np.clip(ih, 0, None) / max(area, 1e-9)


def tall_objects(gt: KittiObjects, class_name: str = "Car") -> int:
    """Labelled objects of ``class_name`` in one frame at least ``MIN_HEIGHT_PX`` tall."""
    boxes = gt.bbox[gt.type == class_name]
    return int(np.sum((boxes[:, 3] - boxes[:, 1]) >= MIN_HEIGHT_PX))


def frame_counts(
    gt: KittiObjects, dt: KittiObjects, threshold: float, class_name: str = "Car"
) -> tuple[int, int, int, int]:
    """``(detections, false, found at IoU 0.5, found at IoU 0.7)`` of one frame and class.

    Args:
      gt: the frame's labels; dt: its detections (with scores).
      threshold: detections below this score are left out.
      class_name: the class counted; ``found`` counts its labelled objects at least
        ``MIN_HEIGHT_PX`` tall that some kept detection overlaps at that IoU.
    """
    keep = (dt.type == class_name) & (dt.score >= threshold)
    boxes = dt.bbox[keep][np.argsort(-dt.score[keep], kind="stable")]
    objects = gt.bbox[gt.type == class_name]
    near = gt.bbox[np.isin(gt.type, NEIGHBOURS.get(class_name, ()))]
    dontcare = gt.bbox[gt.type == "DontCare"]
    taken = np.zeros(len(objects), bool)
    false = 0
    iou = box_iou_matrix(boxes, objects) if len(objects) else np.zeros((len(boxes), 0))
    for i, box in enumerate(boxes):
        free = np.flatnonzero(~taken & (iou[i] >= MATCH_IOU))
        if len(free):
            taken[free[np.argmax(iou[i, free])]] = True
            continue
        if len(near) and box_iou_matrix(box[None], near).max() >= MATCH_IOU:
            continue
        if len(dontcare) and inside_share(box, dontcare).max() >= 0.5:
            continue
        false += 1
    tall = (objects[:, 3] - objects[:, 1]) >= MIN_HEIGHT_PX if len(objects) else taken
    best = iou.max(axis=0) if len(boxes) and len(objects) else np.zeros(len(objects))
    return len(boxes), false, int(np.sum(tall & (best >= 0.5))), int(np.sum(tall & (best >= 0.7)))


def threshold_sweep(
    gts: Sequence[KittiObjects],
    dts: Sequence[KittiObjects],
    thresholds: Sequence[float],
    classes: Sequence[str] = ("Car",),
) -> dict[float, dict]:
    """Detections, false positives, precision, recall and F1 per score threshold.

    Args:
      gts, dts: labels and detections per frame, same order.
      thresholds: score thresholds.
      classes: the classes counted, pooled.

    Returns:
      ``{threshold: {...}}``: per frame ``detections`` and ``false_positives``
      (:func:`frame_counts`), ``found`` (labelled objects at least 25 px tall found at IoU
      0.5), ``precision`` (share of the detections that are not false), ``recall`` (``found``
      over the labelled objects at least 25 px tall) and their harmonic mean ``f1``.
    """
    n = max(len(gts), 1)
    tall = sum(tall_objects(g, c) for g in gts for c in classes)
    out = {}
    for t in thresholds:
        tot = np.zeros(4, np.int64)
        for gt, dt in zip(gts, dts, strict=True):
            if len(dt):
                for c in classes:
                    tot += frame_counts(gt, dt, t, c)
        precision = (tot[0] - tot[1]) / tot[0] if tot[0] else 0.0
        recall = tot[2] / tall if tall else 0.0
        f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
        out[float(t)] = {
            "detections": tot[0] / n,
            "false_positives": tot[1] / n,
            "found": int(tot[2]),
            "precision": float(precision),
            "recall": float(recall),
            "f1": float(f1),
        }
    return out


def best_threshold(sweep: dict[float, dict], beta: float = 1.0) -> float:
    """The threshold of best F-beta in :func:`threshold_sweep`'s output (its ``precision``
    and ``recall``; the lowest threshold on a tie). Keys may be floats or strings."""

    def key(t):
        score = f_beta(sweep[t]["precision"], sweep[t]["recall"], beta)
        return (round(score, 12), -float(t))

    return max(sorted(sweep, key=float), key=key)


def chosen_threshold(sweep: dict, beta: float = 1.0) -> float | None:
    """:func:`best_threshold` as a float, or None where no threshold finds any object (F-beta
    0 everywhere: nothing to choose from)."""
    best = best_threshold(sweep, beta)
    return float(best) if sweep[best]["recall"] > 0 else None


def threshold_grid(min_score: float) -> list[float]:
    """``min_score`` (the evaluation's threshold: nothing below it was kept), then the
    multiples of 0.05 above it up to 0.95."""
    k = int(np.floor(min_score / GRID_STEP + 1e-9)) + 1
    grid = [round(GRID_STEP * i, 2) for i in range(k, int(round(GRID_TOP / GRID_STEP)) + 1)]
    return [float(min_score), *[t for t in grid if t > min_score + 1e-9]]


def operating_point(
    gts: Sequence[KittiObjects],
    dts: Sequence[KittiObjects],
    classes: Sequence[str],
    min_score: float,
    beta: float = 1.0,
) -> dict:
    """The operating point of detections kept at ``min_score`` (module docstring).

    Returns:
      ``{'threshold', 'beta', 'rule', 'classes', 'frames', 'objects', 'sweep'}``:
      ``threshold`` is None where no threshold finds any object (F-beta 0 everywhere: nothing
      to choose from); ``objects`` counts the labelled objects at least 25 px tall; ``sweep``
      is :func:`threshold_sweep` on :func:`threshold_grid` (keys as strings, for JSON).
    """
    beta = check_beta(beta)
    sweep = threshold_sweep(gts, dts, threshold_grid(min_score), classes)
    return {
        "threshold": chosen_threshold(sweep, beta),
        "beta": beta,
        "rule": rule(beta),
        "classes": list(classes),
        "frames": len(gts),
        "objects": int(sum(tall_objects(g, c) for g in gts for c in classes)),
        "sweep": {f"{t:.2f}": v for t, v in sweep.items()},
    }


def describe(record: dict) -> str:
    """One line for a person: the threshold and its figures, or why there is none."""
    t = record.get("threshold")
    if t is None:
        return (
            f"no operating point: no score threshold finds any of the {record['objects']} "
            f"objects at least 25 px tall in {record['frames']} frames"
        )
    s = record["sweep"][f"{t:.2f}"]
    beta = float(record.get("beta", 1.0))  # records made before the key: F1
    score = f_beta(s["precision"], s["recall"], beta)
    return (
        f"operating point: score >= {t:.2f} (best {score_name(beta)} {score:.2f}: precision "
        f"{s['precision']:.2f}, recall {s['recall']:.2f} of {record['objects']} objects "
        f">= 25 px tall, {s['false_positives']:.2f} false boxes per frame over "
        f"{record['frames']} frames)"
    )
