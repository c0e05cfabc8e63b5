"""The paired frame bootstrap of AP (gac_jax.guard.ap_bootstrap) against the evaluator.

Resampled AP is computed from per-frame pieces; with every frame once it must give exactly
the evaluator's numbers, and with any resample's counts the evaluator's numbers on the frames
repeated that often (real KITTI labels: DontCare areas, vans, small and occluded objects)."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.kitti import read_label, read_split
from gac_jax.evaluation.kitti_object import DIFFICULTIES, DetectionEvalSet, evaluate_detections
from gac_jax.guard import ap_bootstrap
from tests.test_detector_rule import label_detections


@pytest.fixture(scope="module")
def labelled(kitti_object_root):
    ids = read_split(kitti_object_root / "ImageSets" / "labeled.txt")
    gts = [read_label(kitti_object_root / "training" / "label_2" / f"{i}.txt") for i in ids]
    rng = np.random.default_rng(4)
    return gts, label_detections(gts, rng, 0.6), label_detections(gts, rng, 0.6)


def _evaluator_entries(result: dict, cls: str = "Car") -> dict[str, float]:
    """The evaluator's entries under the bootstrap's names."""
    out = {}
    for points in ("11", "40"):
        for key, entry in result[f"ap{points}"][cls].items():
            for metric, values in entry.items():
                name = {"bbox": "2d@0.70", "aos": "aos"}.get(metric, f"{metric}@{key}")
                for difficulty, v in zip(DIFFICULTIES, values, strict=True):
                    out[f"{cls} AP{points} {name} {difficulty}"] = v
    return out


def test_every_frame_once_is_the_evaluator_and_a_resample_is_the_repeated_frames(labelled):
    gts, dts, _ = labelled
    result = ap_bootstrap.paired_ap_bootstrap(gts, dts, dts, resamples=2)
    expected = _evaluator_entries(evaluate_detections(gts, dts, classes=("Car",)))
    assert set(result) == set(expected) and len(expected) == 36
    for name, v in expected.items():
        assert result[name]["reference"] == pytest.approx(v, abs=1e-9), name
        assert result[name]["diff"] == result[name]["se"] == result[name]["bias"] == 0.0
    evalset = DetectionEvalSet(gts, dts)
    counts = np.random.default_rng(0).multinomial(len(gts), np.full(len(gts), 1 / len(gts)))
    frames = np.repeat(np.arange(len(gts)), counts)
    again = _evaluator_entries(
        evaluate_detections([gts[i] for i in frames], [dts[i] for i in frames], ("Car",))
    )
    for d, difficulty in enumerate(DIFFICULTIES):
        for name, metric, thr in ap_bootstrap.curves("Car"):
            pieces = ap_bootstrap.curve_pieces(evalset, "Car", d, metric, thr)
            got = ap_bootstrap.curve_ap(pieces, counts, metric == "bbox")
            for points in ("11", "40"):
                assert got[f"ap{points}"] == pytest.approx(
                    again[f"Car AP{points} {name} {difficulty}"], abs=1e-9
                )
                if metric == "bbox":
                    assert got[f"aos{points}"] == pytest.approx(
                        again[f"Car AP{points} aos {difficulty}"], abs=1e-9
                    )


def test_two_runs_differ_by_their_ap_with_a_bootstrap_spread(labelled):
    gts, ref, cand = labelled
    result = ap_bootstrap.paired_ap_bootstrap(gts, ref, cand, resamples=30, seed=1)
    a = _evaluator_entries(evaluate_detections(gts, ref, classes=("Car",)))
    b = _evaluator_entries(evaluate_detections(gts, cand, classes=("Car",)))
    for name, row in result.items():
        assert row["diff"] == pytest.approx(b[name] - a[name], abs=1e-9)
    assert any(row["se"] > 0 for row in result.values())
    assert result == ap_bootstrap.paired_ap_bootstrap(gts, ref, cand, resamples=30, seed=1)
    with pytest.raises(ValueError, match="at least 2 bootstrap resamples"):
        ap_bootstrap.paired_ap_bootstrap(gts, ref, cand, resamples=1)
