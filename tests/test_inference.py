"""Inference path: decoding inverts encoding through crop/resize/flip, hill climbing wiring,
ground truth through the whole path scores 100 AP, compile-once, CPU thread plumbing.

The network is replaced by a fake whose outputs carry the encoded targets of the
real KITTI labels of ``../shared`` on one anchor per object (the anchor of best IoU),
so every number is checked against the labels themselves (float64, independent of
the decoder: 3D boxes from the label file, 2D boxes re-projected through the
original calibration).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.builders.detect3d import anchor_layout, eval_transform
from gac_jax.cli import evaluate as cli
from gac_jax.config import load_config
from gac_jax.data import transforms as tf
from gac_jax.data.kitti import KittiObjectLayout, write_label
from gac_jax.data.loader import collate, detection_arrays
from gac_jax.data.sources import KittiObjectSource
from gac_jax.detection.anchor_priors import DetectionConstants
from gac_jax.detection.anchors import box_iou_np, generate_anchors
from gac_jax.detection.box_coding import encode_np
from gac_jax.detection.hill_climbing import optimize_rotation_y
from gac_jax.detection.inference import (
    PostprocessConfig,
    candidates_to_objects,
    make_predict_fn,
    postprocess,
)
from gac_jax.evaluation.detector_evaluator import InputArrays

REPO = Path(__file__).resolve().parents[1]
CLASSES = ("Car", "Pedestrian", "Cyclist")
EXACT = PostprocessConfig(score_threshold=0.5, nms_iou=1.0, hill_climbing=False)


class FakeDetector:
    """``apply`` returns the outputs passed as ``variables`` (the predict fn's first argument)."""

    def apply(self, variables, images, P2, train, plane=None):
        return variables


@pytest.fixture(scope="module")
def setup():
    """Paper multi-class input geometry (288x1280, 48 anchors per cell), made-up valid priors."""
    config = load_config(str(REPO / "configs" / "detect3d_kitti.py:multiclass"))
    layout = anchor_layout(config)
    anchors = generate_anchors(layout)
    n, k = len(anchors.boxes), len(CLASSES)
    rng = np.random.default_rng(0)
    mean = np.stack(
        [
            rng.uniform(10, 40, (k, n)),
            rng.uniform(-0.3, 0.3, (k, n)),
            rng.uniform(-0.3, 0.3, (k, n)),
        ],
        axis=-1,
    )
    std = np.stack(
        [rng.uniform(3, 15, (k, n)), rng.uniform(0.4, 0.8, (k, n)), rng.uniform(0.4, 0.8, (k, n))],
        axis=-1,
    )
    dims_mean = np.array([[1.5, 1.6, 3.9], [1.75, 0.65, 0.85], [1.7, 0.6, 1.75]])
    dims_std = np.array([[0.15, 0.1, 0.4], [0.1, 0.1, 0.2], [0.1, 0.1, 0.2]])
    constants = DetectionConstants(
        anchor_boxes=jnp.asarray(anchors.boxes, jnp.float32),
        anchor_centers=jnp.asarray(anchors.centers, jnp.float32),
        prior_mean=jnp.asarray(mean, jnp.float32),
        prior_std=jnp.asarray(std, jnp.float32),
        prior_valid=jnp.ones((k, n), bool),
        dims_mean=jnp.asarray(dims_mean, jnp.float32),
        dims_std=jnp.asarray(dims_std, jnp.float32),
        angle_mode="double",
    )
    predict = make_predict_fn(FakeDetector(), constants, top_k=100, use_ground_filter=False)
    return config, constants, predict


def fake_outputs(constants: DetectionConstants, arr: dict, alpha_offset: float = 0.0) -> dict:
    """Network outputs (1, N, ...) whose best-IoU anchor per object encodes that object."""
    m = int(arr["gt_mask"].sum())
    boxes = np.asarray(constants.anchor_boxes, np.float64)
    n, k = boxes.shape[0], constants.num_classes
    iou = box_iou_np(arr["gt_boxes"][:m], boxes)
    chosen = []
    for j in range(m):
        order = np.argsort(-iou[j], kind="stable")
        chosen.append(next(int(a) for a in order if a not in chosen))
    idx, cls = np.array(chosen), arr["gt_class"][:m]
    targets, sign = encode_np(
        boxes[idx],
        arr["gt_boxes"][:m],
        arr["gt_center"][:m],
        arr["gt_depth"][:m],
        arr["gt_dims"][:m],
        arr["gt_alpha"][:m] + alpha_offset,
        np.asarray(constants.prior_mean)[cls, idx],
        np.asarray(constants.prior_std)[cls, idx],
        np.asarray(constants.dims_mean)[cls],
        np.asarray(constants.dims_std)[cls],
    )
    logits = np.full((1, n, k), -20.0, np.float32)
    logits[0, idx, cls] = 8.0 + 0.01 * np.arange(m)  # distinct scores, all > 0.99
    reg = np.zeros((1, n, 12), np.float32)
    reg[0, idx] = targets
    sign_logits = np.full((1, n), -10.0, np.float32)
    sign_logits[0, idx] = np.where(sign > 0.5, 10.0, -10.0)
    return {"cls_logits": logits, "sign_logits": sign_logits, "reg": reg}


def run_frame(setup, sample, extra_transforms=(), alpha_offset=0.0, config=EXACT):
    """Transforms one raw sample, fakes the network, returns (objects, transformed sample, arr)."""
    cfg, constants, predict = setup
    chain = tf.Compose(
        list(eval_transform(cfg, normalize=False).transforms) + list(extra_transforms)
    )
    s = chain(dict(sample))
    arr = detection_arrays(s, CLASSES, max_objects=64)
    cand = predict(
        fake_outputs(constants, arr, alpha_offset), np.zeros((1, 1, 1, 3)), s["P2"][None]
    )
    cand = {key: np.asarray(v)[0] for key, v in cand.items()}
    objects = candidates_to_objects(
        cand,
        s["P2"],
        s["image_transform"],
        s["image"].shape[:2],
        s["original_size"],
        CLASSES,
        config,
    )
    return objects, s, arr, cand


def match(found: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """Index into ``found`` of the point nearest to each expected point (must be one-to-one)."""
    d = np.linalg.norm(found[None, :, :] - expected[:, None, :], axis=-1)
    idx = np.argmin(d, axis=1)
    assert len(set(idx.tolist())) == len(idx)
    return idx


def valid_region(s) -> np.ndarray:
    """Original-image pixels the network input covers, as xyxy (the 2D clip window)."""
    h, w = s["image"].shape[:2]
    h0, w0 = s["original_size"]
    inv = np.linalg.inv(s["image_transform"])
    r = tf.transform_boxes(np.array([[0.0, 0.0, w, h]]), inv)[0]
    return np.array([max(r[0], 0.0), max(r[1], 0.0), min(r[2], w0 - 1.0), min(r[3], h0 - 1.0)])


@pytest.mark.parametrize("flip", [False, True], ids=["eval-transform", "eval-transform+flip"])
def test_decoding_inverts_encoding_through_the_transforms(setup, kitti_object_root, flip):
    source = KittiObjectSource(kitti_object_root, "labeled")
    extra = [tf.HorizontalFlip()] if flip else []
    checked = 0
    for i in range(len(source)):
        sample = source[i]
        gt = sample["objects"].select(np.isin(sample["objects"].type, CLASSES))
        if not len(gt):
            continue
        # The 2D target is the box re-derived from the 3D label through the transformed P2.
        objs, s, arr, _ = run_frame(setup, sample, extra + [tf.ReprojectBoxes()])
        assert len(objs) == len(gt)
        if flip:  # the decoded scene is the mirrored one; mirror it back
            objs = tf.mirror_objects(objs).replace(bbox=objs.bbox)
        j = match(objs.location, gt.location)
        objs = objs.select(j)
        np.testing.assert_allclose(objs.location, gt.location, atol=1e-4)
        np.testing.assert_allclose(objs.dimensions, gt.dimensions, atol=1e-4)
        dry = geometry.wrap_angle(objs.rotation_y - gt.rotation_y)
        np.testing.assert_allclose(dry, 0.0, atol=1e-4)
        np.testing.assert_array_equal(objs.type, gt.type)
        # KITTI alpha of the written result: from ry and the location (reference origin).
        alpha = geometry.alpha_from_rotation_y(gt.rotation_y, gt.location, None)
        np.testing.assert_allclose(geometry.wrap_angle(objs.alpha - alpha), 0.0, atol=1e-4)
        # 2D box in original pixels: the 3D label projected through the ORIGINAL P2, clipped
        # to the part of the original image that the network input covers.
        corners = geometry.box3d_corners(gt.location, gt.dimensions, gt.rotation_y)
        expected = geometry.box2d_from_corners(corners, source[i]["P2"])
        r = valid_region(s)
        expected[:, [0, 2]] = np.clip(expected[:, [0, 2]], r[0], r[2])
        expected[:, [1, 3]] = np.clip(expected[:, [1, 3]], r[1], r[3])
        np.testing.assert_allclose(objs.bbox, expected, atol=2e-3)
        checked += len(gt)
    assert checked >= 15  # of the 19 labelled Car/Pedestrian/Cyclist objects


def test_hill_climbing_refines_only_the_configured_classes(setup, kitti_object_root):
    source = KittiObjectSource(kitti_object_root, "labeled")
    frames = [source[i] for i in range(len(source))]
    frames = [f for f in frames if {"Car", "Pedestrian"} <= set(f["objects"].type)]
    assert frames, "need a frame with cars and pedestrians"
    sample = frames[0]
    offset = 0.25  # a wrong observation angle for every object
    repro = [tf.ReprojectBoxes()]
    plain, s, arr, cand = run_frame(setup, sample, repro, offset, EXACT)
    truth = sample["objects"]
    assert np.isin(plain.type, ["Car"]).sum() >= 2 and np.isin(plain.type, ["Pedestrian"]).any()

    # Reference: the hill climber on each detection alone, from the unrefined yaw, with the
    # network's clipped 2D box in input pixels (the candidates are in score order, as kept).
    h, w = s["image"].shape[:2]
    keep = cand["scores"] > EXACT.score_threshold
    order = np.argsort(-cand["scores"][keep], kind="stable")
    boxes = cand["boxes"][keep][order].astype(np.float64)
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0, w)
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0, h)
    refined = np.array(
        [
            optimize_rotation_y(b, loc, dims, ry, s["P2"], (h, w))
            for b, loc, dims, ry in zip(
                boxes, plain.location, plain.dimensions, plain.rotation_y, strict=True
            )
        ]
    )
    far = plain.location[:, 2] > 3.0
    for labels, refined_types in [
        ((0,), {"Car"}),
        ((0, 1), {"Car", "Pedestrian"}),
        (None, set(CLASSES)),
    ]:
        cfg = PostprocessConfig(score_threshold=0.5, nms_iou=1.0, hill_climbing_labels=labels)
        out, *_ = run_frame(setup, sample, repro, offset, cfg)
        np.testing.assert_allclose(out.location, plain.location, atol=0)  # only the yaw moves
        picked = np.isin(out.type, list(refined_types)) & far
        np.testing.assert_allclose(out.rotation_y[picked], refined[picked], atol=1e-12)
        np.testing.assert_allclose(out.rotation_y[~picked], plain.rotation_y[~picked], atol=1e-12)
        assert picked.any() and (labels != (0,) or (~picked).any())
    # The refinement moves the wrong yaw back towards the labelled one.
    j = match(plain.location, truth.select(np.isin(truth.type, CLASSES)).location)
    truth = truth.select(np.isin(truth.type, CLASSES)).select(j)
    before = np.abs(geometry.wrap_angle(plain.rotation_y - truth.rotation_y))
    after = np.abs(geometry.wrap_angle(refined - truth.rotation_y))
    np.testing.assert_allclose(before, offset, atol=1e-4)
    assert np.median(after[far]) < 0.1


def test_ground_truth_through_the_whole_path_scores_100(setup, kitti_object_root, tmp_path):
    """Labels -> fake network -> predict -> postprocess -> result files -> evaluate.py: 100 AP.

    The devkit samples precision at 41 recall thresholds per valid object, so each
    class/difficulty needs >= 41 objects for a perfect score: the real frames are repeated
    41 times (results and labels under new frame ids).
    """
    cfg, constants, predict = setup
    source = KittiObjectSource(kitti_object_root, "labeled")
    layout = KittiObjectLayout(kitti_object_root)
    chain = eval_transform(cfg)  # the evaluator's chain, with normalisation
    results, labels = tmp_path / "results", tmp_path / "labels"
    labels.mkdir()
    for i, fid in enumerate(source.frame_ids):
        s = chain(source[i])
        arr = detection_arrays(s, CLASSES, max_objects=64)
        m = int(arr["gt_mask"].sum())
        # alpha measured from the transformed camera, as the decoder reads it
        arr["gt_alpha"][:m] = geometry.alpha_from_rotation_y(
            arr["gt_rotation_y"][:m], arr["gt_location"][:m], s["P2"]
        )
        batch = collate([InputArrays()(s)])
        cand = predict(fake_outputs(constants, arr), batch["image"], batch["P2"])
        (objects,) = postprocess(cand, batch, CLASSES, EXACT)
        assert len(objects) == m
        text = layout.label(fid).read_text()
        for r in range(41):
            write_label(results / f"{fid}_{r:02d}.txt", objects, with_score=True)
            (labels / f"{fid}_{r:02d}.txt").write_text(text)
    out = tmp_path / "ap.json"
    code = cli.main(["--task", "detect3d", "--label-dir", str(labels), "--result-dir", str(results),
                     "--json", str(out)])  # fmt: skip
    assert code == 0
    import json

    res = json.loads(out.read_text())
    seen = 0
    for ap in ("ap40", "ap11"):
        for cls in CLASSES:
            for entry in res[ap][cls].values():
                for d in range(3):
                    if entry["bbox"][d] == 0.0:  # no valid object of this class/difficulty
                        continue
                    seen += 1
                    for metric in ("bbox", "bev", "3d"):
                        assert entry[metric][d] == pytest.approx(100.0, abs=1e-9), (cls, d, metric)
                    assert entry["aos"][d] > 99.9  # KITTI's alpha is rounded to 0.01
    assert seen >= 2 * 2 * 6  # Car and Pedestrian, all difficulties, both IoU settings


def test_predict_compiles_once_per_input_shape(setup):
    _, constants, _ = setup
    predict = make_predict_fn(FakeDetector(), constants, top_k=10, use_ground_filter=True)
    n, k = constants.anchor_boxes.shape[0], constants.num_classes
    rng = np.random.default_rng(0)

    def outputs(b):
        return {
            "cls_logits": rng.normal(size=(b, n, k)).astype(np.float32),
            "sign_logits": rng.normal(size=(b, n)).astype(np.float32),
            "reg": rng.normal(size=(b, n, 12)).astype(np.float32),
        }

    P2 = np.array([[721.5, 0, 609.6, 44.9], [0, 721.5, 72.9, 0.2], [0, 0, 1, 0.003]], np.float32)
    images = np.zeros((2, 8, 8, 3), np.float32)
    for pitch in (0.0, 0.1, 0.35):  # per-frame planes are inputs: one trace
        plane = np.float32([[0, -np.cos(pitch), -np.sin(pitch), 1.65], [0, -1, 0, 1.5]])
        out = predict(outputs(2), images, np.stack([P2, P2 * 0.5]), plane)
    assert predict._cache_size() == 1
    assert out["scores"].shape == (2, 10)
    predict(outputs(1), np.zeros((1, 8, 8, 3), np.float32), P2[None], plane[:1])
    assert predict._cache_size() == 2


def test_cpu_thread_count_follows_the_affinity(tmp_path):
    """``limit_cpu_threads(n)`` before JAX starts gives XLA exactly n compute threads."""
    script = textwrap.dedent(
        """
        import sys
        from gac_jax.cli.model_mode import available_cores, limit_cpu_threads, xla_thread_count
        want = None if sys.argv[1] == "all" else int(sys.argv[1])
        n = limit_cpu_threads(want)
        import jax.numpy as jnp
        (jnp.ones((256, 256)) @ jnp.ones((256, 256))).block_until_ready()
        print(n, xla_thread_count(), len(available_cores()))
        try:
            limit_cpu_threads(1 if n > 1 else 2)
            print("no error")
        except ValueError as e:
            print("error:", e)
        """
    )
    env = dict(os.environ, PYTHONPATH=str(REPO))
    runs = {}
    for arg in ("all", "1"):
        proc = subprocess.run(
            [sys.executable, "-c", script, arg],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr[-2000:]
        runs[arg] = proc.stdout.split("\n")
    n_all, threads_all, cores = (int(v) for v in runs["all"][0].split())
    assert n_all == threads_all == cores == len(os.sched_getaffinity(0))
    n1, threads1, cores1 = (int(v) for v in runs["1"][0].split())
    assert n1 == threads1 == cores1 == 1
    assert runs["1"][1].startswith("error:")  # 2 threads asked for, 1 usable core
    if cores > 1:  # once JAX runs, the count cannot change any more
        assert "already runs with" in runs["all"][1]
