"""Anchor assignment vs a brute-force numpy reference, plus hand-checked threshold cases."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.detection.anchors import AnchorLayout, box_iou_np, generate_anchors
from gac_jax.detection.assignment import assign_anchors, box_iou, first_argmax

LAYOUT = AnchorLayout(image_size=(48, 96), base_size=16.0, scales=(1.0, 1.5, 2.0, 3.0))


def _brute_force(anchors, gt_boxes, gt_mask, gt_class, ground, prior_valid, pos=0.5, neg=0.4):
    batch, num_anchors = ground.shape
    labels = np.full((batch, num_anchors), -1)
    matched = np.full((batch, num_anchors), -1)
    iou_max = np.zeros((batch, num_anchors))
    for b in range(batch):
        real = [m for m in range(gt_boxes.shape[1]) if gt_mask[b, m] and gt_class[b, m] >= 0]
        if not real:
            continue
        for n in range(num_anchors):
            ious = [box_iou_np(anchors[n : n + 1], gt_boxes[b, m : m + 1])[0, 0] for m in real]
            best = max(ious)
            j = real[ious.index(best)]
            iou_max[b, n] = best
            if not ground[b, n]:
                continue
            if best >= pos:
                if prior_valid[gt_class[b, j], n]:
                    labels[b, n], matched[b, n] = 1, j
            elif best < neg:
                labels[b, n] = 0
    return labels, matched, iou_max


def _random_case(rng, batch=3, max_gt=8, num_classes=2):
    anchors = generate_anchors(LAYOUT)
    n = len(anchors)
    picks = rng.integers(0, n, (batch, max_gt))
    centers = anchors.centers[picks] + rng.normal(0, 4, (batch, max_gt, 2))
    shapes = anchors.shapes[picks] * rng.uniform(0.7, 1.4, (batch, max_gt, 2))
    gt_boxes = np.concatenate([centers - shapes / 2, centers + shapes / 2], axis=-1)
    gt_class = rng.integers(0, num_classes, (batch, max_gt))
    gt_mask = rng.uniform(size=(batch, max_gt)) > 0.25
    gt_mask[-1] = False  # the last image has no GT at all
    gt_class[0, 0], gt_mask[0, 0] = -1, True  # class -1 is padding even when the mask says True
    gt_boxes[~gt_mask] = rng.uniform(0, 90, ((~gt_mask).sum(), 4))  # garbage in padding rows
    ground = rng.uniform(size=(batch, n)) > 0.2
    prior_valid = rng.uniform(size=(num_classes, n)) > 0.2
    return anchors.boxes, gt_boxes, gt_mask, gt_class, ground, prior_valid


def test_box_iou_matches_numpy_with_batch_broadcasting():
    rng = np.random.default_rng(0)
    a = np.concatenate([rng.uniform(0, 50, (7, 2)), rng.uniform(55, 90, (7, 2))], axis=1)
    b = np.concatenate([rng.uniform(0, 50, (2, 4, 2)), rng.uniform(55, 90, (2, 4, 2))], axis=-1)
    got = np.asarray(box_iou(jnp.asarray(a)[None], jnp.asarray(b)))
    for i in range(2):
        np.testing.assert_allclose(got[i], box_iou_np(a, b[i]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_assignment_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    anchors, gt_boxes, gt_mask, gt_class, ground, prior_valid = _random_case(rng)
    result = jax.jit(assign_anchors)(
        anchors, gt_boxes, gt_mask, gt_class, ground_mask=ground, prior_valid=prior_valid
    )
    labels, matched, iou_max = _brute_force(
        anchors, gt_boxes, gt_mask, gt_class, ground, prior_valid
    )
    got = np.asarray(result.labels)
    near = (np.abs(iou_max - 0.5) < 1e-5) | (np.abs(iou_max - 0.4) < 1e-5)
    np.testing.assert_array_equal(got[~near], labels[~near])
    counts = [(labels == v).sum() for v in (1, 0, -1)]
    assert min(counts) > 10, counts  # every kind of label is exercised
    pos = labels == 1
    np.testing.assert_array_equal(np.asarray(result.matched_gt)[pos], matched[pos])
    expected_class = np.where(pos, np.take_along_axis(gt_class, np.maximum(matched, 0), 1), -1)
    np.testing.assert_array_equal(np.asarray(result.matched_class), expected_class)
    np.testing.assert_allclose(np.asarray(result.max_iou), iou_max, atol=1e-5)
    assert (got[-1] == -1).all()  # no GT: no positives and no negatives
    # Every positive of the reference lies on a ground-kept anchor with a valid prior bin.
    assert ground[pos].all()


def test_thresholds_are_inclusive_for_positives_and_exclusive_for_negatives():
    anchors = np.array([[0.0, 0, 10, 10]] * 4)
    gts = np.array([[0.0, 0, 10, 5], [0.0, 0, 10, 4], [0.0, 0, 10, 3.9], [0, 0, 10, 6]])
    for i, expected in enumerate([1, -1, 0, 1]):  # IoU 0.5, 0.4, 0.39, 0.6
        res = assign_anchors(anchors[:1], gts[None, i : i + 1], np.ones((1, 1), bool), [[0]])
        assert int(res.labels[0, 0]) == expected, (i, float(res.max_iou[0, 0]))


def test_ground_mask_and_invalid_bins_turn_positives_into_ignores():
    anchors = np.array([[0.0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10], [60, 0, 70, 10]])
    gts = np.array([[[0.0, 0, 10, 10], [20, 0, 30, 10], [40, 0, 50, 10], [100, 0, 110, 10]]])
    mask, cls = np.ones((1, 4), bool), np.array([[0, 1, 1, 0]])
    ground = np.array([[True, False, True, True]])
    prior_valid = np.array([[True, True, True, True], [True, True, False, True]])
    res = assign_anchors(anchors, gts, mask, cls, ground_mask=ground, prior_valid=prior_valid)
    # anchor 0 positive; 1 outside the ground mask; 2 matches class 1 whose bin is invalid;
    # 3 overlaps nothing: negative.
    np.testing.assert_array_equal(res.labels[0], [1, -1, -1, 0])
    np.testing.assert_array_equal(res.matched_class[0], [0, -1, -1, -1])


def test_low_quality_matching_forces_each_gts_best_anchor():
    anchors = np.array([[0.0, 0, 10, 10], [0, 0, 30, 30], [50, 50, 60, 60]])
    gts = np.array([[[0.0, 0, 20, 20], [52, 52, 70, 70], [0, 0, 1, 1]]])
    mask, cls = np.array([[True, True, False]]), np.array([[0, 0, 0]])
    off = assign_anchors(anchors, gts, mask, cls)
    on = assign_anchors(anchors, gts, mask, cls, match_low_quality=True)
    # IoUs: anchor 0 / gt 0 = 0.25, anchor 1 / gt 0 = 0.444, anchor 2 / gt 1 = 64 / 360.
    np.testing.assert_array_equal(off.labels[0], [0, -1, 0])
    np.testing.assert_array_equal(on.labels[0], [0, 1, 1])
    np.testing.assert_array_equal(on.matched_gt[0, 1:], [0, 1])
    # A ground-masked anchor is never forced; the next best ground-kept one is.
    ground = np.array([[True, False, True]])
    masked = assign_anchors(anchors, gts, mask, cls, ground_mask=ground, match_low_quality=True)
    np.testing.assert_array_equal(masked.labels[0], [1, -1, 1])


def test_first_argmax_equals_jnp_argmax_with_ties_and_padding():
    rng = np.random.default_rng(3)
    x = rng.integers(0, 4, (5, 200, 7)).astype(np.float32) / 4  # many ties, incl. whole rows
    x[:, :10] = -1.0  # rows of padding (all equal)
    x[0, 20, 3] = np.inf
    x = jnp.asarray(x)
    ours = jax.jit(lambda x: first_argmax(x, jnp.max(x, -1)))(x)
    np.testing.assert_array_equal(ours, jnp.argmax(x, -1))
    assert ours.dtype == jnp.int32
