"""The paired AP difference of two runs with a frame-bootstrap standard error.

Every entry the KITTI evaluator prints
(:func:`~gac_jax.evaluation.kitti_object.evaluate_detections`: AP|R11 and AP|R40 of 2D,
AOS, BEV and 3D at both overlap settings, every difficulty) is compared between a reference
run and a candidate on the same frames: ``diff`` on all frames and ``se``, the standard
deviation of the difference over ``resamples`` *paired frame bootstrap* resamples (frames
drawn with replacement, the same draw for both runs), so objects of one frame move together.

Resampling is cheap because the devkit's statistics are sums over frames: per frame, the
true-positive scores of its threshold pass and, per detection in score order, what adding it
changes in the frame's true positives, false positives and orientation similarity
(:meth:`~gac_jax.evaluation.kitti_object.DetectionEvalSet.level_statistics`). A resample
weights those by how often it drew each frame; the recall thresholds, the precision envelope
and AP then follow the devkit exactly (all weights 1 gives the evaluator's numbers, and any
integer weights the evaluator's numbers on the frames repeated that often).

AP is not a mean over frames, so ``diff -+ z se`` is an approximate interval: the bootstrap
measures how much the difference varies between frame sets of this size, not how far AP on
this many frames is from AP on many more (the precision envelope and the recall sampling make
AP of a frame set a biased estimate). ``benchmarks/bench_guard_coverage.py`` measures it: at
nominal 90 %, on 500- and 2,000-frame sets of generated frames, the median entry covers the
large-set difference 87-88 % of the time, single entries (AP|R11 AOS, BEV@0.5) as little as
27-56 %; ``bias`` (the resamples' mean minus ``diff``) does not correct that (it lowers the
coverage). The guard's count criteria, whose intervals are checked by simulation, carry its
guarantee; the AP entries are a check beside them.

Pure numpy; no JAX.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.evaluation.kitti_object import (
    DIFFICULTIES,
    MIN_OVERLAPS,
    DetectionEvalSet,
    average_precision,
    get_thresholds,
)

RESAMPLES = 200


def curves(class_name: str) -> list[tuple[str, str, float]]:
    """``(name, devkit metric, min overlap)`` of every precision curve of a class (Car:
    ``2d@0.70`` (with AOS), ``bev@0.50``, ``bev@0.70``, ``3d@0.50``, ``3d@0.70``)."""
    strict, loose = MIN_OVERLAPS[class_name]
    out = [(f"2d@{strict[0]:.2f}", "bbox", strict[0])]
    for prefix, metric, k in (("bev", "bev", 1), ("3d", "3d", 2)):
        out += [(f"{prefix}@{t:.2f}", metric, t) for t in sorted({loose[k], strict[k]})]
    return out


def curve_pieces(
    evalset: DetectionEvalSet, class_name: str, difficulty: int, metric: str, min_overlap: float
) -> dict[str, np.ndarray]:
    """Per-frame pieces of one precision curve: ``tp_score``, ``tp_frame`` (threshold pass),
    ``valid`` (F,) evaluated ground truth per frame, and per detection in descending score
    order ``score``, ``frame``, ``dtp``, ``dfp``, ``dsim`` (what it adds when it passes)."""
    _, lone, groups = evalset.curve_parts(class_name, difficulty, metric, min_overlap)
    ign_g, _, _ = evalset.ignore_flags(class_name, difficulty)
    frames = evalset.num_frames
    zeros = np.zeros(int(lone.sum()))
    parts = {
        "score": [evalset.dt_score[lone]],
        "frame": [evalset.dt_frame[lone]],
        "dtp": [zeros],
        "dfp": [zeros + 1.0],
        "dsim": [zeros],
    }
    tp_score, tp_frame = [], []
    for grp in groups:
        scores, rows = DetectionEvalSet.threshold_pass(grp)
        tp_score.append(scores)
        tp_frame.append(grp.frame[rows])
        stats = DetectionEvalSet.level_statistics(grp, metric == "bbox")
        order = np.argsort(-grp.score, axis=1, kind="stable")
        real = np.take_along_axis(grp.real_d, order, axis=1)
        rows = np.broadcast_to(np.arange(len(grp.frame))[:, None], order.shape)
        parts["score"].append(np.take_along_axis(grp.score, order, axis=1)[real])
        parts["frame"].append(grp.frame[rows[real]])
        for key, value in zip(("dtp", "dfp", "dsim"), stats, strict=True):
            parts[key].append(np.diff(value, axis=1).astype(np.float64)[real])
    out = {k: np.concatenate(v) for k, v in parts.items()}
    order = np.argsort(-out["score"], kind="stable")
    out = {k: v[order] for k, v in out.items()}
    out["tp_score"] = np.concatenate(tp_score) if tp_score else np.zeros(0)
    out["tp_frame"] = np.concatenate(tp_frame) if tp_frame else np.zeros(0, np.int64)
    out["valid"] = np.bincount(evalset.gt_frame[ign_g == 0], minlength=frames)
    return out


def curve_ap(pieces: dict, weights: np.ndarray, with_aos: bool) -> dict[str, float]:
    """AP|R11 and AP|R40 (and AOS) of a curve on frames weighted by ``weights`` (F,) ints:
    ``{'ap11', 'ap40'[, 'aos11', 'aos40']}``."""
    scores = np.repeat(pieces["tp_score"], weights[pieces["tp_frame"]])
    thresholds = get_thresholds(scores, max(int(np.dot(weights, pieces["valid"])), 1))
    w = weights[pieces["frame"]].astype(np.float64)
    passed = np.searchsorted(-pieces["score"], -thresholds, side="right")  # scores >= t
    sums = []
    for key in ("dtp", "dfp", "dsim"):
        total = np.concatenate([[0.0], np.cumsum(w * pieces[key])])
        sums.append(total[passed])
    tp, fp, sim = sums
    t = len(thresholds)
    out = {}
    for name, numerator in (("ap", tp), ("aos", sim)) if with_aos else (("ap", tp),):
        curve = np.zeros(41)
        np.divide(numerator, tp + fp, out=curve[:t], where=tp + fp > 0)
        curve = np.maximum.accumulate(curve[::-1])[::-1]
        out[f"{name}11"] = average_precision(curve, 11)
        out[f"{name}40"] = average_precision(curve, 40)
    return out


def _entries(evalsets, classes, with_aos) -> tuple[list, list]:
    keys, pieces = [], []
    for cls in classes:
        for d, difficulty in enumerate(DIFFICULTIES):
            for name, metric, thr in curves(cls):
                aos = with_aos and metric == "bbox"
                keys.append((cls, difficulty, name, aos))
                pieces.append([curve_pieces(e, cls, d, metric, thr) for e in evalsets])
    return keys, pieces


def _named(key, values: dict) -> dict[str, float]:
    cls, difficulty, name, _ = key
    out = {}
    for points in ("11", "40"):
        out[f"{cls} AP{points} {name} {difficulty}"] = values[f"ap{points}"]
        if f"aos{points}" in values:
            out[f"{cls} AP{points} aos {difficulty}"] = values[f"aos{points}"]
    return out


def paired_ap_bootstrap(
    gt: Sequence[KittiObjects],
    ref: Sequence[KittiObjects],
    cand: Sequence[KittiObjects],
    classes: Sequence[str] = ("Car",),
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> dict[str, dict[str, float]]:
    """Every AP entry of both runs and its paired bootstrap (module docstring).

    Returns ``{"Car AP40 3d@0.70 moderate": {'reference', 'candidate', 'diff', 'se'}, ...}``
    (AP points; ``aos`` entries when both runs have valid orientations)."""
    if resamples < 2:
        raise ValueError(f"need at least 2 bootstrap resamples, got {resamples}")
    evalsets = (DetectionEvalSet(gt, ref), DetectionEvalSet(gt, cand))
    with_aos = all(e.compute_aos for e in evalsets)
    keys, pieces = _entries(evalsets, classes, with_aos)
    frames = len(gt)

    def both(weights):
        r, c = {}, {}
        for key, (p_ref, p_cand) in zip(keys, pieces, strict=True):
            r |= _named(key, curve_ap(p_ref, weights, key[3]))
            c |= _named(key, curve_ap(p_cand, weights, key[3]))
        return r, c

    ref_ap, cand_ap = both(np.ones(frames, np.int64))
    rng = np.random.default_rng(seed)
    draws = {k: np.empty(resamples) for k in ref_ap}
    for b in range(resamples):
        r, c = both(rng.multinomial(frames, np.full(frames, 1.0 / frames)))
        for k in draws:
            draws[k][b] = c[k] - r[k]
    return {
        k: {
            "reference": ref_ap[k],
            "candidate": cand_ap[k],
            "diff": cand_ap[k] - ref_ap[k],
            "se": float(draws[k].std(ddof=1)),
            "bias": float(draws[k].mean()) - (cand_ap[k] - ref_ap[k]),
        }
        for k in ref_ap
    }
