"""KITTI depth metrics: hand-computed values and the real KITTI-depth frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gac_jax.data.files import read_depth_png
from gac_jax.evaluation.depth_metrics import (
    DEPTH_METRICS,
    DepthMetricAccumulator,
    depth_metrics,
    format_depth_table,
)

DEPTH_GT = (
    "depth/data_depth_annotated/train/2011_09_26_drive_0001_sync/proj_depth/groundtruth/"
    "image_02/0000000005.png"
)


def test_hand_computed_small_array():
    gt = np.array([[1.0, 2.0], [0.0, 4.0]])  # the 0 pixel is invalid and ignored
    pred = np.array([[2.0, 2.0], [-5.0, 2.5]])  # a negative value where gt is invalid is fine
    m = depth_metrics(pred, gt)
    # valid pairs (p, g): (2, 1), (2, 2), (2.5, 4)
    # e = p - g = 1, 0, -1.5;  d = ln p - ln g = ln 2, 0, ln(5/8)
    d = [math.log(2.0), 0.0, math.log(2.5 / 4.0)]
    mean_d = sum(d) / 3
    silog = 100 * math.sqrt(sum(x * x for x in d) / 3 - mean_d**2)
    assert m["silog"] == pytest.approx(silog, rel=1e-12)
    # sq_rel = mean((e/g)^2) = (1 + 0 + 0.140625)/3; abs_rel = mean(|e|/g) = (1 + 0 + .375)/3
    assert m["sq_rel"] == pytest.approx(100 * (1 + 0 + 0.140625) / 3, rel=1e-12)
    assert m["abs_rel"] == pytest.approx(100 * (1 + 0 + 0.375) / 3, rel=1e-12)
    # 1/g - 1/p = 0.5, 0, 0.25 - 0.4 = -0.15  (1/m) -> x1000 for 1/km
    assert m["irmse"] == pytest.approx(1000 * math.sqrt((0.25 + 0 + 0.0225) / 3), rel=1e-12)
    assert m["imae"] == pytest.approx(1000 * (0.5 + 0 + 0.15) / 3, rel=1e-12)
    # metres -> mm
    assert m["rmse"] == pytest.approx(1000 * math.sqrt((1 + 0 + 2.25) / 3), rel=1e-12)
    assert m["mae"] == pytest.approx(1000 * 2.5 / 3, rel=1e-12)
    # max(p/g, g/p) = 2, 1, 1.6: < 1.25 -> 1 of 3; < 1.5625 -> 1; < 1.953125 -> 2
    assert m["delta1"] == pytest.approx(100 / 3)
    assert m["delta2"] == pytest.approx(100 / 3)
    assert m["delta3"] == pytest.approx(200 / 3)
    assert list(m) == list(DEPTH_METRICS)


def test_images_are_averaged_not_pixels():
    gt1, pred1 = np.array([[1.0, 1.0, 1.0, 1.0]]), np.array([[2.0, 2.0, 2.0, 2.0]])  # abs_rel 100
    gt2, pred2 = np.array([[1.0, 0.0, 0.0, 0.0]]), np.array([[1.0, 1.0, 1.0, 1.0]])  # abs_rel 0
    acc = DepthMetricAccumulator()
    acc.update(pred1, gt1)
    acc.update(pred2, gt2)
    assert acc.count == 2
    assert acc.result()["abs_rel"] == pytest.approx(50.0)  # pixel-weighted would be 80
    assert acc.result()["delta1"] == pytest.approx(50.0)
    with pytest.raises(ValueError, match="no image"):
        DepthMetricAccumulator().result()


@pytest.mark.parametrize(
    "pred, message",
    [
        (np.array([[1.0, 0.0]]), "finite and > 0"),
        (np.array([[1.0, -2.0]]), "finite and > 0"),
        (np.array([[1.0, np.nan]]), "finite and > 0"),
        (np.array([[1.0, np.inf]]), "finite and > 0"),
        (np.ones((2, 2)), "shape"),
    ],
)
def test_invalid_predictions(pred, message):
    with pytest.raises(ValueError, match=message):
        depth_metrics(pred, np.array([[3.0, 4.0]]))


def test_no_valid_ground_truth():
    with pytest.raises(ValueError, match="no valid"):
        depth_metrics(np.ones((2, 2)), np.zeros((2, 2)))


def test_real_frame_self_and_scaled(kitti_samples):
    gt = read_depth_png(kitti_samples / DEPTH_GT).astype(np.float64)
    valid = gt > 0
    assert valid.sum() > 10_000
    same = depth_metrics(gt, gt)
    for k in ("silog", "sq_rel", "abs_rel", "irmse", "imae", "rmse", "mae"):
        assert same[k] == 0.0, k
    assert same["delta1"] == same["delta2"] == same["delta3"] == 100.0
    for s in (0.7, 1.1, 2.0):
        m = depth_metrics(gt * s, gt)
        assert m["silog"] == pytest.approx(0.0, abs=1e-6)  # scale invariant
        assert m["abs_rel"] == pytest.approx(100 * abs(s - 1), rel=1e-9)
        assert m["sq_rel"] == pytest.approx(100 * (s - 1) ** 2, rel=1e-9)
        g = gt[valid]
        assert m["mae"] == pytest.approx(1000 * abs(s - 1) * g.mean(), rel=1e-9)
        assert m["imae"] == pytest.approx(1000 * abs(1 - 1 / s) * np.mean(1 / g), rel=1e-9)
        assert m["delta1"] == (100.0 if max(s, 1 / s) < 1.25 else 0.0)
    table = format_depth_table(same, 1)
    assert "silog" in table and "(1 images)" in table
