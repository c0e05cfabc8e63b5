"""How far an accuracy guard can see: AP differences on disjoint folds of the guard frames.

A guard compares two runs of one model (e.g. jax float32 and OpenVINO int8) on the same
frames. Its AP difference mixes what the precision changes systematically with how much the
AP of a few hundred frames jumps when detections move a little (a 3D IoU crossing 0.7, a
score crossing a recall threshold). This module splits the frames into ``k`` disjoint folds
(fixed permutation), scores both result folders on each fold with the project's KITTI
evaluator and gives, per Car AP|R40 entry:

* ``diff``: the difference on all frames (what the guard reports),
* ``fold_std``: the sample std of the per-fold differences: the spread a guard of one
  fold's size (``N / k`` frames) shows between equally good frame sets,
* ``se``: ``fold_std / sqrt(k)``, the standard error of the all-frames difference,

and a verdict against the tolerance ``tol`` (AP points) at about 95 % (2 standard errors):
``within`` if every entry has ``|diff| + 2 se <= tol``, ``beyond`` if some entry has
``|diff| - 2 se > tol``, else ``undecided`` (the guard set is too small to tell).

AP is not additive over frames (the devkit's recall thresholds and precision envelope are
computed on the pooled detections), so the mean of the fold differences need not equal the
all-frames difference, and ``fold_std / sqrt(k)`` is only a rough standard error of it. The
direct one is :func:`bootstrap_differences`: a *paired frame bootstrap* (resample the frames
with replacement, score both runs on the same resample, ``n`` times); its ``se`` is the sample
std of the resampled all-frames differences, and its verdict uses the resamples' 95 %
percentile interval (AP differences of small sets are skewed). The guard reports
both: the bootstrap decides, the folds say what a guard of one fold's size would see.

Pure file reading and numpy; no JAX.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gac_jax.data.kitti import KittiObjects, read_label
from gac_jax.evaluation.kitti_object import DIFFICULTIES, evaluate_detections

Z = 2.0  # standard errors of the verdict (~95 %)


def car_ap40(metrics: dict) -> dict[str, float]:
    """Every Car AP|R40 entry of an evaluation dict: ``'Car 0.70 3d moderate' -> AP``."""
    out = {}
    for iou, kinds in metrics["ap40"]["Car"].items():
        for kind, values in kinds.items():
            for name, v in zip(DIFFICULTIES, values, strict=True):
                out[f"Car {iou} {kind} {name}"] = float(v)
    return out


def folds(ids: Sequence[str], k: int, seed: int = 0) -> list[list[str]]:
    """``ids`` in ``k`` disjoint folds of near-equal size (a fixed permutation of ``seed``)."""
    if not 2 <= k <= len(ids):
        raise ValueError(f"need 2 <= folds <= {len(ids)} frames, got {k}")
    order = np.random.default_rng(seed).permutation(len(ids))
    return [[ids[i] for i in sorted(part)] for part in np.array_split(order, k)]


def read_results(result_dir: Path, ids: Sequence[str]) -> list[KittiObjects]:
    """Detections per frame of ``ids`` (a frame without a result file has none)."""
    out = []
    for frame_id in ids:
        path = Path(result_dir) / f"{frame_id}.txt"
        out.append(read_label(path, with_score=True) if path.exists() else KittiObjects.empty())
    return out


def fold_differences(
    label_dir: Path,
    reference_dir: Path,
    other_dirs: dict[str, Path],
    ids: Sequence[str],
    k: int,
    tol: float,
    seed: int = 0,
) -> dict:
    """Per-entry differences ``other - reference`` on all frames and on ``k`` folds.

    Returns ``{'folds': k, 'frames': N, 'fold_frames': [...], 'reference': {entry: AP},
    'runs': {label: {'entries': {entry: {'diff', 'fold_diffs', 'fold_std', 'se'}},
    'verdict', 'worst_entry'}}}``.
    """
    ids = list(ids)
    gts = [read_label(Path(label_dir) / f"{i}.txt", with_score=False) for i in ids]
    parts = folds(ids, k, seed)
    index = {frame_id: n for n, frame_id in enumerate(ids)}

    def scores(dts: list[KittiObjects]) -> tuple[dict, list[dict]]:
        full = car_ap40(evaluate_detections(gts, dts, classes=("Car",)))
        per_fold = []
        for part in parts:
            sel = [index[i] for i in part]
            per_fold.append(
                car_ap40(
                    evaluate_detections([gts[j] for j in sel], [dts[j] for j in sel], ("Car",))
                )
            )
        return full, per_fold

    ref_full, ref_folds = scores(read_results(reference_dir, ids))
    runs = {}
    for label, other_dir in other_dirs.items():
        full, per_fold = scores(read_results(other_dir, ids))
        entries = {}
        for entry in ref_full:
            diffs = [f[entry] - r[entry] for f, r in zip(per_fold, ref_folds, strict=True)]
            std = statistics.stdev(diffs)
            entries[entry] = {
                "diff": full[entry] - ref_full[entry],
                "fold_diffs": diffs,
                "fold_std": std,
                "se": std / math.sqrt(k),
            }
        runs[label] = {"entries": entries, **verdict(entries, tol)}
    return {
        "folds": k,
        "frames": len(ids),
        "fold_frames": [len(p) for p in parts],
        "reference": ref_full,
        "runs": runs,
    }


def bootstrap_differences(
    label_dir: Path,
    reference_dir: Path,
    other_dirs: dict[str, Path],
    ids: Sequence[str],
    n: int,
    tol: float,
    seed: int = 0,
) -> dict:
    """Per-entry differences ``other - reference`` on all frames with their paired-bootstrap
    standard error (``n`` resamples of the frames with replacement, the same resample for
    every run).

    Returns ``{'resamples': n, 'frames': N, 'reference': {entry: AP}, 'runs': {label:
    {'entries': {entry: {'diff', 'se', 'median', 'ci95'}}, 'verdict', 'worst_entry'}}}``;
    ``median`` and ``ci95`` (2.5 / 97.5 percentiles) are those of the resampled differences.
    """
    if n < 2:
        raise ValueError(f"need at least 2 bootstrap resamples, got {n}")
    ids = list(ids)
    gts = [read_label(Path(label_dir) / f"{i}.txt", with_score=False) for i in ids]
    ref = read_results(reference_dir, ids)
    others = {label: read_results(d, ids) for label, d in other_dirs.items()}

    def ap(sel, dts):
        return car_ap40(evaluate_detections([gts[j] for j in sel], [dts[j] for j in sel], ("Car",)))

    everything = range(len(ids))
    ref_full = ap(everything, ref)
    full = {label: ap(everything, dts) for label, dts in others.items()}
    resampled = {label: {e: [] for e in ref_full} for label in others}
    rng = np.random.default_rng(seed)
    for _ in range(n):
        sel = rng.integers(0, len(ids), len(ids))
        r = ap(sel, ref)
        for label, dts in others.items():
            o = ap(sel, dts)
            for e in ref_full:
                resampled[label][e].append(o[e] - r[e])
    runs = {}
    for label in others:
        entries = {}
        for e in ref_full:
            d = np.asarray(resampled[label][e])
            entries[e] = {
                "diff": full[label][e] - ref_full[e],
                "se": float(d.std(ddof=1)),
                "median": float(np.median(d)),
                "ci95": [float(np.percentile(d, 2.5)), float(np.percentile(d, 97.5))],
            }
        runs[label] = {"entries": entries, **verdict(entries, tol)}
    return {"resamples": n, "frames": len(ids), "reference": ref_full, "runs": runs}


def verdict(entries: dict[str, dict], tol: float) -> dict:
    """``within`` / ``beyond`` / ``undecided`` (module docstring) and the deciding entry.

    An entry's interval is its ``ci95`` where it has one (the bootstrap's percentile
    interval, which keeps the skew of small frame sets), else ``diff -+ 2 se``; ``beyond``:
    some interval lies entirely outside ``[-tol, tol]``, ``within``: every one inside it."""

    def bounds(v: dict) -> tuple[float, float]:
        if "ci95" in v:
            return min(v["ci95"][0], v["diff"]), max(v["ci95"][1], v["diff"])
        return v["diff"] - Z * v["se"], v["diff"] + Z * v["se"]

    iv = {e: bounds(v) for e, v in entries.items()}
    beyond = {e: max(lo - tol, -tol - hi) for e, (lo, hi) in iv.items()}
    beyond = {e: m for e, m in beyond.items() if m > 0}
    if beyond:
        return {"verdict": "beyond", "worst_entry": max(beyond, key=beyond.get)}
    reach = {e: max(abs(lo), abs(hi)) for e, (lo, hi) in iv.items()}
    worst = max(reach, key=reach.get)
    return {"verdict": "within" if reach[worst] <= tol else "undecided", "worst_entry": worst}
