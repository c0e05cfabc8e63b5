"""The faster host path (issue 24, part 3) gives exactly what it gave before.

The implementations these replaced are kept here as references, written as they were:
the hill climbing that projected every candidate through ``consistency_iou`` (box
corners, near-plane cut, clip, IoU), NMS over the full ``N x N`` IoU matrix,
``Normalize`` on the ``(H, W, 3)`` image, the BGR decode + colour conversion, and the
evaluator loop without the host thread. Every comparison is bit-for-bit (``==`` on
float64 / float32 arrays, equal KITTI result text), not within a tolerance.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data import transforms as tf
from gac_jax.data.files import KittiFormatError, read_bytes, read_image
from gac_jax.data.kitti import format_label
from gac_jax.data.sources import KittiObjectSource
from gac_jax.detection import hill_climbing as hc
from gac_jax.detection import inference
from gac_jax.detection import nms as nms_module

P2 = np.array(
    [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ]
)
SIZE = (288, 1280)


def reference_hill_climbing(boxes2d, loc, dims, ry, P, size, initial_step=0.4, min_step=0.01):
    """The loop as it was: each iteration projects the tiled candidates with consistency_iou."""
    boxes2d = np.asarray(boxes2d, np.float64).reshape(-1, 4)
    loc = np.asarray(loc, np.float64).reshape(-1, 3)
    dims = np.asarray(dims, np.float64).reshape(-1, 3)
    ry = np.asarray(ry, np.float64).reshape(-1).copy()
    n = ry.shape[0]
    if n == 0:
        return ry
    step = np.full(n, float(initial_step))
    best = hc.consistency_iou(boxes2d, loc, dims, ry, P, size)
    for _ in range(1000):
        act = np.flatnonzero(step > min_step)
        if act.size == 0:
            break
        m = act.size
        cand = np.concatenate([ry[act] + step[act], ry[act] - step[act]])
        iou = hc.consistency_iou(
            np.tile(boxes2d[act], (2, 1)),
            np.tile(loc[act], (2, 1)),
            np.tile(dims[act], (2, 1)),
            cand,
            P,
            size,
        )
        plus, minus, cur = iou[:m], iou[m:], best[act]
        go_plus = (plus > cur) & (plus > minus)
        go_minus = ~go_plus & (minus > cur)
        ry[act] = np.where(go_plus, cand[:m], np.where(go_minus, cand[m:], ry[act]))
        best[act] = np.where(go_plus, plus, np.where(go_minus, minus, cur))
        step[act] = np.where(go_plus | go_minus, step[act], step[act] / 2.0)
    return geometry.wrap_angle(ry)


def reference_nms(boxes, scores, threshold):
    """Greedy NMS over the full IoU matrix, as it was."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    if order.size == 0:
        return order.astype(np.int64)
    iou = nms_module.box_iou_matrix(boxes[order], boxes[order])
    suppressed = np.zeros(order.size, bool)
    keep = []
    for i in range(order.size):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > threshold
    return order[np.asarray(keep, np.int64)]


def detections(rng, n, odd=True):
    """Car-like detections and network-like 2D boxes (another yaw, jittered); with ``odd``
    also boxes straddling the near plane, behind the camera, off the image and NaN boxes."""
    loc = np.stack([rng.uniform(-20, 20, n), rng.uniform(0.5, 2.5, n), rng.uniform(2, 70, n)], 1)
    dims = np.stack([rng.uniform(1.2, 2.0, n), rng.uniform(0.5, 2.0, n), rng.uniform(0.6, 5, n)], 1)
    ry = rng.uniform(-np.pi, np.pi, n)
    boxes = hc.projected_box(loc, dims, ry + rng.normal(0, 0.6, n), P2, SIZE)
    boxes = boxes + rng.normal(0, 4, boxes.shape)
    if odd and n >= 8:
        loc[0] = [1.0, 1.6, 1.0]  # straddles the near plane
        loc[1] = [0.5, 1.6, -3.0]  # behind the camera
        loc[2] = [45.0, 1.6, 8.0]  # off the image
        boxes[3] = np.nan
        boxes[4] = [600, 150, 600, 150]  # empty box
        loc[5, 2] = 0.1 + 1e-12  # a corner near the near plane
        boxes[6] = [0, 0, SIZE[1], SIZE[0]]
    return boxes, loc, dims, ry


@pytest.mark.parametrize("seed", range(8))
def test_hill_climbing_equals_the_reference_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for n in (0, 1, 3, 17, 120, 700):
        boxes, loc, dims, ry = detections(rng, n)
        got = hc.optimize_rotation_y_batch(boxes, loc, dims, ry, P2, SIZE)
        want = reference_hill_climbing(boxes, loc, dims, ry, P2, SIZE)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == want.dtype == np.float64


def test_hill_climbing_objective_equals_consistency_iou_bit_for_bit():
    rng = np.random.default_rng(11)
    boxes, loc, dims, ry = detections(rng, 300)
    objective = hc.consistency_objective(boxes, loc, dims, P2, SIZE)
    rows = rng.integers(0, 300, 2000)
    yaw = rng.uniform(-4, 4, 2000)
    got = objective(rows, yaw)
    want = hc.consistency_iou(boxes[rows], loc[rows], dims[rows], yaw, P2, SIZE)
    np.testing.assert_array_equal(got, want)
    # Both the 8-corner path (all in front) and the near-plane path are exercised.
    front = objective(rows[loc[rows, 2] > 10], yaw[loc[rows, 2] > 10])
    np.testing.assert_array_equal(front, want[loc[rows, 2] > 10])


def test_hill_climbing_equals_the_reference_on_real_labels(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    rng = np.random.default_rng(0)
    for i in range(len(src)):
        s = src[i]
        objs = s["objects"].select(s["objects"].type != "DontCare")
        size = s["image"].shape[:2]
        box = hc.projected_box(objs.location, objs.dimensions, objs.rotation_y, s["P2"], size)
        box = box + rng.normal(0, 2, box.shape)
        start = objs.rotation_y + rng.normal(0, 0.4, len(objs))
        args = (box, objs.location, objs.dimensions, start, s["P2"], size)
        np.testing.assert_array_equal(
            hc.optimize_rotation_y_batch(*args), reference_hill_climbing(*args)
        )


@pytest.mark.parametrize("block", [1, 3, 256])
@pytest.mark.parametrize("threshold", [0.0, 0.5, 0.7, 1.0])
def test_blocked_nms_equals_the_full_matrix(block, threshold):
    rng = np.random.default_rng(int(threshold * 10) + block)
    for n in (0, 1, 2, 40, 300, 1100):
        centres = rng.uniform(0, 1280, (n, 2))
        centres = np.where(rng.random((n, 1)) < 0.5, np.round(centres / 100) * 100, centres)
        size = rng.uniform(5, 250, (n, 2))
        boxes = np.concatenate([centres - size / 2, centres + size / 2], axis=1)
        boxes[rng.random(n) < 0.1] = 0.0  # zero-area boxes
        scores = rng.choice([0.2, 0.5, 0.9], n) if n % 2 else rng.random(n)  # ties / none
        got = nms_module.nms(boxes, scores, threshold, block=block)
        want = reference_nms(boxes, scores, threshold)
        np.testing.assert_array_equal(got, want)
        assert got.dtype == np.int64


def test_normalize_and_decode_equal_the_reference(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    mean, std = np.float32(tf.IMAGENET_MEAN), np.float32(tf.IMAGENET_STD)
    chain = tf.Compose([tf.CropTop(100), tf.Resize(288), tf.CropOrPadWidth(1280)])
    for i in range(len(src)):
        path = src.layout.image(src.frame_ids[i])
        bgr = cv2.imdecode(np.frombuffer(read_bytes(path), np.uint8), cv2.IMREAD_COLOR)
        np.testing.assert_array_equal(read_image(path), cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        image = chain(src[i])["image"]  # a column-cropped view, as in the eval chain
        want = ((np.asarray(image, np.float32) / np.float32(255.0) - mean) / std).astype(np.float32)
        got = tf.Normalize()({"image": image})["image"]
        assert got.dtype == np.float32 and got.shape == want.shape
        np.testing.assert_array_equal(got, want)


def test_postprocess_writes_the_reference_result_text(monkeypatch):
    """Whole host post-processing on dense random candidates (thousands through NMS and the
    hill climbing), multi-class and class-aware too: the same KITTI result text."""
    rng = np.random.default_rng(5)
    k = 4096
    boxes, loc, dims, _ = detections(rng, k, odd=False)
    boxes = np.clip(boxes, -20, 1300)
    depth = loc[:, 2] + P2[2, 3]
    uv = geometry.project(loc - np.stack([0 * dims[:, 0], dims[:, 0] / 2, 0 * dims[:, 0]], 1), P2)
    cand = {
        "scores": np.sort(rng.random(k).astype(np.float32))[::-1],
        "labels": rng.integers(0, 3, k).astype(np.int32),
        "boxes": boxes.astype(np.float32),
        "center": uv[0].astype(np.float32),
        "depth": depth.astype(np.float32),
        "dims": dims.astype(np.float32),
        "alpha": rng.uniform(-np.pi, np.pi, k).astype(np.float32),
    }
    transform = np.array([[1.03, 0, 0.015], [0, 1.03, -103.0], [0, 0, 1]])
    classes = ("Car", "Pedestrian", "Cyclist")
    configs = [
        inference.PostprocessConfig(score_threshold=0.05),
        inference.PostprocessConfig(score_threshold=0.3, class_agnostic_nms=False),
        inference.PostprocessConfig(score_threshold=0.0, nms_iou=0.7, hill_climbing_labels=None),
    ]

    def run(config):
        objs = inference.candidates_to_objects(
            cand, P2, transform, SIZE, (375, 1242), classes, config
        )
        return objs, format_label(objs, with_score=True)

    new = [run(c) for c in configs]
    monkeypatch.setattr(nms_module, "nms", lambda b, s, t: reference_nms(b, s, t))
    monkeypatch.setattr(inference, "optimize_rotation_y_batch", reference_hill_climbing)
    old = [run(c) for c in configs]
    for (got, got_text), (want, want_text) in zip(new, old, strict=True):
        assert len(got) > 50
        assert got_text == want_text
        np.testing.assert_array_equal(got.rotation_y, want.rotation_y)
        np.testing.assert_array_equal(got.bbox, want.bbox)


class FailingSource:
    """A source whose frame ``bad`` cannot be read (as a corrupt image would)."""

    def __init__(self, source, bad: int):
        self.source, self.bad = source, bad
        self.layout, self.frame_ids = source.layout, source.frame_ids

    def __len__(self):
        return len(self.source)

    def __getitem__(self, i):
        if i == self.bad:
            raise KittiFormatError(f"frame{i}.png", "not a readable image")
        return self.source[i]


@pytest.fixture(scope="module")
def tiny_detector(tiny_detect3d_workdir):
    from gac_jax.trained.detector import load_detector
    from gac_jax.trained.run_config import load_run_config

    config = load_run_config(tiny_detect3d_workdir)
    return load_detector(tiny_detect3d_workdir, config)


@pytest.mark.parametrize("batch_size, threads", [(1, 1), (1, 2), (3, 1), (3, 2)])
def test_evaluator_overlap_writes_what_the_serial_loop_writes(
    tiny_detector, kitti_object_root, tmp_path, batch_size, threads
):
    from gac_jax.trained.detector import evaluator_for

    source = KittiObjectSource(kitti_object_root, "labeled")
    out = {}
    for overlap in (True, False):
        evaluator = evaluator_for(tiny_detector, source, batch_size)
        evaluator.overlap_io, evaluator.io_threads = overlap, threads
        folder = tmp_path / f"overlap_{overlap}"
        objects, timings = evaluator.predict_split(tiny_detector.variables, folder)
        assert list(objects) == source.frame_ids and timings["num_frames"] == len(source)
        assert len(evaluator.batch_timings) == -(-len(source) // batch_size)
        texts = {p.name: p.read_text() for p in sorted(folder.glob("*.txt"))}
        assert len(texts) == len(source) and sum(len(o) for o in objects.values()) > 0
        out[overlap] = objects, texts, dict(evaluator.candidate_counts)
    assert out[True][1] == out[False][1]
    assert out[True][2] == out[False][2]
    for fid, obj in out[True][0].items():
        assert format_label(obj, True) == format_label(out[False][0][fid], True)


@pytest.mark.parametrize("overlap, threads", [(True, 1), (True, 2), (False, 1)])
def test_evaluator_errors_surface_as_in_the_serial_loop(
    tiny_detector, kitti_object_root, tmp_path, overlap, threads
):
    from gac_jax.trained.detector import evaluator_for

    source = FailingSource(KittiObjectSource(kitti_object_root, "labeled"), bad=2)
    evaluator = evaluator_for(tiny_detector, source, 1)
    evaluator.overlap_io, evaluator.io_threads = overlap, threads
    with pytest.raises(KittiFormatError, match="frame2.png"):
        evaluator.predict_split(tiny_detector.variables, tmp_path / "data")
    # The frames before the unreadable one were predicted and their files written.
    assert sorted(p.stem for p in (tmp_path / "data").glob("*.txt")) == source.frame_ids[:2]

    blocked = tmp_path / "blocked"
    blocked.write_text("a file where the result folder should be")
    evaluator = evaluator_for(tiny_detector, source.source, 1)
    evaluator.overlap_io = overlap
    with pytest.raises(OSError):
        evaluator.predict_split(tiny_detector.variables, blocked / "data")


def reference_format_label(objects, with_score):
    """The result-file text as it was formatted, field by field."""
    lines = []
    for i in range(len(objects)):
        x1, y1, x2, y2 = objects.bbox[i]
        h, w, l = objects.dimensions[i]
        x, y, z = objects.location[i]
        line = (
            f"{objects.type[i]} {objects.truncated[i]:.2f} {int(objects.occluded[i])} "
            f"{objects.alpha[i]:.6f} {x1:.2f} {y1:.2f} {x2:.2f} {y2:.2f} "
            f"{h:.6f} {w:.6f} {l:.6f} {x:.6f} {y:.6f} {z:.6f} {objects.rotation_y[i]:.6f}"
        )
        if with_score:
            line += f" {objects.score[i]:.6f}"
        lines.append(line)
    return "".join(line + "\n" for line in lines)


@pytest.mark.parametrize("with_score", [True, False])
def test_result_text_equals_the_reference(with_score):
    from gac_jax.data.kitti import KittiObjects

    rng = np.random.default_rng(3)
    for n in (0, 1, 7, 500):
        special = rng.choice([1.0, 1e-9, 0.0, -0.0, -1e-9, np.nan, np.inf, -np.inf], (n, 1))
        objects = KittiObjects.from_arrays(
            type=rng.choice(["Car", "Pedestrian", "DontCare"], n),
            truncated=rng.uniform(-1, 1, n),
            occluded=rng.integers(-1, 4, n),
            alpha=rng.normal(0, 3, n) * special[:, 0],
            bbox=rng.normal(0, 500, (n, 4)) * special,
            dimensions=rng.uniform(0, 5, (n, 3)),
            location=rng.normal(0, 30, (n, 3)) * special,
            rotation_y=rng.normal(0, 2, n),
            score=rng.random(n) * special[:, 0],
        )
        text = format_label(objects, with_score)
        assert text == reference_format_label(objects, with_score)
        assert text.count("\n") == n
