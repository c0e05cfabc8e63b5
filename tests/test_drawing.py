"""Pictures: boxes land on the labelled objects, BEV metric grid, tiling, depth colours."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data.files import read_image
from gac_jax.data.kitti import KittiObjects
from gac_jax.data.sources import KittiDepthSource, KittiObjectSource
from gac_jax.drawing import boxes, depth_pictures, picture_grid

# Largest gap between the projected 3D box and the labelled 2D box on the sample frames is
# ~3 px for rigid objects and ~10 px for pedestrians (arms and legs stick out of the 3D box).
LABEL_SLACK = {"Pedestrian": 10, "Person_sitting": 10}
RIGID_SLACK = 3
LINE_SLACK = 3.5  # anti-aliased thickness-2 lines reach ~3 px beyond their end points


def _drawn(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    return np.any(before != after, axis=2)


def _inside(mask: np.ndarray, box, margin: float) -> bool:
    v, u = np.nonzero(mask)
    return bool(
        np.all(u >= box[0] - margin)
        and np.all(u <= box[2] + margin)
        and np.all(v >= box[1] - margin)
        and np.all(v <= box[3] + margin)
    )


@pytest.fixture(scope="module")
def frames(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    return [src[i] for i in range(len(src))]


def test_boxes_land_on_labelled_objects(frames, tmp_path):
    checked_cars = 0
    for sample in frames:
        image, P2 = sample["image"], sample["P2"]
        objs = sample["objects"].select(boxes.drawable(sample["objects"]))
        union = np.zeros(image.shape[:2], bool)
        for i in range(len(objs)):
            one = objs.select([i])
            mask = _drawn(image, boxes.draw_objects(image, one, P2, show_labels=False))
            box = one.bbox[0]
            slack = LABEL_SLACK.get(str(one.type[0]), RIGID_SLACK) + LINE_SLACK
            assert mask.any(), (sample["frame_id"], i)
            assert _inside(mask, box, slack), (sample["frame_id"], one.type[0], box)
            projected = geometry.box2d_from_corners(
                geometry.box3d_corners(one.location, one.dimensions, one.rotation_y), P2
            )[0]
            assert _inside(mask, projected, LINE_SLACK)
            union |= mask
            if one.type[0] == "Car" and one.truncated[0] == 0:
                checked_cars += 1
                v, u = np.nonzero(mask)
                # The wireframe's extremes touch all four sides of the labelled box.
                band = RIGID_SLACK + LINE_SLACK
                assert np.abs(u - box[0]).min() <= band and np.abs(u - box[2]).min() <= band
                assert np.abs(v - box[1]).min() <= band and np.abs(v - box[3]).min() <= band
                x1, y1, x2, y2 = np.round(box).astype(int)
                assert mask[y1 : y2 + 1, x1 : x2 + 1].sum() > (x2 - x1 + y2 - y1)
        # All objects together (ground-truth style): nothing drawn outside the labelled boxes.
        together = boxes.draw_objects(image, objs, P2, show_labels=False)
        drawn = _drawn(image, together)
        np.testing.assert_array_equal(drawn, union)
        pic = boxes.draw_detections(image, P2, predictions=None, ground_truth=sample["objects"])
        assert pic.shape == image.shape and pic.dtype == np.uint8
        picture_grid.save_image(tmp_path / f"{sample['frame_id']}.png", pic)
        np.testing.assert_array_equal(read_image(tmp_path / f"{sample['frame_id']}.png"), pic)
    assert checked_cars >= 12  # 13 untruncated cars in the vendored frames


def test_predictions_over_ground_truth_with_labels(frames, tmp_path):
    sample = next(f for f in frames if f["frame_id"] == "000036")  # 7 cars, 2 truncated
    gt = sample["objects"]
    pred = gt.replace(score=np.linspace(0.5, 0.99, len(gt)), rotation_y=gt.rotation_y + 0.2)
    image, P2 = sample["image"], sample["P2"]
    plain = boxes.draw_detections(image, P2, pred, gt, show_labels=False, draw_2d=False)
    labelled = boxes.draw_detections(image, P2, pred, gt, show_labels=True, draw_2d=False)
    labels = _drawn(plain, labelled)
    assert labels.any()
    # Labels sit inside the top-left corner of their object's drawn (projected, clipped) extent.
    cars = pred.select(boxes.drawable(pred))
    corners = geometry.box3d_corners(cars.location, cars.dimensions, cars.rotation_y)
    near_corner = np.zeros_like(labels)
    for box in geometry.box2d_from_corners(corners, P2, image.shape[:2]):
        x1, y1 = int(max(box[0] - 12, 0)), int(max(box[1] - 12, 0))
        near_corner[y1 : y1 + 32, x1 : x1 + 90] = True
    assert not (labels & ~near_corner).any()
    # Both colours show: pixels within 40 levels of pure GT green / the Car orange.
    close = lambda c: np.all(np.abs(labelled.astype(int) - c) <= 40, axis=2)  # noqa: E731
    gt_pixels, pred_pixels = close(boxes.GT_COLOR).sum(), close(boxes.class_color("Car")).sum()
    print(f"\n000036: {gt_pixels} GT-green and {pred_pixels} Car-orange pixels")
    assert gt_pixels > 500 and pred_pixels > 500
    picture_grid.save_image(
        tmp_path / "pred_gt.png", picture_grid.image_grid([labelled, plain], ["labels", "none"])
    )


def test_boxes_behind_and_across_the_camera():
    P2 = np.array([[700.0, 0, 600, 45], [0, 700, 180, 0.2], [0, 0, 1, 0.003]])
    image = np.zeros((360, 1200, 3), np.uint8)
    behind = KittiObjects.from_arrays(
        type=["Car"], dimensions=[[1.5, 1.6, 4.0]], location=[[0.0, 1.6, -8.0]], rotation_y=[0.0]
    )
    assert not _drawn(image, boxes.draw_objects(image, behind, P2)).any()
    # Length along z across the camera (z from -1 to 3): edges are cut at the near plane.
    across = behind.replace(location=np.array([[1.0, 1.6, 1.0]]), rotation_y=np.array([np.pi / 2]))
    segments, valid = boxes.box3d_segments(
        across.location, across.dimensions, across.rotation_y, P2, near=0.1
    )
    assert valid.any() and not valid.all()
    assert np.isfinite(segments).all()
    pic = boxes.draw_objects(image, across, P2)
    assert _drawn(image, pic).sum() > 1000


def test_clip_segments_hand_cases():
    segs = np.array(
        [
            [[-10.0, 5.0], [10.0, 5.0]],  # enters from the left
            [[2.0, 3.0], [8.0, 9.0]],  # inside
            [[-5.0, -5.0], [-1.0, 30.0]],  # left of the image
            [[-10.0, -10.0], [30.0, 30.0]],  # diagonal through both corners
            [[5.0, -100.0], [5.0, 100.0]],  # vertical, through
        ]
    )
    out, ok = boxes.clip_segments(segs, (20, 20))  # H = W = 20: [0, 19] x [0, 19]
    np.testing.assert_array_equal(ok, [True, True, False, True, True])
    np.testing.assert_allclose(out[0], [[0, 5], [10, 5]])
    np.testing.assert_allclose(out[1], segs[1])
    np.testing.assert_allclose(out[3], [[0, 0], [19, 19]])
    np.testing.assert_allclose(out[4], [[5, 0], [5, 19]])


def test_bev_pixels_follow_the_metric_grid():
    grid = boxes.BevGrid()  # x in [-30, 30], z in [0, 70] m at 10 px/m
    assert grid.size == (701, 601)
    empty = boxes.draw_bev(grid=grid)
    # Hand-computed: the x = 0 line is column 300, the z = 10 m line row 600, z = 50 m row 200.
    gray, back = (80, 80, 80), (24, 24, 24)
    assert tuple(empty[450, 300]) == gray and tuple(empty[450, 302]) == back
    assert tuple(empty[600, 450]) == gray and tuple(empty[601, 450]) == back
    assert tuple(empty[200, 450]) == gray

    def box(ry):
        return KittiObjects.from_arrays(
            type=["Car"], dimensions=[[1.5, 2.0, 4.0]], location=[[5.0, 1.6, 30.0]], rotation_y=[ry]
        )

    # ry = 0: length along +x: x in [3, 7] -> u in [330, 370]; z in [29, 31] -> v in [390, 410].
    mask = _drawn(empty, boxes.draw_bev(box(0.0), grid=grid))
    assert _inside(mask, [330, 390, 370, 410], 2)
    for u, v in [(330, 390), (370, 390), (330, 410), (370, 410)]:
        assert mask[v - 1 : v + 2, u - 1 : u + 2].any()
    assert mask[400, 360] and not mask[400, 340]  # heading mark towards +x (right)
    # ry = pi/2 heads to -z (towards the camera, down the picture); ground truth in GT_COLOR.
    pic = boxes.draw_bev(None, box(np.pi / 2), grid=grid)
    mask = _drawn(empty, pic)
    assert _inside(mask, [340, 380, 360, 420], 2)
    assert mask[410, 350] and not mask[390, 350]
    assert np.all(pic[mask.nonzero()].max(axis=0) <= [255, 255, 255])
    assert (np.all(pic == boxes.GT_COLOR, axis=2)).sum() > 100


def test_image_grid_shape_and_placement():
    rng = np.random.default_rng(0)
    pics = [rng.integers(0, 256, (30, 40, 3), dtype=np.uint8) for _ in range(5)]
    out = picture_grid.image_grid(pics, [f"frame {i}" for i in range(5)], columns=2, pad=4)
    assert out.shape == (3 * (30 + 18) + 4 * 4, 2 * 40 + 3 * 4, 3)
    np.testing.assert_array_equal(out[4 + 18 : 4 + 18 + 30, 4:44], pics[0])
    np.testing.assert_array_equal(out[4 + 18 : 4 + 18 + 30, 48:88], pics[1])
    np.testing.assert_array_equal(out[2 * 52 + 4 + 18 : 2 * 52 + 52, 4:44], pics[4])
    assert out[4 : 4 + 18, 4:44].any()  # caption text
    bare = picture_grid.image_grid(pics[:3], None, columns=3, pad=0)
    assert bare.shape == (30, 120, 3)
    np.testing.assert_array_equal(bare[:, 80:], pics[2])
    small = picture_grid.image_grid([pics[0], np.zeros((10, 20), np.uint8)], columns=1, pad=0)
    assert small.shape == (60, 40, 3)
    with pytest.raises(ValueError, match="captions"):
        picture_grid.image_grid(pics, ["a"])


@pytest.mark.parametrize("scale", ["inverse", "log"])
def test_depth_colours_monotonic_and_invalid_black(scale):
    depth = np.linspace(1.0, 80.0, 400)[None, :]
    rgb = depth_pictures.colorize_depth(depth, scale=scale).astype(np.float64)[0]
    luma = rgb @ [0.299, 0.587, 0.114]
    # OpenCV's 8-bit MAGMA table has one -0.06 luma step (index 49 -> 50): tolerate 0.1.
    assert np.all(np.diff(luma) <= 0.1), "brightness must not increase with depth"
    octaves = depth_pictures.colorize_depth(np.array([[1.0, 2, 4, 8, 16, 32, 64]]), scale=scale)[0]
    assert np.all(np.diff(octaves.astype(float) @ [0.299, 0.587, 0.114]) < 0)
    assert luma[0] > 200 and luma[-1] < 40
    assert np.all(rgb.sum(axis=1) > 0), "valid pixels are never black"
    bad = np.array([[0.0, -3.0, np.nan, np.inf, 5.0, 200.0, 0.5]])
    out = depth_pictures.colorize_depth(bad, scale=scale)
    assert not out[0, :4].any()
    np.testing.assert_array_equal(out[0, 5], rgb[-1])  # beyond max_depth clamps to the far colour
    np.testing.assert_array_equal(out[0, 6], rgb[0])  # nearer than min_depth clamps to near


def test_sparse_depth_dilation_nearest_wins():
    depth = np.zeros((12, 12))
    depth[5, 5], depth[5, 6] = 10.0, 20.0
    out = depth_pictures.colorize_depth(depth, dilate=3)
    c10 = depth_pictures.colorize_depth(np.array([[10.0]]))[0, 0]
    c20 = depth_pictures.colorize_depth(np.array([[20.0]]))[0, 0]
    np.testing.assert_array_equal(out[4, 4], c10)
    np.testing.assert_array_equal(out[5, 6], c10)  # the 10 m point covers its neighbour
    np.testing.assert_array_equal(out[5, 7], c20)
    assert not out[0, 0].any() and not out[5, 8].any()
    assert np.count_nonzero(out.any(axis=2)) == 3 * 4


def test_depth_panel_on_real_frame(kitti_samples, tmp_path):
    src = KittiDepthSource(kitti_samples / "depth", "train", cameras=(2,))
    sample = src[0]
    image, gt = sample["image"], sample["depth"]
    prediction = geometry.ground_depth_map(image.shape[:2], sample["P2"])  # a flat road
    panel = depth_pictures.depth_panel(image, prediction, gt)
    h, w = image.shape[:2]
    assert panel.shape == (3 * (h + 18) + 4 * 4, w + 8, 3)
    top = 3 * 4 + 2 * (h + 18) + 18
    gt_pic = panel[top : top + h, 4 : 4 + w]
    np.testing.assert_array_equal(gt_pic, depth_pictures.colorize_depth(gt, dilate=3))
    coverage = gt_pic.any(axis=2).mean()
    assert (gt > 0).mean() < coverage < 1.0  # dilated, yet the empty sky stays black
    pred_pic = panel[4 + 18 + h + 4 + 18 : 4 + 18 + h + 4 + 18 + h, 4 : 4 + w]
    horizon = int(np.ceil(sample["P2"][1, 2]))
    assert not pred_pic[: horizon - 1].any()  # no ground above the horizon
    luma = pred_pic[horizon + 2 :, w // 2].astype(float) @ [0.299, 0.587, 0.114]
    assert np.all(np.diff(luma) >= -0.1)  # the road gets nearer (brighter) downwards
    assert luma[-1] > luma[0] + 20
    picture_grid.save_image(tmp_path / "depth_panel.png", panel)
    # Smaller prediction (network resolution) is resized to the image.
    small = cv2.resize(prediction, (w // 4, h // 4), interpolation=cv2.INTER_NEAREST)
    assert depth_pictures.depth_panel(image, small).shape == (2 * (h + 18) + 3 * 4, w + 8, 3)


def test_2d_boxes_trace_the_bbox_border():
    image = np.zeros((100, 200, 3), np.uint8)
    objs = KittiObjects.from_arrays(
        type=["Car", "DontCare"], bbox=[[20.0, 30.0, 120.0, 80.0], [0.0, 0.0, 199.0, 99.0]]
    )
    mask = _drawn(
        image,
        boxes.draw_objects(
            image, objs, np.eye(3, 4), draw_3d=False, draw_2d=True, show_labels=False
        ),
    )
    v, u = np.nonzero(mask)
    on_border = (np.minimum(np.abs(u - 20), np.abs(u - 120)) <= 1) | (
        np.minimum(np.abs(v - 30), np.abs(v - 80)) <= 1
    )
    assert on_border.all() and _inside(mask, [20, 30, 120, 80], 1)
    assert mask[30, 20:121].mean() > 0.9 and mask[30:81, 120].mean() > 0.9


def test_wireframes_in_one_call_equal_segment_by_segment(frames):
    """The vectorised drawing (one cv2.polylines per run of one colour) gives the pixels of
    cv2.line per segment in the same order, byte for byte (the reference loop written out)."""
    sample = next(f for f in frames if f["frame_id"] == "000036")
    gt = sample["objects"]
    objects = gt.select(boxes.drawable(gt))
    image, P2 = np.asarray(sample["image"]), sample["P2"]
    segments, valid = boxes.box3d_segments(
        objects.location, objects.dimensions, objects.rotation_y, P2
    )
    clipped, visible = boxes.clip_segments(segments, image.shape[:2])
    reference = image.copy()
    for k in range(len(objects)):
        colour = boxes.class_color(objects.type[k])
        for (p, q), ok in zip(clipped[k], visible[k] & valid[k], strict=True):
            if ok:
                a = tuple(int(round(c * 16)) for c in p)
                b = tuple(int(round(c * 16)) for c in q)
                cv2.line(reference, a, b, colour, 2, cv2.LINE_AA, 4)
    drawn = boxes.draw_objects(image, objects, P2, show_labels=False)
    np.testing.assert_array_equal(drawn, reference)


def test_labels_of_nearby_boxes_do_not_overlap(frames):
    """Labels are placed highest score first; one that would cover another moves below it
    or is left out, never drawn over it."""
    sample = next(f for f in frames if f["frame_id"] == "000036")
    gt = sample["objects"].select(boxes.drawable(sample["objects"]))
    # every box twice, shifted 0.3 m: their labels would land on each other
    crowd = KittiObjects.concatenate([gt, gt.replace(location=gt.location + [0.3, 0.0, 0.0])])
    crowd = crowd.replace(score=np.linspace(0.2, 0.95, len(crowd)))
    texts = [f"{t} {s:.2f}" for t, s in zip(crowd.type, crowd.score, strict=True)]
    corners = np.repeat(np.array([[100.0, 50.0]]), len(texts), axis=0)
    spots = boxes.place_labels(texts, corners, (375, 1242), 0.4)
    placed = [s for s in spots if s is not None]
    assert len(placed) == 4 and spots[0] == (100, 50, *spots[0][2:])  # the first keeps its place
    cover = np.zeros((375, 1242), int)
    for x, y, w, h, _ in placed:
        cover[y : y + h, x : x + w] += 1
    assert cover.max() == 1
    pic = boxes.draw_objects(sample["image"], crowd, sample["P2"])
    assert pic.shape == sample["image"].shape


def test_bev_axis_labels_do_not_collide():
    """The bottom-left corner holds the "0 m" label alone (the x = -30 label sat on it), and
    a label that would be cut by the picture's edge is left out."""
    grid = boxes.BevGrid(pixels_per_metre=5.3)  # the grid of a 375-row picture
    h, w = grid.size
    empty = boxes.draw_bev(grid=grid)
    back, line = (24, 24, 24), (80, 80, 80)
    alone = np.empty_like(empty)
    alone[:] = back
    cv2.line(alone, (0, 0), (0, h - 1), line, 1)  # x = -30 m
    cv2.line(alone, (0, h - 1), (w - 1, h - 1), line, 1)  # z = 0 m
    cv2.putText(alone, "0 m", (3, h - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, line, 1, cv2.LINE_AA)
    (tw, th), _ = cv2.getTextSize("0 m", cv2.FONT_HERSHEY_SIMPLEX, 0.35, 1)
    corner = np.s_[h - 6 - th : h, : 3 + tw + 3]
    np.testing.assert_array_equal(empty[corner], alone[corner])
    # z = 70 m (the top edge) has no label; the top rows are plain background or grid lines
    assert set(map(tuple, empty[:2].reshape(-1, 3))) <= {back, line}
