"""Ground-plane anchor filtering: hand-checked cases, jnp/numpy agreement, real KITTI frames."""

from __future__ import annotations

import functools

import jax
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data.files import read_image
from gac_jax.data.kitti import KittiObjectLayout, read_calib, read_label
from gac_jax.detection.anchor_filter import (
    ground_filter_mask,
    ground_filter_mask_np,
    ground_mask_from_constants,
)
from gac_jax.detection.anchor_priors import AnchorPriors, make_detection_constants
from gac_jax.detection.anchors import AnchorLayout, box_iou_np, generate_anchors

P_SIMPLE = np.array([[700.0, 0, 600, 0], [0, 700, 180, 0], [0, 0, 1, 0]])


def test_hand_checked_reference_and_paper_cases():
    centers = np.array(
        [
            [600.0, 180 + 700 * 1.0 / 20],  # y3d = 1.0 m: kept
            [600.0, 180 - 700 * 0.6 / 20],  # y3d = -0.6 m (above the band): dropped
            [600.0, 180 + 700 * 1.9 / 20],  # y3d = 1.9 m (below the road): dropped
            [600 + 700 * 41 / 20, 180 + 700 * 1.0 / 20],  # x3d = 41 m: dropped
            [600 - 700 * 39 / 20, 180 + 700 * 1.0 / 20],  # x3d = -39 m: kept
        ]
    )
    mean_z = np.full((1, 5), 20.0)
    valid = np.ones((1, 5), bool)
    expected = [True, False, False, False, True]
    for mode in ("reference", "paper"):
        keep = ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE, mode=mode)
        np.testing.assert_array_equal(keep, expected)
        np.testing.assert_array_equal(
            np.asarray(ground_filter_mask(centers, mean_z, valid, P_SIMPLE, mode=mode)), expected
        )
    # No lateral limit: the far-right anchor is back.
    keep = ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE, x_limit=None)
    np.testing.assert_array_equal(keep, [True, False, False, True, True])
    # Paper mode: a camera mounted 1 m higher moves the band 1 m down (y3d in (0.5, 2.8)).
    keep = ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE, mode="paper", camera_height=2.65)
    np.testing.assert_array_equal(keep, [True, False, True, False, True])


def pitched_plane(degrees: float, height: float = 1.65) -> np.ndarray:
    p = np.radians(degrees)
    return np.array([0.0, -np.cos(p), -np.sin(p), height])


@pytest.mark.parametrize("camera", [1.65, 2.4])
def test_both_modes_follow_a_tilted_plane(camera):
    """Centres 1.0 / 2.5 / -0.5 m above a road pitched 20 degrees (20 m ahead), the camera
    ``camera`` above it: paper mode keeps the height in (-0.15, 2.15), reference mode the depth
    below a camera 1.65 m above the road (1.65 - height) in (-0.5, 1.8); a level y band would
    keep none of them."""
    plane = pitched_plane(20.0, camera)
    n = plane[:3]
    on_road = np.array([0.0, -(n[2] * 20.0 + plane[3]) / n[1], 20.0])
    centres = np.stack([on_road + h * n for h in (1.0, 2.5, -0.5)])
    assert np.allclose(geometry.height_above_plane(centres, plane), [1.0, 2.5, -0.5])
    uv, _ = geometry.project(centres, P_SIMPLE)
    mean_z, valid = centres[None, :, 2], np.ones((1, 3), bool)
    for mode in ("reference", "paper"):
        for fn in (ground_filter_mask_np, ground_filter_mask):
            keep = np.asarray(fn(uv, mean_z, valid, P_SIMPLE, plane, mode=mode))
            np.testing.assert_array_equal(keep, [True, False, False], err_msg=mode)
        level = ground_filter_mask_np(uv, mean_z, valid, P_SIMPLE, mode=mode)
        np.testing.assert_array_equal(level, [False, False, False])  # y = -6.5, -7.9, -5.1 m


def test_any_class_keeps_an_anchor_and_invalid_bins_keep_none():
    # Anchor 1 is 210 px below cy: y3d = 6 m at class 0's depth 20 m, 1.5 m at class 1's 5 m.
    centers = np.array([[600.0, 180 + 700 * 1.0 / 20], [600.0, 180 + 210]])
    mean_z = np.array([[20.0, 20.0], [5.0, 5.0]])
    valid = np.ones((2, 2), bool)
    np.testing.assert_array_equal(ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE), [1, 1])
    np.testing.assert_array_equal(
        ground_filter_mask_np(centers, mean_z[:1], valid[:1], P_SIMPLE), [1, 0]
    )
    valid[1, 1] = False
    np.testing.assert_array_equal(ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE), [1, 0])


def test_reference_quirk_for_invalid_bins_keeps_anchors_just_above_the_horizon():
    # Sentinel depth -100: y3d = -100 (v - cy) / fy is in the band for v slightly above cy.
    centers = np.array([[600.0, 180 - 0.01 * 700], [600.0, 180 + 0.01 * 700]])
    mean_z = np.full((1, 2), 30.0)
    valid = np.zeros((1, 2), bool)
    keep_ref = ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE, invalid_bins="reference")
    np.testing.assert_array_equal(keep_ref, [True, False])
    assert not ground_filter_mask_np(centers, mean_z, valid, P_SIMPLE).any()


def test_x_focal_flag_selects_the_divisor():
    P = P_SIMPLE.copy()
    P[0, 0] = 1400.0  # fx = 2 fy
    centers = np.array([[600 + 700 * 50 / 20, 180 + 700 / 20]])  # x = 50 m with fy, 25 m with fx
    z, ok = np.full((1, 1), 20.0), np.ones((1, 1), bool)
    assert not ground_filter_mask_np(centers, z, ok, P, x_focal="fy")[0]
    assert ground_filter_mask_np(centers, z, ok, P, x_focal="fx")[0]
    with pytest.raises(ValueError, match="x_focal"):
        ground_filter_mask_np(centers, z, ok, P, x_focal="f")
    with pytest.raises(ValueError, match="mode"):
        ground_filter_mask(centers, z, ok, P, mode="tilted")


@pytest.mark.parametrize("mode", ["reference", "paper"])
def test_jitted_jnp_matches_numpy_on_a_batch(mode):
    rng = np.random.default_rng(0)
    layout = AnchorLayout(image_size=(96, 320))
    anchors = generate_anchors(layout)
    n = len(anchors)
    mean_z = rng.uniform(3, 60, (2, n))
    valid = rng.uniform(size=(2, n)) > 0.2
    P2 = np.stack([P_SIMPLE * [[s], [s], [1]] for s in (0.1, 0.12, 0.15)])
    P2[:, 1, 2] = [20.0, 30.0, 40.0]
    P2[:, :, 3] = rng.normal(0, 0.01, (3, 3))
    fn = jax.jit(functools.partial(ground_filter_mask, mode=mode))
    got = np.asarray(fn(anchors.centers, mean_z, valid, P2))
    want = ground_filter_mask_np(anchors.centers, mean_z, valid, P2, mode=mode)
    assert got.shape == (3, n) and 0.05 < want.mean() < 0.95
    assert (got != want).sum() <= 2  # float32 vs float64 right at a threshold
    # the default is the level plane of camera_height, exactly; other planes do not retrace
    level = np.tile(geometry.level_plane(1.65), (3, 1))
    np.testing.assert_array_equal(np.asarray(fn(anchors.centers, mean_z, valid, P2, level)), got)
    planes = np.stack([pitched_plane(a, 1.65 + 0.1 * a) for a in (3.0, -2.0, 6.0)])
    got = np.asarray(fn(anchors.centers, mean_z, valid, P2, planes))
    want = ground_filter_mask_np(anchors.centers, mean_z, valid, P2, planes, mode=mode)
    assert (got != want).sum() <= 2 and fn._cache_size() == 2  # None and an array


def _kitti_network_frames(root):
    """(P2, car boxes) of the labeled frames after the reference test chain (crop 100, h 288)."""
    kitti = KittiObjectLayout(root)
    for fid in kitti.frame_ids("labeled"):
        height = read_image(kitti.image(fid)).shape[0]
        s = 288.0 / (height - 100)
        A = np.diag([s, s, 1.0]) @ np.array([[1.0, 0, 0], [0, 1, -100], [0, 0, 1]])
        P2 = A @ read_calib(kitti.calib(fid)).P2
        objs = read_label(kitti.label(fid))
        cars = objs.select((objs.type == "Car") & (objs.occluded < 2) & (objs.location[:, 2] > 3))
        corners = geometry.box3d_corners(cars.location, cars.dimensions, cars.rotation_y)
        yield P2, geometry.box2d_from_corners(corners, P2)


def test_filter_keeps_real_kitti_cars_and_drops_the_sky(kitti_object_root):
    layout = AnchorLayout(image_size=(288, 1280))
    anchors = generate_anchors(layout)
    # Depth-from-height prior per bin: a 1.55 m tall object filling the anchor's height.
    bin_h = layout.bin_shapes()[:, 1]
    mean_z = (755.0 * 1.55 / bin_h)[anchors.bin_index][None]
    valid = np.ones_like(mean_z, bool)
    frames = list(_kitti_network_frames(kitti_object_root))
    P2 = np.stack([p for p, _ in frames])
    keep = {
        m: ground_filter_mask_np(anchors.centers, mean_z, valid, P2, mode=m)
        for m in ("reference", "paper")
    }
    assert np.mean(keep["reference"] == keep["paper"]) > 0.99
    num_cars = 0
    for i, (p2, boxes) in enumerate(frames):
        iou = box_iou_np(anchors.boxes, boxes)  # (N, M)
        covered = iou >= 0.5
        coverable = covered.any(axis=0)  # cars some anchor can be positive for at all
        num_cars += coverable.sum()
        for mode in keep:
            kept_cover = (covered & keep[mode][i][:, None]).any(axis=0)
            assert kept_cover[coverable].all(), (i, mode, boxes[coverable & ~kept_cover])
        # Anchors lying entirely above the horizon are all dropped; of those centred more
        # than a stride above it, only large boxes reaching far below it (close-range
        # priors) survive: all anchors up to 64 px tall go, ~70 % overall.
        above = anchors.boxes[:, 3] < p2[1, 2]
        sky = anchors.centers[:, 1] < p2[1, 2] - 16
        assert above.sum() > 3000 and not keep["reference"][i][above].any()
        assert keep["reference"][i][sky].mean() < 0.35
        assert not keep["reference"][i][sky & (anchors.shapes[:, 1] <= 64)].any()
        # Below the horizon a good part survives (the filter is not trivially empty).
        assert keep["reference"][i][~sky].mean() > 0.2
    assert num_cars >= 10


def test_mask_from_detection_constants_uses_each_bins_prior_depth():
    layout = AnchorLayout(image_size=(96, 160))
    anchors = generate_anchors(layout)
    rng = np.random.default_rng(3)
    a = layout.anchors_per_cell
    valid = rng.uniform(size=(1, a)) > 0.3
    priors = AnchorPriors(
        layout=layout,
        class_names=("Car",),
        angle_mode="double",
        count=np.full((1, a), 30),
        mean=np.stack([rng.uniform(2, 20, (1, a)), np.zeros((1, a)), np.zeros((1, a))], -1),
        std=np.ones((1, a, 3)),
        valid=valid,
        dims_mean=np.ones((1, 3)),
        dims_std=np.ones((1, 3)),
        num_objects=np.array([100]),
        num_frames=5,
    )
    const = make_detection_constants(anchors, priors)
    P2 = np.stack([P_SIMPLE * [[0.2], [0.2], [1]]] * 2)
    P2[1, 1, 2] = 30.0
    got = np.asarray(ground_mask_from_constants(const, P2, mode="paper"))
    mean_z = priors.mean[:, anchors.bin_index, 0]
    want = ground_filter_mask_np(
        anchors.centers, mean_z, priors.valid[:, anchors.bin_index], P2, mode="paper"
    )
    assert got.shape == (2, len(anchors)) and 0.05 < want.mean() < 0.95
    assert (got != want).sum() <= 2
    assert not got[:, ~valid[0, anchors.bin_index]].any()
