"""Candidate selection before NMS keeps every anchor above the score threshold (as the
reference does), and the cap, when it bites, is counted rather than silent.

Paper geometry (288x1280, 46 080 anchors), a fake network whose logits put several hundred
filter-kept anchors of one image above the threshold, clustered so that NMS has work to do.
The reference is written out here in float64 numpy (sigmoid, best class, invalid-prior and
ground masks, threshold, 2D decode, clipping, greedy class-agnostic NMS) with no cap.
"""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.builders.detect3d import anchor_layout, filter_options
from gac_jax.config import load_config
from gac_jax.detection.anchor_filter import ground_filter_mask_np
from gac_jax.detection.anchor_priors import DetectionConstants
from gac_jax.detection.anchors import generate_anchors
from gac_jax.detection.box_coding import BOX_DELTA_STDS
from gac_jax.detection.inference import (
    PostprocessConfig,
    candidates_to_objects,
    make_predict_fn,
)

REPO = Path(__file__).resolve().parents[1]
# KITTI 000001 calibration after crop 100 + resize to 288 (close enough for the filter).
P2 = np.array([[754.4, 0.0, 644.6, 48.8], [0.0, 754.2, 85.9, -0.9], [0.0, 0.0, 1.0, 0.005]])
POST = PostprocessConfig(score_threshold=0.75, nms_iou=0.5, hill_climbing=False)


class FakeDetector:
    """``apply`` returns the outputs passed as ``variables``."""

    def apply(self, variables, images, P2, train, plane=None):
        return variables


@pytest.fixture(scope="module")
def scene():
    config = load_config(str(REPO / "configs" / "detect3d_kitti.py"))
    anchors = generate_anchors(anchor_layout(config))
    n = len(anchors.boxes)
    rng = np.random.default_rng(3)
    z, sin, cos = rng.uniform(5, 60, n), rng.uniform(-0.3, 0.3, n), rng.uniform(-0.3, 0.3, n)
    mean = np.stack([z, sin, cos], -1)[None]  # (1, N, 3)
    valid = rng.random((1, n)) < 0.9
    constants = DetectionConstants(
        anchor_boxes=jnp.asarray(anchors.boxes, jnp.float32),
        anchor_centers=jnp.asarray(anchors.centers, jnp.float32),
        prior_mean=jnp.asarray(mean, jnp.float32),
        prior_std=jnp.ones((1, n, 3), jnp.float32),
        prior_valid=jnp.asarray(valid),
        dims_mean=jnp.asarray([[1.5, 1.6, 3.9]], jnp.float32),
        dims_std=jnp.asarray([[0.15, 0.1, 0.4]], jnp.float32),
        angle_mode="double",
    )
    options = filter_options(config)
    kept = (
        ground_filter_mask_np(anchors.centers, mean[..., 0], valid, P2[None], **options)[0]
        & valid[0]
    )
    # Image 0: 600 high logits on filter-kept anchors around 12 "objects" (crowded frame);
    # image 1: 5. Distinct, well separated logits (float32 vs float64 order agrees).
    logits = rng.uniform(-8.0, 0.0, (2, n, 1)).astype(np.float32)  # below 0.75 (logit 1.10)
    centres = anchors.centers[kept][rng.choice(kept.sum(), 12, replace=False)]
    near = np.flatnonzero(kept)[
        np.argsort(np.min(np.linalg.norm(anchors.centers[kept][:, None] - centres, axis=2), 1))
    ][:600]
    logits[0, near, 0] = rng.permutation(np.linspace(1.3, 9.0, 600))
    logits[1, rng.choice(np.flatnonzero(kept), 5, replace=False), 0] = [2.0, 3.0, 4.0, 5.0, 6.0]
    outputs = {
        "cls_logits": logits,
        "sign_logits": rng.normal(size=(2, n)).astype(np.float32),
        "reg": (0.5 * rng.normal(size=(2, n, 12))).astype(np.float32),
    }
    return config, constants, options, outputs, np.asarray(anchors.boxes, np.float64)


def reference_detections(outputs, anchor_boxes, prior_mean_z, prior_valid, options, b):
    """Uncapped float64 numpy post-processing of image ``b``: (boxes (M, 4), scores (M,))."""
    probs = 1.0 / (1.0 + np.exp(-np.asarray(outputs["cls_logits"][b], np.float64)))
    scores = probs.max(1)  # one class
    keep = (
        ground_filter_mask_np(
            (anchor_boxes[:, :2] + anchor_boxes[:, 2:]) / 2,  # anchor centres
            prior_mean_z,
            prior_valid,
            P2[None],
            **options,
        )[0]
        & prior_valid[0]
    )
    sel = np.flatnonzero(keep & (scores > POST.score_threshold))
    a, d = anchor_boxes[sel], np.asarray(outputs["reg"][b], np.float64)[sel]
    pw, ph = a[:, 2] - a[:, 0], a[:, 3] - a[:, 1]
    cx = a[:, 0] + pw / 2 + d[:, 0] * BOX_DELTA_STDS[0] * pw
    cy = a[:, 1] + ph / 2 + d[:, 1] * BOX_DELTA_STDS[1] * ph
    w, h = pw * np.exp(d[:, 2] * BOX_DELTA_STDS[2]), ph * np.exp(d[:, 3] * BOX_DELTA_STDS[3])
    boxes = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], 1)
    boxes = np.clip(boxes, 0.0, [1280, 288, 1280, 288])
    order = np.argsort(-scores[sel])
    kept: list[int] = []
    for i in order:  # greedy NMS, suppress IoU > 0.5 with a kept box
        x1, y1 = np.maximum(boxes[kept, 0], boxes[i, 0]), np.maximum(boxes[kept, 1], boxes[i, 1])
        x2, y2 = np.minimum(boxes[kept, 2], boxes[i, 2]), np.minimum(boxes[kept, 3], boxes[i, 3])
        inter = np.clip(x2 - x1, 0, None) * np.clip(y2 - y1, 0, None)
        area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
        if not np.any(inter / (area[kept] + area[i] - inter) > POST.nms_iou):
            kept.append(int(i))
    boxes = np.clip(boxes[kept], 0.0, [1279, 287, 1279, 287])  # to original-image pixels
    return boxes, scores[sel][kept], len(sel)


def objects_of(predict, outputs, b):
    cand = predict(outputs, np.zeros((2, 8, 8, 3), np.float32), np.stack([P2, P2]))
    cand = {k: np.asarray(v)[b] for k, v in cand.items()}
    obj = candidates_to_objects(cand, P2, np.eye(3), (288, 1280), (288, 1280), ("Car",), POST)
    return obj, cand


def test_every_anchor_above_threshold_reaches_nms(scene):
    config, constants, options, outputs, anchor_boxes = scene
    mean_z = np.asarray(constants.prior_mean, np.float64)[..., 0]
    valid = np.asarray(constants.prior_valid)
    predicts = {
        top_k: make_predict_fn(
            FakeDetector(),
            constants,
            top_k=top_k,
            score_threshold=POST.score_threshold,
            filter_options=options,
        )
        for top_k in (config.eval.top_k, None, 100)
    }
    for b in (0, 1):
        boxes, scores, count = reference_detections(
            outputs, anchor_boxes, mean_z, valid, options, b
        )
        assert count == (600 if b == 0 else 5)
        for top_k in (config.eval.top_k, None):
            obj, cand = objects_of(predicts[top_k], outputs, b)
            assert int(cand["num_candidates"]) == count
            assert np.sum(cand["scores"] > POST.score_threshold) == count  # all reach NMS
            assert len(obj) == len(scores) and len(scores) > (100 if b == 0 else 0)
            assert len(scores) < count or b == 1  # NMS suppressed some
            np.testing.assert_allclose(obj.score, scores, rtol=1e-6)
            np.testing.assert_allclose(obj.bbox, boxes, atol=2e-3)
    # The former cap of 100: the count says it bit, and detections are lost or changed.
    obj, cand = objects_of(predicts[100], outputs, 0)
    assert cand["scores"].shape == (100,) and int(cand["num_candidates"]) == 600
    boxes, scores, _ = reference_detections(outputs, anchor_boxes, mean_z, valid, options, 0)
    assert len(obj) < len(scores)
    print(f"600 candidates -> {len(scores)} detections uncapped, {len(obj)} with top_k 100")


def test_top_k_none_keeps_every_anchor_and_bad_values_fail(scene):
    _, constants, options, outputs, _ = scene
    predict = make_predict_fn(FakeDetector(), constants, top_k=None, use_ground_filter=False)
    cand = predict(outputs, np.zeros((2, 8, 8, 3), np.float32), np.stack([P2, P2]))
    n = constants.anchor_boxes.shape[0]
    assert cand["scores"].shape == (2, n)
    # Without a threshold the count is every valid-prior anchor.
    np.testing.assert_array_equal(cand["num_candidates"], np.asarray(constants.prior_valid).sum())
    with pytest.raises(ValueError, match="top_k"):
        make_predict_fn(FakeDetector(), constants, top_k=0)
