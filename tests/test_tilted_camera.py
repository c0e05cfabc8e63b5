"""A camera pitched down by 20 degrees (the authors' issue #69: every anchor filtered out) with
its KITTI ``planes/`` files: training and prediction keep a sane share of anchors, the cars'
anchors among them, and draw detections. (That a level y band drops objects on such a road is
shown in tests/test_anchor_filter.py; here the priors come from the tilted frames themselves,
all close by, so the band would keep every anchor with a valid prior.)"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gac_jax.builders import detect3d as det_builders
from gac_jax.config import apply_overrides, load_config
from gac_jax.data.loader import DetectionArrays, Loader
from gac_jax.data.sources import open_object_source
from gac_jax.detection.anchor_filter import ground_mask_from_constants
from gac_jax.detection.anchor_priors import make_detection_constants
from gac_jax.detection.anchors import box_iou_np, generate_anchors
from gac_jax.trainers import detect3d
from tests.tilted_frames import write_tilted_root

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tilted_run(tmp_path_factory):
    root = write_tilted_root(tmp_path_factory.mktemp("tilted_kitti"), 6)
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(
        config,
        [
            "data.source=kitti",
            f"data.root={root}",
            "data.train_split=all",
            "data.val_split=all",
            "data.use_right_image=False",
            "data.crop_top=0",  # pitched 20 degrees down: the top rows are road, not sky
            "train.num_steps=3",
            "eval.score_threshold=0.0",
            "eval.num_pictures=2",
        ],
    )
    workdir = tmp_path_factory.mktemp("tilted_run")
    return config, workdir, detect3d.train_and_evaluate(config, workdir)


def test_tilted_frames_train_predict_and_draw(tilted_run):
    config, workdir, out = tilted_run
    assert out["num_frames"] == 6
    results = sorted((workdir / "results" / "step_3" / "data").glob("*.txt"))
    assert len(results) == 6 and sum(len(p.read_text().splitlines()) for p in results) > 0
    assert list(workdir.rglob("grid.png"))  # detections drawn


def test_the_plane_filter_keeps_the_cars_anchors_and_drops_others(tilted_run):
    config, workdir, _ = tilted_run
    layout = det_builders.anchor_layout(config)
    priors = det_builders.compute_priors(config, Path(config.data.root), layout, workdir)  # cached
    constants = make_detection_constants(generate_anchors(layout), priors)
    source = open_object_source(config.data.root, "all")
    arrays = DetectionArrays(("Car",), 32, True, config.model.gac.camera_height)
    transform = det_builders.eval_transform(config)
    loader = Loader(source, transform, arrays, batch_size=6, shuffle=False)
    batch = loader.load_batch(0)
    assert np.all(batch["plane"][:, 2] < -0.3)  # the files' pitched planes reached the batch
    options = det_builders.filter_options(config)
    kept = np.asarray(ground_mask_from_constants(constants, batch["P2"], batch["plane"], **options))
    valid = np.asarray(constants.prior_valid).any(axis=0)
    assert not (kept & ~valid).any()
    assert 0.1 * valid.mean() < kept.mean() < 0.8 * valid.mean(), (kept.mean(), valid.mean())
    # the anchors that match a car (IoU > 0.5) survive the plane's filter
    boxes = np.asarray(constants.anchor_boxes)
    matched = kept_matched = 0
    for b in range(len(kept)):
        gt = batch["gt_boxes"][b][batch["gt_mask"][b]]
        if len(gt):
            hit = (box_iou_np(boxes, gt).max(axis=1) > 0.5) & valid
            matched += hit.sum()
            kept_matched += (hit & kept[b]).sum()
    assert matched > 0 and kept_matched >= 0.8 * matched, (kept_matched, matched)
