"""NMS against an obviously-correct O(n^2) Python reference."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.detection.nms import batched_nms, box_iou_matrix, nms


def _iou(a, b) -> float:
    """IoU of two xyxy boxes in plain Python floats (continuous area convention)."""
    ix = min(a[2], b[2]) - max(a[0], b[0])
    iy = min(a[3], b[3]) - max(a[1], b[1])
    inter = max(ix, 0.0) * max(iy, 0.0)
    area_a = max(a[2] - a[0], 0.0) * max(a[3] - a[1], 0.0)
    area_b = max(b[2] - b[0], 0.0) * max(b[3] - b[1], 0.0)
    union = area_a + area_b - inter
    return inter / union if union > 0 else 0.0


def _reference_nms(boxes, scores, threshold, indices=None) -> list[int]:
    """Visit by (score desc, index asc); keep a box unless it overlaps a kept one > threshold."""
    indices = list(range(len(scores))) if indices is None else list(indices)
    order = sorted(indices, key=lambda i: (-float(scores[i]), i))
    keep: list[int] = []
    for i in order:
        if all(_iou(boxes[i].tolist(), boxes[k].tolist()) <= threshold for k in keep):
            keep.append(i)
    return keep


def _reference_batched(boxes, scores, classes, threshold) -> list[int]:
    keep = []
    for c in set(classes.tolist()):
        keep += _reference_nms(boxes, scores, threshold, np.flatnonzero(classes == c))
    return sorted(keep, key=lambda i: (-float(scores[i]), i))


def _random_case(rng: np.random.Generator, n: int):
    centres = rng.uniform(0, 100, (n, 2))
    # Few cluster centres so that many boxes overlap; a few exact duplicates.
    centres = np.where(rng.random((n, 1)) < 0.6, np.round(centres / 25) * 25, centres)
    size = rng.uniform(5, 40, (n, 2))
    boxes = np.concatenate([centres - size / 2, centres + size / 2], axis=1)
    dup = rng.random(n) < 0.15
    boxes[dup] = boxes[0]
    scores = rng.choice([0.1, 0.3, 0.5, 0.7, 0.9], n)  # many ties
    classes = rng.integers(0, 3, n)
    return boxes, scores, classes


@pytest.mark.parametrize("seed", range(12))
@pytest.mark.parametrize("threshold", [0.0, 0.3, 0.5, 0.7])
def test_nms_matches_reference(seed, threshold):
    rng = np.random.default_rng(seed)
    boxes, scores, classes = _random_case(rng, int(rng.integers(1, 60)))
    np.testing.assert_array_equal(
        nms(boxes, scores, threshold), _reference_nms(boxes, scores, threshold)
    )
    np.testing.assert_array_equal(
        batched_nms(boxes, scores, classes, threshold),
        _reference_batched(boxes, scores, classes, threshold),
    )
    np.testing.assert_array_equal(
        batched_nms(boxes, scores, classes, threshold, class_agnostic=True),
        _reference_nms(boxes, scores, threshold),
    )


def test_iou_matrix_matches_scalar_reference():
    rng = np.random.default_rng(0)
    a, _, _ = _random_case(rng, 7)
    b, _, _ = _random_case(rng, 5)
    expected = [[_iou(x.tolist(), y.tolist()) for y in b] for x in a]
    np.testing.assert_allclose(box_iou_matrix(a, b), expected, rtol=1e-12, atol=1e-15)


def test_empty_input():
    empty = np.zeros((0, 4))
    for out in (
        nms(empty, np.zeros(0), 0.5),
        batched_nms(empty, np.zeros(0), np.zeros(0, np.int64), 0.5),
        batched_nms(empty, np.zeros(0), np.zeros(0, np.int64), 0.5, class_agnostic=True),
    ):
        assert out.shape == (0,) and out.dtype == np.int64


def test_identical_boxes_keep_the_best_then_lowest_index():
    boxes = np.tile([10.0, 10.0, 50.0, 40.0], (4, 1))
    np.testing.assert_array_equal(nms(boxes, [0.2, 0.9, 0.4, 0.9], 0.5), [1])
    np.testing.assert_array_equal(nms(boxes, [0.5, 0.5, 0.5, 0.5], 0.99), [0])


def test_threshold_is_strict():
    # IoU exactly 0.5: kept at threshold 0.5 (suppression needs IoU > threshold).
    boxes = np.array([[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 5.0]])
    assert _iou(boxes[0].tolist(), boxes[1].tolist()) == 0.5
    np.testing.assert_array_equal(nms(boxes, [0.9, 0.8], 0.5), [0, 1])
    np.testing.assert_array_equal(nms(boxes, [0.9, 0.8], 0.49), [0])


def test_class_aware_versus_agnostic():
    boxes = np.array([[0.0, 0.0, 10.0, 10.0], [1.0, 0.0, 11.0, 10.0], [0.0, 1.0, 10.0, 11.0]])
    scores = np.array([0.6, 0.9, 0.7])
    classes = np.array([0, 1, 0])
    np.testing.assert_array_equal(batched_nms(boxes, scores, classes, 0.5), [1, 2])
    np.testing.assert_array_equal(
        batched_nms(boxes, scores, classes, 0.5, class_agnostic=True), [1]
    )


def test_batched_ties_across_classes_are_ordered_by_index():
    boxes = np.array([[0.0, 0.0, 10.0, 10.0], [20.0, 0.0, 30.0, 10.0], [40.0, 0.0, 50.0, 10.0]])
    np.testing.assert_array_equal(batched_nms(boxes, [0.5, 0.5, 0.5], [2, 0, 1], 0.5), [0, 1, 2])


def test_zero_area_boxes_never_suppress():
    boxes = np.array([[5.0, 5.0, 5.0, 9.0], [5.0, 5.0, 5.0, 9.0], [0.0, 0.0, 10.0, 10.0]])
    np.testing.assert_array_equal(nms(boxes, [0.9, 0.8, 0.7], 0.0), [0, 1, 2])


def test_accepts_lists():
    boxes = [[0.0, 0.0, 10.0, 10.0], [0.0, 0.0, 10.0, 9.0]]
    np.testing.assert_array_equal(batched_nms(boxes, [0.1, 0.2], [0, 0], 0.5), [1])
