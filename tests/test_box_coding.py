"""Box coding: hand-computed targets, exact round trips on random data and real KITTI labels."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data.files import read_image
from gac_jax.data.kitti import KittiObjectLayout, read_calib, read_label
from gac_jax.detection.anchor_priors import AnchorPriors, make_detection_constants
from gac_jax.detection.anchors import AnchorLayout, box_iou_np, generate_anchors
from gac_jax.detection.box_coding import (
    decode,
    decode_np,
    decode_outputs,
    encode,
    encode_np,
    gather_priors,
)


def _wrap(a):
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def test_hand_computed_targets():
    anchor = [0.0, 0.0, 20.0, 10.0]  # centre (10, 5), size (20, 10)
    args = (
        [2.0, 1.0, 26.0, 13.0],  # centre (14, 7), size (24, 12)
        [16.0, 3.0],
        25.0,
        [1.5, 1.6, 4.0],  # (h, w, l)
        np.pi / 6,
        [20.0, 0.1, 0.2],
        [5.0, 0.5, 0.5],
        [1.4, 1.7, 3.8],
        [0.1, 0.2, 0.4],
    )
    expected = [
        2.0,
        2.0,
        np.log(1.2) / 0.2,
        np.log(1.2) / 0.2,
        3.0,
        -2.0,
        1.0,
        (np.sin(np.pi / 3) - 0.1) / 0.5,
        (0.5 - 0.2) / 0.5,
        -0.5,  # w3d = (1.6 - 1.7) / 0.2
        1.0,  # h3d = (1.5 - 1.4) / 0.1
        0.5,  # l3d = (4.0 - 3.8) / 0.4
    ]
    targets, sign = encode_np(anchor, *args)
    np.testing.assert_allclose(targets, expected, rtol=1e-12, atol=1e-12)
    assert sign == 1.0
    targets32, sign32 = encode(jnp.asarray(anchor), *map(jnp.asarray, args))
    np.testing.assert_allclose(targets32, expected, rtol=1e-5, atol=1e-5)
    _, sign_back = encode_np(anchor, *args[:4], 2.0, *args[5:])
    assert sign_back == 0.0  # cos(2.0) < 0


def _random_pairs(rng, n):
    anchors_c = rng.uniform(0, 500, (n, 2))
    anchors_s = rng.uniform(10, 300, (n, 2))
    anchors = np.concatenate([anchors_c - anchors_s / 2, anchors_c + anchors_s / 2], -1)
    gt_c = anchors_c + rng.normal(0, 10, (n, 2))
    gt_s = anchors_s * rng.uniform(0.5, 2.0, (n, 2))
    gt_boxes = np.concatenate([gt_c - gt_s / 2, gt_c + gt_s / 2], -1)
    alpha = rng.uniform(-np.pi, np.pi, n)
    alpha = np.where(np.abs(np.abs(alpha) - np.pi / 2) < 1e-3, 0.3, alpha)
    return (
        anchors,
        gt_boxes,
        gt_c + rng.normal(0, 20, (n, 2)),
        rng.uniform(3, 80, n),
        rng.uniform([1.2, 0.4, 0.5], [3.0, 2.5, 12.0], (n, 3)),
        alpha,
        np.stack([rng.uniform(5, 60, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)], -1),
        rng.uniform(0.2, 10, (n, 3)),
        rng.uniform([1.3, 1.5, 3.5], [1.7, 1.8, 4.5], (n, 3)),
        rng.uniform(0.1, 0.5, (n, 3)),
    )


@pytest.mark.parametrize("angle_mode", ["double", "single"])
def test_random_round_trip_numpy_and_jnp(angle_mode):
    rng = np.random.default_rng(0)
    anchors, gt_boxes, center, depth, dims, alpha, pm, ps, dm, ds = _random_pairs(rng, 500)
    priors = (pm, ps, dm, ds)
    targets, sign = encode_np(
        anchors, gt_boxes, center, depth, dims, alpha, *priors, angle_mode=angle_mode
    )
    logit = np.where(sign > 0.5, 8.0, -8.0)
    for out, tol in (
        (decode_np(anchors, targets, logit, *priors, angle_mode=angle_mode), 1e-9),
        (
            jax.jit(decode, static_argnames="angle_mode")(
                *map(jnp.asarray, (anchors, targets, logit, *priors)), angle_mode=angle_mode
            ),
            2e-4,
        ),
    ):
        np.testing.assert_allclose(out["boxes"], gt_boxes, rtol=tol, atol=tol * 100)
        np.testing.assert_allclose(out["center"], center, rtol=tol, atol=tol * 100)
        np.testing.assert_allclose(out["depth"], depth, rtol=tol, atol=tol * 10)
        np.testing.assert_allclose(out["dims"], dims, rtol=tol, atol=tol)
        np.testing.assert_allclose(_wrap(np.asarray(out["alpha"]) - alpha), 0.0, atol=tol * 10)
    # jnp encode agrees with the float64 twin.
    t32, s32 = encode(
        *map(jnp.asarray, (anchors, gt_boxes, center, depth, dims, alpha, *priors)),
        angle_mode=angle_mode,
    )
    np.testing.assert_allclose(t32, targets, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(s32, sign)


def test_alpha_decoding_range_follows_the_reference():
    anchors = np.zeros((4, 4)) + [0, 0, 10, 10]
    deltas = np.zeros((4, 12))
    alpha = np.array([0.5, -1.0, 2.5, -2.5])
    deltas[:, 7], deltas[:, 8] = np.sin(2 * alpha), np.cos(2 * alpha)
    logits = np.where(np.cos(alpha) > 0, 1.0, -1.0)
    priors = (np.zeros(3), np.ones(3), np.ones(3), np.ones(3))
    out = decode_np(anchors, deltas, logits, *priors)
    # Not re-wrapped: the negative-cosine angles come back in (pi/2, 3pi/2].
    np.testing.assert_allclose(out["alpha"], [0.5, -1.0, 2.5, 2 * np.pi - 2.5], atol=1e-12)
    wrapped = decode_np(anchors, deltas, logits, *priors, wrap_alpha=True)
    np.testing.assert_allclose(wrapped["alpha"], alpha, atol=1e-12)


def _kitti_cars(root):
    kitti = KittiObjectLayout(root)
    for fid in kitti.frame_ids("labeled"):
        s = 288.0 / (read_image(kitti.image(fid)).shape[0] - 100)
        A = np.diag([s, s, 1.0]) @ np.array([[1.0, 0, 0], [0, 1, -100], [0, 0, 1]])
        objs = read_label(kitti.label(fid))
        yield A @ read_calib(kitti.calib(fid)).P2, objs.select(np.isin(objs.type, ["Car", "Van"]))


def test_kitti_labels_round_trip_through_p2(kitti_object_root):
    """Encode real labels (the data contract's targets via P2), decode, and recover the 3D box."""
    anchors = generate_anchors(AnchorLayout(image_size=(288, 1280)))
    rows = []
    for P2, cars in _kitti_cars(kitti_object_root):
        h = cars.dimensions[:, 0]
        centre3d = cars.location - np.stack([0 * h, h / 2, 0 * h], -1)
        uv, depth = geometry.project(centre3d, P2)
        corners = geometry.box3d_corners(cars.location, cars.dimensions, cars.rotation_y)
        boxes = geometry.box2d_from_corners(corners, P2)
        alpha = geometry.alpha_from_rotation_y(cars.rotation_y, cars.location, P2)
        best = box_iou_np(anchors.boxes, boxes).argmax(0)  # each car's best anchor
        for i in range(len(cars)):
            pose = (P2, centre3d[i], cars.location[i], cars.rotation_y[i], anchors.boxes[best[i]])
            rows.append((*pose, boxes[i], uv[i], depth[i], cars.dimensions[i], alpha[i]))
    assert len(rows) >= 16  # every car of the vendored frames
    P2s, centre3d, location, ry_gt, anchor_boxes, *gt = (
        np.stack(c) for c in zip(*rows, strict=True)
    )
    m = len(rows)
    priors = [
        np.tile(v, (m, 1))
        for v in ([25.0, 0.0, 0.3], [12.0, 0.7, 0.7], [1.53, 1.63, 3.88], [0.14, 0.10, 0.43])
    ]

    @jax.jit
    def round_trip(anchor_boxes, gt, priors):
        targets, sign = encode(anchor_boxes, *gt, *priors)
        return decode(anchor_boxes, targets, jnp.where(sign > 0, 5.0, -5.0), *priors)

    out = jax.tree.map(np.asarray, round_trip(anchor_boxes, gt, priors))
    boxes, uv, depth, dims, _ = gt
    np.testing.assert_allclose(out["boxes"], boxes, atol=2e-3)
    np.testing.assert_allclose(out["center"], uv, atol=2e-3)
    np.testing.assert_allclose(out["depth"], depth, atol=1e-4)
    np.testing.assert_allclose(out["dims"], dims, atol=1e-5)
    # Back to the 3D box: centre by unprojection, yaw from the decoded alpha.
    for i in range(m):
        c, d = out["center"][i].astype(np.float64), np.float64(out["depth"][i])
        np.testing.assert_allclose(geometry.unproject(c, d, P2s[i]), centre3d[i], atol=2e-3)
        ry = geometry.rotation_y_from_alpha(np.float64(out["alpha"][i]), location[i], P2s[i])
        np.testing.assert_allclose(_wrap(ry - ry_gt[i]), 0.0, atol=1e-5)


def test_decode_outputs_uses_the_best_class_priors():
    layout = AnchorLayout(image_size=(32, 32), base_size=16.0, scales=(1.0, 2.0))
    anchors = generate_anchors(layout)
    rng = np.random.default_rng(1)
    k, a = 2, layout.anchors_per_cell
    priors = AnchorPriors(
        layout=layout,
        class_names=("Car", "Pedestrian"),
        angle_mode="double",
        count=np.full((k, a), 20),
        mean=rng.uniform(5, 40, (k, a, 3)),
        std=rng.uniform(0.5, 5, (k, a, 3)),
        valid=np.array([[True, True, False, True], [True, False, True, True]]),
        dims_mean=rng.uniform(1, 4, (k, 3)),
        dims_std=rng.uniform(0.1, 0.5, (k, 3)),
        num_objects=np.full(k, 100),
        num_frames=10,
    )
    const = make_detection_constants(anchors, priors)
    n = len(anchors)
    outputs = {
        "cls_logits": jnp.asarray(rng.normal(0, 2, (2, n, k)), jnp.float32),
        "sign_logits": jnp.asarray(rng.normal(0, 2, (2, n)), jnp.float32),
        "reg": jnp.asarray(rng.normal(0, 1, (2, n, 12)), jnp.float32),
    }
    out = jax.jit(decode_outputs)(outputs, const)
    labels = np.asarray(outputs["cls_logits"]).argmax(-1)
    np.testing.assert_array_equal(out["labels"], labels)
    np.testing.assert_allclose(
        out["scores"], 1 / (1 + np.exp(-np.asarray(outputs["cls_logits"]).max(-1))), rtol=1e-6
    )
    b, bins = labels, anchors.bin_index[None]
    np.testing.assert_array_equal(out["prior_valid"], priors.valid[b, bins])
    ref = decode_np(
        anchors.boxes[None],
        np.asarray(outputs["reg"]),
        np.asarray(outputs["sign_logits"]),
        priors.effective_mean()[b, bins],
        priors.effective_std()[b, bins],
        priors.dims_mean[b],
        priors.dims_std[b],
    )
    ok = priors.valid[b, bins]  # sentinel (1e10) stds make invalid bins' numbers meaningless
    for key in ("boxes", "center", "dims", "alpha"):
        np.testing.assert_allclose(np.asarray(out[key])[ok], ref[key][ok], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(out["depth"])[ok], ref["depth"][ok], rtol=1e-5)
    pm, ps, dm, ds = gather_priors(const, jnp.asarray(labels))
    np.testing.assert_allclose(pm, priors.effective_mean()[b, bins], rtol=1e-6)
    np.testing.assert_allclose(ds, priors.dims_std[b], rtol=1e-6)


@pytest.mark.parametrize("axis", [0.0, np.pi / 4, 1.0])
def test_sign_axis_round_trip_and_reference_equivalence(axis):
    """Any sign-bit axis round-trips alpha; axis 0 is the reference's 1[cos a > 0] rule."""
    rng = np.random.default_rng(3)
    n = 400
    alpha = rng.uniform(-np.pi, np.pi, n)
    anchors = np.tile([10.0, 20.0, 50.0, 60.0], (n, 1))
    boxes = anchors + rng.uniform(-3, 3, (n, 4))
    center = rng.uniform(20, 50, (n, 2))
    depth = rng.uniform(5, 50, n)
    dims = rng.uniform(1, 4, (n, 3))
    pm, ps = np.tile([20.0, 0.0, 0.0], (n, 1)), np.tile([8.0, 0.7, 0.7], (n, 1))
    dm, ds = np.array([1.5, 1.6, 3.9]), np.array([0.2, 0.2, 0.5])
    args = (anchors, boxes, center, depth, dims, alpha, pm, ps, dm, ds)
    targets, sign = encode_np(*args, sign_axis=axis)
    np.testing.assert_array_equal(sign, np.cos(alpha - axis) > 0)
    logit = np.where(sign > 0.5, 5.0, -5.0)
    out = decode_np(anchors, targets, logit, pm, ps, dm, ds, sign_axis=axis, wrap_alpha=True)
    err = np.abs(np.angle(np.exp(1j * (out["alpha"] - alpha))))
    assert err.max() < 1e-9
    if axis == 0.0:
        ref_sign = np.cos(alpha) > 0
        np.testing.assert_array_equal(sign, ref_sign)
        a0 = np.arctan2(np.sin(2 * alpha), np.cos(2 * alpha)) / 2
        ref = np.where(ref_sign, a0, a0 + np.pi)
        np.testing.assert_allclose(
            decode_np(anchors, targets, logit, pm, ps, dm, ds)["alpha"], ref, atol=1e-9
        )


def test_sign_axis_makes_views_from_behind_stable():
    """Near a = -pi/2 (seen from behind) tiny errors in sin 2a flip the reference's decoded
    angle by pi unless the bit is exactly consistent; with the axis at pi/4 they do not."""
    alpha = np.array([-np.pi / 2 + 0.02, -np.pi / 2 - 0.02])
    s, c = np.sin(2 * alpha), np.cos(2 * alpha)
    # The network gets the 2a regression right up to the sign of the small sin term
    # (swap it) and predicts the bit that is right for the *other* object.
    deltas = np.zeros((2, 12))
    deltas[:, 7], deltas[:, 8] = -s, c
    zeros3, ones3 = np.zeros((2, 3)), np.ones((2, 3))
    anchors = np.tile([0.0, 0.0, 10.0, 10.0], (2, 1))
    for axis, expect_flip in [(0.0, True), (np.pi / 4, False)]:
        bit = np.cos(alpha - axis) > 0
        out = decode_np(
            anchors, deltas, np.where(bit, 5.0, -5.0), zeros3, ones3, zeros3, ones3,
            sign_axis=axis,
        )  # fmt: skip
        err = np.abs(np.angle(np.exp(1j * (out["alpha"] - alpha))))
        assert (err.max() > 3.0) == expect_flip, (axis, err)
