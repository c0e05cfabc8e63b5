"""The depth evaluator: back to the original geometry, 16-bit PNGs, resume, the ground-plane
baseline, agreement with the offline scorer; on the real KITTI-depth frame of ``../shared``."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.cli import evaluate as cli
from gac_jax.data import transforms
from gac_jax.data.files import read_depth_png, write_png
from gac_jax.data.kitti_calib import read_calib
from gac_jax.data.sources import KittiDepthSource, new_sample
from gac_jax.evaluation.depth_evaluator import (
    BASELINE_MAX_DEPTH,
    DepthEvaluator,
    GroundPlanePredictor,
    ground_plane_depth,
    prediction_relpath,
    quantize_depth,
    to_original_geometry,
)
from gac_jax.evaluation.depth_metrics import DepthMetricAccumulator

DRIVE = "2011_09_26_drive_0001_sync"


@pytest.fixture(scope="module")
def depth_root(kitti_samples) -> Path:
    return kitti_samples / "depth"


@pytest.fixture(scope="module")
def P2(depth_root) -> np.ndarray:
    return read_calib(depth_root / "raw" / "2011_09_26" / "calib_cam_to_cam.txt").P2


def _linear_log_depth(u, v):
    return 2.0 + 0.001 * u + 0.002 * v


@pytest.mark.parametrize(
    "ops",
    [
        # the paper's test view of a 375x1242 frame: bottom 352 rows, left 1216 columns
        [transforms.CropBottomTo(352), transforms.CropOrPadWidth(1216)],
        # the default config's: resized to 96 rows, zero-padded to 352 columns
        [transforms.CropBottomTo(352), transforms.Resize(96), transforms.CropOrPadWidth(352)],
    ],
)
def test_to_original_geometry_inverts_the_test_view(ops, P2):
    H0, W0 = 375, 1242
    sample = new_sample("x", 2, np.zeros((H0, W0, 3), np.uint8), P2)
    out = transforms.Compose(ops)(sample)
    A = out["image_transform"]
    h, w = out["image"].shape[:2]
    # The network map of a log-depth linear in ORIGINAL pixels (float64 reference).
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float64)
    inv = np.linalg.inv(A)
    net = _linear_log_depth(inv[0, 0] * uu + inv[0, 2], inv[1, 1] * vv + inv[1, 2])
    depth = to_original_geometry(net.astype(np.float32), A, (H0, W0))
    assert depth.shape == (H0, W0) and depth.dtype == np.float32
    v0, u0 = np.mgrid[0:H0, 0:W0].astype(np.float64)
    expected = np.exp(_linear_log_depth(u0, v0))
    # Inside the network's view (and its resized content) the linear map comes back exactly.
    un, vn = A[0, 0] * u0 + A[0, 2], A[1, 1] * v0 + A[1, 2]
    content_w = min(w - 1, A[0, 0] * (W0 - 1) + A[0, 2])
    inside = (vn >= 0) & (vn <= h - 1) & (un >= 0) & (un <= content_w)
    assert inside.mean() > 0.9
    np.testing.assert_allclose(depth[inside], expected[inside], rtol=2e-5)
    # Rows above the crop (and at its top edge) all replicate the network's first row; the
    # columns right of the network's width its last column.
    top = vn[:, 0] <= 0
    assert top.sum() >= 23
    np.testing.assert_array_equal(depth[top], np.broadcast_to(depth[top][0], depth[top].shape))
    right = un[0] >= w - 1
    assert right.sum() == (W0 - w + 1 if A[0, 0] == 1 else 0)  # 1242 - 1216 + 1 for the crop
    col = depth[:, right]
    np.testing.assert_array_equal(col, np.broadcast_to(col[:, :1], col.shape))


def test_to_original_geometry_rejects_rotations():
    A = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="axis-aligned"):
        to_original_geometry(np.zeros((4, 4), np.float32), A, (4, 4))


def test_quantize_depth_is_the_kitti_format():
    d = np.array([0.0, 1e-6, 1 / 256, 0.3, 12.3456, 1e6, np.nan, np.inf], np.float64)
    q = quantize_depth(d)
    assert q.dtype == np.uint16
    assert q.tolist() == [1, 1, 1, 77, 3160, 65535, 65535, 65535]
    z = np.random.default_rng(0).uniform(0.5, 200.0, 1000)
    np.testing.assert_array_less(np.abs(quantize_depth(z) / 256.0 - z), 1 / 512 + 1e-12)


def test_prediction_paths_mirror_the_ground_truth():
    assert prediction_relpath(f"{DRIVE}/0000000005", 3) == Path(
        f"{DRIVE}/proj_depth/groundtruth/image_03/0000000005.png"
    )
    stem = f"{DRIVE}_image_0000000005_image_02"
    assert prediction_relpath(stem, 2) == Path(f"{stem}.png")


def test_ground_plane_baseline_is_the_ground_depth_of_each_row(P2):
    H, W = 375, 1242
    z = ground_plane_depth(P2, (H, W))
    assert z.shape == (H, W) and np.all(z == z[:, :1])
    v = np.arange(H)
    ref = geometry.ground_depth(v, P2, 1.65)
    below = np.isfinite(ref) & (ref < BASELINE_MAX_DEPTH)
    assert below.sum() > 150  # KITTI: the horizon is near row 173
    np.testing.assert_allclose(z[below, 0], ref[below], rtol=1e-6)
    # Hand formula for a KITTI P (translation terms included), float64.
    fy, cy, ty, tz = P2[1, 1], P2[1, 2], P2[1, 3], P2[2, 3]
    hand = (fy * 1.65 + ty - v * tz) / (v - cy)
    np.testing.assert_allclose(z[below, 0], hand[below], rtol=1e-6)  # float32 output
    assert np.all(z[~below, 0] == np.float32(BASELINE_MAX_DEPTH))
    assert np.all(np.diff(z[below, 0]) < 0)  # farther towards the horizon


def test_baseline_evaluation_writes_scores_resumes_and_matches_offline(depth_root, P2, tmp_path):
    source = KittiDepthSource(depth_root, "train", (2, 3))
    view = transforms.Compose([transforms.CropBottomTo(352), transforms.Resize(64)])
    evaluator = DepthEvaluator(source, view, batch_size=2, num_pictures=2)
    out_dir, pic_dir = tmp_path / "pred", tmp_path / "pictures"
    first = evaluator.evaluate(GroundPlanePredictor(), out_dir, pic_dir)
    assert (first["num_frames"], first["num_predicted"], first["num_scored"]) == (2, 2, 2)

    # Written PNGs: full size, the per-row ground depth (to 1/256 m), recovered through A^-1.
    acc = DepthMetricAccumulator()
    for cam in (2, 3):
        rel = prediction_relpath(f"{DRIVE}/0000000005", cam)
        pred = read_depth_png(out_dir / rel)
        gt = read_depth_png(depth_root / "data_depth_annotated" / "train" / rel)
        assert pred.shape == gt.shape == (375, 1242)
        acc.update(pred, gt)
        if cam == 2:
            ref = np.minimum(geometry.ground_depth(np.arange(375), P2), BASELINE_MAX_DEPTH)
            np.testing.assert_array_less(np.abs(pred - ref[:, None]), 1 / 512 + 1e-4)
    assert first["metrics"] == pytest.approx(acc.result(), rel=1e-12)
    pictures = sorted(p.name for p in pic_dir.glob("*.png"))
    assert pictures == [
        f"00000_{DRIVE}_0000000005_image_02.png",
        f"00001_{DRIVE}_0000000005_image_03.png",
    ]

    # Offline mode of evaluate.py scores the folder to the same numbers.
    gt_dir = tmp_path / "gt"
    shutil.copytree(depth_root / "data_depth_annotated" / "train", gt_dir)
    metrics, count = cli.evaluate_depth_folders(gt_dir, out_dir)
    assert count == 2 and metrics == pytest.approx(first["metrics"], rel=1e-12)

    # Resume: nothing predicted again, the same numbers (read back from the PNGs).
    class Failing:
        def __call__(self, batch):
            raise AssertionError("resumed evaluation must not predict")

    again = evaluator.evaluate(Failing(), out_dir)
    assert again["num_predicted"] == 0 and again["metrics"] == first["metrics"]


def test_selection_folder_without_ground_truth_is_written_not_scored(depth_root, P2, tmp_path):
    """The test-server layout: flat image + intrinsics folders, PNGs named as the images."""
    image = cv2.imread(str(depth_root / "raw/2011_09_26" / DRIVE / "image_02/data/0000000005.png"))
    sel = tmp_path / "test_depth_prediction_anonymous"
    stem = "0000000000"
    write_png(sel / "image" / f"{stem}.png", cv2.cvtColor(image[-352:, :1216], cv2.COLOR_BGR2RGB))
    K = P2[:, :3].copy()
    K[1, 2] -= 375 - 352
    (sel / "intrinsics").mkdir(parents=True)
    (sel / "intrinsics" / f"{stem}.txt").write_text(" ".join(f"{x:.6e}" for x in K.ravel()) + "\n")
    out = tmp_path / "submission"
    code = cli.main(
        [
            "--task",
            "depth",
            "--baseline",
            "ground-plane",
            "--data",
            str(sel),
            "--out",
            str(out),
            "--json",
            str(tmp_path / "r.json"),
        ]
    )
    assert code == 0
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["metrics"] == {} and result["num_frames"] == 1 and result["num_scored"] == 0
    pred = read_depth_png(out / f"{stem}.png")
    assert pred.shape == (352, 1216) and pred.min() > 0
    # P has no translation here: the baseline is fy * 1.65 / (v - cy) below the horizon.
    v = np.arange(352)
    ref = np.where(v > K[1, 2], K[1, 1] * 1.65 / np.maximum(v - K[1, 2], 1e-9), np.inf)
    ref = np.minimum(ref, BASELINE_MAX_DEPTH)
    np.testing.assert_array_less(np.abs(pred[:, 0] - ref), 1 / 512 + 1e-4)


def test_cli_reports_a_missing_workdir(tmp_path, capsys):
    assert cli.main(["--task", "depth", "--workdir", str(tmp_path / "nope")]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and "not a training workdir" in err
