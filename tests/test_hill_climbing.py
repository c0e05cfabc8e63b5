"""Hill climbing of the yaw on 2D-3D box consistency."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.sources import KittiObjectSource
from gac_jax.detection import hill_climbing as hc

# A KITTI-like P2 (frame 000008) and image size.
P2 = np.array(
    [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ]
)
SIZE = (375, 1242)


def _projected_box_reference(loc, dims, ry, P, size):
    """Independent float64 version: 8 explicit corners, pinhole projection, clip to [0,W]x[0,H]."""
    h, w, l = dims
    c, s = np.cos(ry), np.sin(ry)
    pts = []
    for dx, dy, dz in [
        (sx * l / 2, -yy, sz * w / 2) for sx in (1, -1) for sz in (1, -1) for yy in (0, h)
    ]:
        pts.append([loc[0] + c * dx + s * dz, loc[1] + dy, loc[2] - s * dx + c * dz, 1.0])
    hom = np.asarray(pts) @ P.T
    assert (hom[:, 2] > 0.1).all(), "reference only handles boxes in front of the camera"
    u, v = hom[:, 0] / hom[:, 2], hom[:, 1] / hom[:, 2]
    H, W = size
    return np.array(
        [
            np.clip(u.min(), 0, W),
            np.clip(v.min(), 0, H),
            np.clip(u.max(), 0, W),
            np.clip(v.max(), 0, H),
        ]
    )


def _random_objects(rng, n):
    loc = np.stack([rng.uniform(-15, 15, n), rng.uniform(1.0, 2.0, n), rng.uniform(5, 60, n)], 1)
    dims = np.stack(
        [rng.uniform(1.3, 1.9, n), rng.uniform(1.4, 2.0, n), rng.uniform(3.0, 5.0, n)], 1
    )
    return loc, dims, rng.uniform(-np.pi, np.pi, n)


def test_projected_box_matches_independent_projection():
    rng = np.random.default_rng(0)
    loc, dims, ry = _random_objects(rng, 20)
    got = hc.projected_box(loc, dims, ry, P2, SIZE)
    for i in range(20):
        want = _projected_box_reference(loc[i], dims[i], ry[i], P2, SIZE)
        np.testing.assert_allclose(got[i], want, atol=1e-9)
        np.testing.assert_allclose(
            hc.projected_box(loc[i], dims[i], ry[i], P2, SIZE), want, atol=1e-9
        )


def test_paired_iou_hand_cases():
    a = np.array([[0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 10, 10], [0, 0, 0, 0], [0, 0, 2, 2.0]])
    b = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30], [0, 0, 0, 0], [np.nan] * 4])
    np.testing.assert_allclose(hc.paired_iou(a, b), [1.0, 50 / 150, 0.0, 0.0, 0.0])


def _recording_objective(monkeypatch, f):
    """Replaces the IoU with f(ry) and records every batch of evaluated angles."""
    calls = []

    def objective(box2d, location, dims, P, size):
        def iou(rows, ry):
            ry = np.asarray(ry, np.float64).reshape(-1)
            calls.append(ry.copy())
            return f(ry)

        return iou

    monkeypatch.setattr(hc, "consistency_objective", objective)
    return calls


def test_schedule_hand_trace(monkeypatch):
    # f peaks at 0.25. Traced by hand with s = 0.4 halving to 0.00625 (6 halvings):
    # 0 -> +0.4 (better); at 0.4 both worse -> s=0.2; -0.2 better -> 0.2; both worse -> s=0.1;
    # 0.3 only ties (not strict) -> s=0.05; +0.05 -> 0.25; then halvings to the end.
    calls = _recording_objective(monkeypatch, lambda r: -np.abs(r - 0.25))
    out = hc.optimize_rotation_y(np.zeros(4), np.zeros(3), np.ones(3), 0.0, P2, SIZE)
    expected = [
        [0.0],
        [0.4, -0.4],
        [0.8, 0.0],
        [0.6, 0.2],
        [0.4, 0.0],
        [0.3, 0.1],
        [0.25, 0.15],
        [0.3, 0.2],
        [0.275, 0.225],
        [0.2625, 0.2375],
    ]
    assert len(calls) == len(expected)
    for got, want in zip(calls, expected, strict=True):
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert out == pytest.approx(0.25, abs=1e-12)


def test_schedule_ties_go_minus_and_steps_are_kept(monkeypatch):
    # Both sides equally better: '+' must also beat '-', so '-' is taken; the step stays 0.4
    # after the move and the plateau (no strict gain) ends the search at -0.8.
    calls = _recording_objective(monkeypatch, lambda r: np.minimum(np.abs(r), 0.8))
    out = hc.optimize_rotation_y(np.zeros(4), np.zeros(3), np.ones(3), 0.0, P2, SIZE)
    np.testing.assert_allclose(calls[1], [0.4, -0.4])
    np.testing.assert_allclose(calls[2], [0.0, -0.8])
    np.testing.assert_allclose(calls[3], [-0.4, -1.2])
    np.testing.assert_allclose(calls[4], [-0.6, -1.0])  # halved to 0.2
    assert len(calls) == 1 + 3 + 5  # initial, 2 moves + 1 failed at 0.4, 5 more halvings
    assert out == pytest.approx(-0.8)


def test_result_is_wrapped(monkeypatch):
    _recording_objective(monkeypatch, lambda r: -np.abs(r - 3.5))
    out = hc.optimize_rotation_y(np.zeros(4), np.zeros(3), np.ones(3), 3.0, P2, SIZE)
    assert out == pytest.approx(3.5 - 2 * np.pi, abs=0.01)


def test_never_lowers_iou_and_leaves_inputs_untouched():
    rng = np.random.default_rng(1)
    loc, dims, ry = _random_objects(rng, 40)
    # Network-like 2D boxes: the projection at another yaw, jittered by a few pixels.
    boxes = hc.projected_box(loc, dims, ry + rng.normal(0, 0.5, 40), P2, SIZE)
    boxes = boxes + rng.normal(0, 3, boxes.shape)
    args = [a.copy() for a in (boxes, loc, dims, ry)]
    out = hc.optimize_rotation_y_batch(*args, P2, SIZE)
    for a, b in zip(args, (boxes, loc, dims, ry), strict=True):
        np.testing.assert_array_equal(a, b)
    before = hc.consistency_iou(boxes, loc, dims, ry, P2, SIZE)
    after = hc.consistency_iou(boxes, loc, dims, out, P2, SIZE)
    assert (after >= before - 1e-12).all()
    assert (after > before + 1e-3).mean() > 0.5
    assert np.all((out > -np.pi) & (out <= np.pi))


def test_batch_equals_one_by_one_and_handles_odd_boxes():
    rng = np.random.default_rng(2)
    loc, dims, ry = _random_objects(rng, 6)
    loc[4] = [1.0, 1.6, 1.0]  # straddles the near plane (extends behind the camera)
    loc[5] = [40.0, 1.6, 8.0]  # projects entirely outside the image
    boxes = hc.projected_box(loc, dims, ry + 0.3, P2, SIZE)
    boxes[5] = [0, 0, 50, 50]
    batch = hc.optimize_rotation_y_batch(boxes, loc, dims, ry, P2, SIZE)
    single = [hc.optimize_rotation_y(boxes[i], loc[i], dims[i], ry[i], P2, SIZE) for i in range(6)]
    np.testing.assert_array_equal(batch, single)
    assert np.isfinite(batch).all()
    assert batch[5] == pytest.approx(ry[5])  # IoU 0 everywhere: nothing moves
    assert hc.optimize_rotation_y_batch(
        np.zeros((0, 4)), loc[:0], dims[:0], ry[:0], P2, SIZE
    ).shape == (0,)
    with pytest.raises(ValueError, match="matching counts"):
        hc.optimize_rotation_y_batch(boxes, loc[:2], dims, ry, P2, SIZE)


def test_objective_equals_consistency_iou_for_any_rows_in_any_order():
    """The objective keeps the last rows' arrays: calls with other rows (fewer, repeated,
    reordered, a box straddling the near plane) still give ``consistency_iou`` bit for bit."""
    rng = np.random.default_rng(3)
    loc, dims, ry = _random_objects(rng, 8)
    loc[2] = [1.0, 1.6, 1.0]  # straddles the near plane
    boxes = hc.projected_box(loc, dims, ry + 0.2, P2, SIZE) + rng.normal(0, 2, (8, 4))
    objective = hc.consistency_objective(boxes, loc, dims, P2, SIZE)
    all_rows = np.arange(8)
    for rows in (all_rows, all_rows[3:], np.r_[all_rows, all_rows], all_rows[::-1], all_rows):
        yaw = rng.uniform(-np.pi, np.pi, len(rows))
        want = hc.consistency_iou(boxes[rows], loc[rows], dims[rows], yaw, P2, SIZE)
        np.testing.assert_array_equal(objective(rows, yaw), want)


def test_recovers_kitti_yaw(kitti_object_root):
    """Real labels: 2D box = projection of the true 3D box, yaw perturbed by +-0.3 rad."""
    src = KittiObjectSource(kitti_object_root, "labeled")
    before, after = [], []
    for i in range(len(src)):
        sample = src[i]
        objs = sample["objects"].select(sample["objects"].type == "Car")
        size = sample["image"].shape[:2]
        if not len(objs):
            continue
        box = hc.projected_box(objs.location, objs.dimensions, objs.rotation_y, sample["P2"], size)
        for sign in (1.0, -1.0):
            start = objs.rotation_y + sign * 0.3
            out = hc.optimize_rotation_y_batch(
                box, objs.location, objs.dimensions, start, sample["P2"], size
            )
            iou0 = hc.consistency_iou(
                box, objs.location, objs.dimensions, start, sample["P2"], size
            )
            iou1 = hc.consistency_iou(box, objs.location, objs.dimensions, out, sample["P2"], size)
            assert (iou1 >= iou0 - 1e-12).all()
            before.append(np.abs(np.angle(np.exp(1j * (start - objs.rotation_y)))))
            after.append(np.abs(np.angle(np.exp(1j * (out - objs.rotation_y)))))
    before, after = np.concatenate(before), np.concatenate(after)
    assert before.size >= 30  # 16 cars, two perturbations each
    print(
        f"\nKITTI cars n={before.size}: median |ry err| before {np.median(before):.3f} "
        f"after {np.median(after):.4f}; mean {before.mean():.3f} -> {after.mean():.3f}; "
        f"within 0.05 rad: {(after < 0.05).mean():.2f}"
    )
    assert np.median(after) < 0.02
    assert (after < 0.05).mean() > 0.7
    assert after.mean() < 0.5 * before.mean()
