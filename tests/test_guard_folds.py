"""The accuracy guard's fold spread and verdict (gac_jax.guard.ap_resampling) on real KITTI
labels: folds partition the frames, identical runs are "within", a run that lost detections
is "beyond", and the verdict's 2-standard-error boundaries by hand."""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path

import numpy as np
import pytest

from gac_jax.data.kitti import read_label, read_split, write_label
from gac_jax.evaluation.kitti_object import evaluate_detections

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def guard_folds():
    return importlib.import_module("gac_jax.guard.ap_resampling")


def _as_results(labels, out: Path, ids, keep=lambda i: True):
    """Ground truth written as result files (the cars only, distinct scores: the devkit's
    recall thresholds need them), frames failing ``keep`` without detections."""
    out.mkdir()
    scores = iter(np.linspace(0.99, 0.5, 1000))
    for frame_id, objects in zip(ids, labels, strict=True):
        cars = objects.type == "Car"
        cars = cars if keep(frame_id) else np.zeros_like(cars)
        picked = {f.name: getattr(objects, f.name)[cars] for f in dataclasses.fields(objects)}
        picked["score"] = np.array([next(scores) for _ in range(int(cars.sum()))])
        write_label(out / f"{frame_id}.txt", type(objects)(**picked), with_score=True)
    return out


def test_folds_partition_the_frames(guard_folds):
    ids = [f"{i:06d}" for i in range(13)]
    parts = guard_folds.folds(ids, 4)
    assert sorted(sum(parts, [])) == ids and sorted(len(p) for p in parts) == [3, 3, 3, 4]
    assert parts == guard_folds.folds(ids, 4)  # fixed permutation
    assert parts != guard_folds.folds(ids, 4, seed=1)
    with pytest.raises(ValueError, match="folds"):
        guard_folds.folds(ids, 14)


def test_identical_runs_are_within_and_lost_detections_beyond(
    guard_folds, kitti_samples_full, tmp_path
):
    root = kitti_samples_full / "object"
    ids = read_split(root / "ImageSets" / "labeled.txt")
    labels = [read_label(root / "training" / "label_2" / f"{i}.txt") for i in ids]
    ref = _as_results(labels, tmp_path / "ref", ids)
    same = _as_results(labels, tmp_path / "same", ids)
    half = _as_results(labels, tmp_path / "half", ids, keep=lambda i: int(i) % 2 == 0)
    res = guard_folds.fold_differences(
        root / "training" / "label_2", ref, {"same": same, "half": half}, ids, 3, tol=0.5
    )
    assert res["frames"] == len(ids) and sum(res["fold_frames"]) == len(ids)
    reference = [read_label(ref / f"{i}.txt", with_score=True) for i in ids]
    ap_ref = evaluate_detections(labels, reference, classes=("Car",))["ap40"]["Car"]["0.70"]
    # the labels as detections: every car found (R40 of 13 frames: min(n_gt, 40) / 40)
    assert res["reference"]["Car 0.70 3d moderate"] == pytest.approx(ap_ref["3d"][1])
    assert ap_ref["3d"][1] > 40
    s = res["runs"]["same"]
    assert s["verdict"] == "within"
    assert all(v["diff"] == 0 and v["fold_std"] == 0 for v in s["entries"].values())
    h = res["runs"]["half"]
    assert h["verdict"] == "beyond"
    # the all-frames difference is the evaluator's on the reduced result set
    kept = [read_label(half / f"{i}.txt", with_score=True) for i in ids]
    direct = evaluate_detections(labels, kept, classes=("Car",))["ap40"]["Car"]["0.70"]["3d"][1]
    assert h["entries"]["Car 0.70 3d moderate"]["diff"] == pytest.approx(direct - ap_ref["3d"][1])
    assert direct < ap_ref["3d"][1] - 10
    e = h["entries"]["Car 0.70 3d moderate"]
    assert len(e["fold_diffs"]) == 3 and e["se"] == pytest.approx(e["fold_std"] / np.sqrt(3))


def test_verdict_boundaries(guard_folds):
    def entries(*pairs):
        return {f"e{i}": {"diff": d, "se": se} for i, (d, se) in enumerate(pairs)}

    v = guard_folds.verdict
    assert v(entries((0.1, 0.1), (-0.2, 0.15)), 0.5) == {"verdict": "within", "worst_entry": "e1"}
    assert v(entries((0.1, 0.1), (0.3, 0.15)), 0.5)["verdict"] == "undecided"  # 0.3 + 0.3
    assert v(entries((0.9, 0.1), (-1.4, 0.4)), 0.5) == {"verdict": "beyond", "worst_entry": "e0"}
    assert v(entries((-1.2, 0.4)), 0.5)["verdict"] == "undecided"  # 1.2 - 0.8 < 0.5
    # a bootstrap's percentile interval decides where an entry has one (skewed: -1.2 with
    # se 0.4 but every resample below -0.6 is beyond; one inside [-0.5, 0.5] within)
    skewed = {"a": {"diff": -1.2, "se": 0.4, "ci95": [-1.9, -0.6]}}
    assert v(skewed, 0.5) == {"verdict": "beyond", "worst_entry": "a"}
    inside = {"a": {"diff": 0.1, "se": 0.3, "ci95": [-0.2, 0.45]}}
    assert v(inside, 0.5)["verdict"] == "within"


def test_paired_bootstrap(guard_folds, kitti_samples_full, tmp_path):
    """The bootstrap's all-frames difference is the folds' (the evaluator on all frames), an
    identical run has zero spread, a run that lost every other frame's cars a positive one,
    and the resamples are a fixed draw of the seed."""
    root = kitti_samples_full / "object"
    ids = read_split(root / "ImageSets" / "labeled.txt")
    label_dir = root / "training" / "label_2"
    labels = [read_label(label_dir / f"{i}.txt") for i in ids]
    ref = _as_results(labels, tmp_path / "ref", ids)
    same = _as_results(labels, tmp_path / "same", ids)
    half = _as_results(labels, tmp_path / "half", ids, keep=lambda i: int(i) % 2 == 0)
    others = {"same": same, "half": half}
    boot = guard_folds.bootstrap_differences(label_dir, ref, others, ids, 20, tol=0.5)
    folded = guard_folds.fold_differences(label_dir, ref, others, ids, 3, tol=0.5)
    assert boot["resamples"] == 20 and boot["frames"] == len(ids)
    assert boot["reference"] == folded["reference"]
    s = boot["runs"]["same"]
    assert s["verdict"] == "within"
    assert all(
        v["diff"] == v["se"] == v["median"] == 0 and v["ci95"] == [0, 0]
        for v in s["entries"].values()
    )
    h = boot["runs"]["half"]["entries"]["Car 0.70 3d moderate"]
    assert h["diff"] == folded["runs"]["half"]["entries"]["Car 0.70 3d moderate"]["diff"]
    assert h["se"] > 0 and h["ci95"][0] <= h["median"] <= h["ci95"][1] < 0  # all lost AP
    # decided by the percentile interval: every resample lost more than 0.5 AP (13 frames:
    # the differences are skewed, diff - 2 se would reach past zero)
    assert boot["runs"]["half"]["verdict"] == "beyond"
    again = guard_folds.bootstrap_differences(label_dir, ref, {"half": half}, ids, 20, tol=0.5)
    assert again["runs"]["half"]["entries"] == boot["runs"]["half"]["entries"]
    with pytest.raises(ValueError, match="resamples"):
        guard_folds.bootstrap_differences(label_dir, ref, others, ids, 1, tol=0.5)
