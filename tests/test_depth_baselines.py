"""The row-mean depth baseline: fitted statistics against a float64 loop, rows counted from
the bottom, and end to end through ``evaluate.py`` on the real KITTI-depth frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gac_jax.cli import evaluate as cli
from gac_jax.data.files import KittiFormatError, read_depth_png
from gac_jax.evaluation.depth_baselines import RowMeanPredictor, fit_row_log_depth
from gac_jax.evaluation.depth_evaluator import prediction_relpath

DRIVE = "2011_09_26_drive_0001_sync"


def _sparse_depth(rng, h, w, empty_rows=()):
    z = rng.uniform(2.0, 80.0, (h, w)) * (rng.random((h, w)) < 0.3)
    z[list(empty_rows)] = 0.0
    return z


def _loop_reference(maps):
    """Per row from the bottom: mean log of valid values, nearest filled row elsewhere."""
    height = max(m.shape[0] for m in maps)
    values = [[] for _ in range(height)]
    for m in maps:
        for v in range(m.shape[0]):
            r = m.shape[0] - 1 - v
            values[r] += list(np.log(m[v][m[v] > 0]))
    filled = [r for r in range(height) if values[r]]
    out = []
    for r in range(height):
        nearest = min(filled, key=lambda f: (abs(f - r), f))
        out.append(sum(values[nearest]) / len(values[nearest]))
    return np.array(out)


def test_fit_matches_a_float64_loop_over_images_of_different_heights():
    rng = np.random.default_rng(0)
    # Two heights (KITTI drives have 370-376 rows); the top rows of the taller image and a
    # band of rows in both images have no valid pixel.
    maps = [
        _sparse_depth(rng, 12, 9, empty_rows=(0, 1, 5, 6)),
        _sparse_depth(rng, 10, 7, empty_rows=(3, 4)),
    ]
    source = [{"depth": m} for m in maps]
    fitted = fit_row_log_depth(source)
    assert fitted.shape == (12,) and fitted.dtype == np.float64
    np.testing.assert_allclose(fitted, _loop_reference(maps), rtol=1e-12)
    # Rows 5 and 6 from the bottom (image rows 6, 5 / 4, 3) are empty in both, rows 10 and 11
    # exist only in the taller image and are empty there: each takes its nearest filled row.
    assert fitted[5] == fitted[4] and fitted[6] == fitted[7]
    assert fitted[10] == fitted[11] == fitted[9]


def test_fit_refuses_a_split_without_valid_pixels():
    with pytest.raises(KittiFormatError, match="no valid ground-truth pixel"):
        fit_row_log_depth([{"depth": np.zeros((4, 5))}])


def test_predictor_counts_rows_from_the_bottom_and_repeats_the_top():
    predictor = RowMeanPredictor(np.log([10.0, 20.0, 30.0]))
    batch = {"original_size": np.array([[5, 2], [2, 3]])}
    tall, short = predictor(batch)
    assert tall.shape == (5, 2) and short.shape == (2, 3) and tall.dtype == np.float32
    np.testing.assert_allclose(tall[:, 0], [30, 30, 30, 20, 10], rtol=1e-6)
    np.testing.assert_allclose(short[:, 2], [20, 10], rtol=1e-6)


def test_row_mean_baseline_end_to_end_on_the_real_frame(kitti_samples, tmp_path):
    depth_root = kitti_samples / "depth"
    out, report = tmp_path / "pred", tmp_path / "r.json"
    code = cli.main(
        ["--task", "depth", "--baseline", "row-mean", "--data", str(depth_root), "--split"]
        + ["train", "--out", str(out), "--json", str(report)]
    )
    assert code == 0
    result = json.loads(report.read_text())
    assert result["baseline"] == {"name": "row-mean", "fitted_on": "train", "fitted_frames": 2}
    assert result["num_scored"] == 2 and np.isfinite(result["metrics"]["silog"])
    # Fitted on the frame's two cameras: every written row is their rows' geometric mean.
    gts = [
        read_depth_png(depth_root / "data_depth_annotated" / "train" / prediction_relpath(f, c))
        for f, c in [(f"{DRIVE}/0000000005", 2), (f"{DRIVE}/0000000005", 3)]
    ]
    expected = np.exp(_loop_reference(gts))[::-1]
    pred = read_depth_png(out / prediction_relpath(f"{DRIVE}/0000000005", 2))
    assert pred.shape == gts[0].shape and np.all(pred == pred[:, :1])
    np.testing.assert_array_less(np.abs(pred[:, 0] - np.minimum(expected, 255.0)), 1 / 512 + 1e-3)
