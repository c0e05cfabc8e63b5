"""Per-anchor priors: statistics vs a float64 loop reference, the depth/size effect, file I/O."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gac_jax.data.kitti import KittiObjects
from gac_jax.detection.anchor_priors import (
    INVALID_MEAN,
    INVALID_STD,
    AnchorPriors,
    PriorsMismatchError,
    compute_anchor_priors,
    load_or_compute_priors,
    load_priors,
    make_detection_constants,
    prior_frame_from_objects,
    save_priors,
)
from gac_jax.detection.anchors import AnchorLayout, generate_anchors

SMALL = AnchorLayout(image_size=(48, 96), base_size=16.0, scales=(1.0, 1.5, 2.0, 3.0))


def _random_frames(layout, num_frames, rng, constant_z_class=None):
    """Frames whose boxes are jittered anchors (so many anchors match), two classes."""
    anchors = generate_anchors(layout)
    frames = []
    for _ in range(num_frames):
        m = int(rng.integers(0, 5))
        picks = rng.integers(0, len(anchors), m)
        centers = anchors.centers[picks] + rng.normal(0, 3, (m, 2))
        shapes = anchors.shapes[picks] * rng.uniform(0.8, 1.25, (m, 2))
        boxes = np.concatenate([centers - shapes / 2, centers + shapes / 2], axis=1)
        classes = rng.integers(0, 2, m)
        z = rng.uniform(5, 50, m)
        if constant_z_class is not None:
            z[classes == constant_z_class] = 20.0
        frames.append(
            {
                "boxes": boxes,
                "classes": classes,
                "z": z,
                "alpha": rng.uniform(-np.pi, np.pi, m),
                "dims": rng.uniform([1.3, 1.5, 3.0], [1.8, 2.0, 5.0], (m, 3)),
            }
        )
    # Padding entries (class -1) must be ignored.
    frames[0] = {k: np.concatenate([v, v[:1] * 0 - 1]) for k, v in frames[0].items()}
    return frames


def _iou(a, b):
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / max(union, 1e-8)


def _loop_reference(frames, layout, num_classes, min_count, thr=0.5):
    anchors = generate_anchors(layout)
    samples = {}
    dims = {k: [] for k in range(num_classes)}
    for f in frames:
        for k in range(num_classes):
            idx = [i for i in range(len(f["classes"])) if f["classes"][i] == k]
            dims[k] += [f["dims"][i] for i in idx]
            if not idx:
                continue
            for n in range(len(anchors)):
                ious = [_iou(anchors.boxes[n], f["boxes"][i]) for i in idx]
                best = max(ious)
                if best > thr:
                    i = idx[ious.index(best)]
                    a = f["alpha"][i]
                    value = (f["z"][i], math.sin(2 * a), math.cos(2 * a))
                    samples.setdefault((k, int(anchors.bin_index[n])), []).append(value)
    num_bins = layout.anchors_per_cell
    count = np.zeros((num_classes, num_bins), int)
    mean = np.full((num_classes, num_bins, 3), np.nan)
    std = np.full((num_classes, num_bins, 3), np.nan)
    for (k, b), vals in samples.items():
        v = np.array(vals)
        count[k, b] = len(v)
        mean[k, b] = v.mean(0)
        std[k, b] = v.std(0)
    valid = (count >= min_count) & np.all(np.nan_to_num(std) >= 1e-3, axis=-1)
    dims_mean = np.array([np.mean(dims[k], 0) for k in range(num_classes)])
    dims_std = np.array([np.std(dims[k], 0) for k in range(num_classes)])
    return count, mean, std, valid, dims_mean, dims_std


def test_statistics_match_a_float64_loop_reference():
    rng = np.random.default_rng(1)
    frames = _random_frames(SMALL, 40, rng, constant_z_class=1)
    priors = compute_anchor_priors(frames, SMALL, ("Car", "Pedestrian"), min_count=10)
    count, mean, std, valid, dims_mean, dims_std = _loop_reference(frames, SMALL, 2, 10)
    assert count.sum() > 100 and valid[0].sum() >= 4  # the test exercises real statistics
    np.testing.assert_array_equal(priors.count, count)
    np.testing.assert_allclose(priors.mean, mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(priors.std, std, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(priors.valid, valid)
    np.testing.assert_allclose(priors.dims_mean, dims_mean, rtol=1e-12)
    np.testing.assert_allclose(priors.dims_std, dims_std, rtol=1e-8)
    # Class 1 has a constant depth: zero spread makes every one of its bins invalid.
    assert priors.count[1].max() >= 10 and not priors.valid[1].any()
    # Bins with fewer than min_count samples are invalid even with spread.
    few = (priors.count[0] > 1) & (priors.count[0] < 10)
    assert few.sum() >= 2 and not priors.valid[0][few].any()
    eff_mean, eff_std = priors.effective_mean(), priors.effective_std()
    assert np.all(eff_mean[~priors.valid] == INVALID_MEAN)
    assert np.all(eff_std[~priors.valid] == INVALID_STD)
    np.testing.assert_array_equal(eff_mean[priors.valid], priors.mean[priors.valid])


def test_single_angle_mode_uses_alpha_itself():
    rng = np.random.default_rng(2)
    frames = _random_frames(SMALL, 10, rng)
    frames_2x = [dict(f, alpha=2 * f["alpha"]) for f in frames]
    single = compute_anchor_priors(frames_2x, SMALL, ("A", "B"), angle_mode="single", min_count=1)
    double = compute_anchor_priors(frames, SMALL, ("A", "B"), angle_mode="double", min_count=1)
    np.testing.assert_allclose(single.mean, double.mean, atol=1e-12)
    with pytest.raises(ValueError, match="angle_mode"):
        compute_anchor_priors(frames, SMALL, ("A", "B"), angle_mode="half")


def test_larger_anchors_get_lower_depth_spread():
    """The paper's observation: z ~ f H / box height, so depth spread falls with anchor size."""
    rng = np.random.default_rng(3)
    layout = AnchorLayout(image_size=(160, 640))
    focal = 700.0
    frames = []
    for _ in range(150):
        m = 8
        h = np.exp(rng.uniform(np.log(18), np.log(150), m))
        w = h * rng.uniform(1.3, 2.6, m)
        u, v = rng.uniform(0, 640, m), rng.uniform(40, 140, m)
        height_3d = rng.uniform(1.4, 1.7, m)
        z = focal * height_3d / h * (1 + rng.normal(0, 0.03, m))
        frames.append(
            {
                "boxes": np.stack([u - w / 2, v - h / 2, u + w / 2, v + h / 2], -1),
                "classes": np.zeros(m, int),
                "z": z,
                "alpha": rng.uniform(-np.pi, np.pi, m),
                "dims": np.stack([height_3d, rng.uniform(1.5, 1.9, m), rng.uniform(3, 5, m)], -1),
            }
        )
    priors = compute_anchor_priors(frames, layout, ("Car",))
    wide = priors.valid[0, :16]  # ratio 0.5 (wide) bins, scale index 0..15
    scales = np.flatnonzero(wide)
    assert len(scales) >= 6, priors.count[0, :16]
    std_z = priors.std[0, scales, 0]
    mean_z = priors.mean[0, scales, 0]
    assert np.corrcoef(scales, np.log(std_z))[0, 1] < -0.9
    assert std_z[-1] < 0.35 * std_z[0]
    assert np.all(np.diff(mean_z) < 0)  # bigger boxes are closer


def test_save_load_round_trip_and_layout_refusal(tmp_path):
    rng = np.random.default_rng(4)
    priors = compute_anchor_priors(_random_frames(SMALL, 10, rng), SMALL, ("Car", "Cyclist"))
    path = tmp_path / "priors.npz"
    save_priors(path, priors)
    loaded = load_priors(path, SMALL, ("Car", "Cyclist"), "double")
    assert loaded.layout == SMALL and loaded.class_names == ("Car", "Cyclist")
    for name in ("count", "mean", "std", "valid", "dims_mean", "dims_std", "num_objects"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(priors, name))
    assert loaded.num_frames == 10 and loaded.min_count == 10
    other = AnchorLayout(image_size=(48, 96), base_size=16.0, scales=(1.0, 1.5, 2.0, 3.0), stride=8)
    with pytest.raises(PriorsMismatchError, match=r"priors\.npz.*stride"):
        load_priors(path, other)
    with pytest.raises(PriorsMismatchError, match="classes"):
        load_priors(path, SMALL, ("Car",))
    with pytest.raises(PriorsMismatchError, match="angle_mode"):
        load_priors(path, SMALL, angle_mode="single")
    with pytest.raises(PriorsMismatchError, match="image_size"):
        make_detection_constants(generate_anchors(AnchorLayout((64, 96), 16, 16.0)), priors)
    (tmp_path / "junk.npz").write_bytes(b"not an npz")
    with pytest.raises(ValueError, match="junk.npz"):
        load_priors(tmp_path / "junk.npz")


def test_load_or_compute_caches_and_refuses_other_layouts(tmp_path):
    rng = np.random.default_rng(5)
    frames = _random_frames(SMALL, 8, rng)
    calls = []

    def source():
        calls.append(1)
        return iter(frames)

    path = tmp_path / "cache" / "priors.npz"
    first = load_or_compute_priors(path, source, SMALL, ("Car", "Cyclist"), min_count=2)
    second = load_or_compute_priors(path, source, SMALL, ("Car", "Cyclist"), min_count=2)
    assert len(calls) == 1 and path.exists()
    np.testing.assert_array_equal(first.mean, second.mean)
    with pytest.raises(PriorsMismatchError, match="ratios"):
        load_or_compute_priors(path, source, AnchorLayout((48, 96), 16, 16.0, (1.0,)), ("Car",))


def test_bad_frames_are_reported():
    layout, ok = SMALL, {"boxes": np.zeros((1, 4)), "z": [1.0], "alpha": [0.0], "dims": [[1, 1, 1]]}
    with pytest.raises(ValueError, match="frame 0: missing key 'classes'"):
        compute_anchor_priors([ok], layout, ("Car",))
    with pytest.raises(ValueError, match="frame 0: class index 3"):
        compute_anchor_priors([dict(ok, classes=[3])], layout, ("Car",))
    with pytest.raises(ValueError, match="inconsistent"):
        compute_anchor_priors([dict(ok, classes=[0, 0])], layout, ("Car",))
    with pytest.raises(ValueError, match=r"class\(es\) \['Van'\]"):
        compute_anchor_priors([dict(ok, classes=[0])], layout, ("Car", "Van"))


def test_detection_constants_gather_bins_to_anchors():
    rng = np.random.default_rng(6)
    priors = compute_anchor_priors(_random_frames(SMALL, 30, rng), SMALL, ("A", "B"), min_count=2)
    anchors = generate_anchors(SMALL)
    const = make_detection_constants(anchors, priors)
    n = len(anchors)
    assert const.prior_mean.shape == (2, n, 3) and const.prior_valid.shape == (2, n)
    assert const.anchor_boxes.dtype == np.float32 and const.angle_mode == "double"
    for i in (0, 7, 77, n - 1):
        b = anchors.bin_index[i]
        np.testing.assert_allclose(const.prior_mean[:, i], priors.effective_mean()[:, b], rtol=1e-6)
        np.testing.assert_array_equal(const.prior_valid[:, i], priors.valid[:, b])
    assert isinstance(priors, AnchorPriors) and priors.num_classes == 2


def test_prior_frame_from_kitti_objects_maps_boxes_and_drops_other_classes():
    objects = KittiObjects.from_arrays(
        type=["Car", "DontCare", "Pedestrian"],
        bbox=[[100, 150, 300, 250], [0, 0, 10, 10], [500, 120, 540, 220]],
        dimensions=[[1.5, 1.6, 4.0], [0, 0, 0], [1.7, 0.6, 0.8]],
        location=[[1, 1.6, 20], [0, 0, 0], [-3, 1.6, 12]],
        alpha=[0.3, -10, -1.0],
    )
    s = 288 / 275
    A = np.diag([s, s, 1.0]) @ np.array([[1, 0, 0], [0, 1, -100], [0, 0, 1.0]])
    frame = prior_frame_from_objects(objects, ("Car", "Pedestrian"), A)
    np.testing.assert_allclose(frame["boxes"][0], [100 * s, 50 * s, 300 * s, 150 * s])
    np.testing.assert_array_equal(frame["classes"], [0, 1])
    np.testing.assert_allclose(frame["z"], [20, 12])
    np.testing.assert_allclose(frame["alpha"], [0.3, -1.0])
    flip = np.array([[-1, 0, 1279], [0, 1, 0], [0, 0, 1.0]])
    flipped = prior_frame_from_objects(objects, ("Car",), flip)
    np.testing.assert_allclose(flipped["boxes"][0], [1279 - 300, 150, 1279 - 100, 250])
