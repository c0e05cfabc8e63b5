"""What the paired accuracy guard compares: per-object and per-frame outcomes of two runs.

Both runs are scored on the same frames; every ground-truth object that the devkit evaluates
for a class and difficulty (:meth:`~gac_jax.evaluation.kitti_object.DetectionEvalSet.ignore_flags`:
``ignored_gt == 0``) gives paired outcomes, and every frame paired counts. The criteria, per
class and difficulty (Car names; other classes use their own overlaps):

* **recall at several score thresholds** ``2d@0.70``, ``bev@0.50``, ``bev@0.70``, ``3d@0.50``,
  ``3d@0.70``: found = a true positive of the devkit's statistics pass using the detections
  scoring at least the threshold (each ground truth in label order takes the free
  non-ignored detection of largest overlap above the minimum overlap, else a free ignored
  one). The thresholds are the deployed one (``min_score``, names without suffix) and those
  of :data:`SCORE_THRESHOLDS` above it (names ``... s>=0.70``), so a change of the score
  order is seen, not only of the set above one threshold.
* **false positives above each score threshold** (``... fp``, ``... fp s>=0.70``): the
  devkit's false positives of each frame at that threshold (unmatched non-ignored detections
  outside DontCare regions); their per-frame change is counted as objects gained
  (``cand_only``, more false positives) or lost (``ref_only``), in points of the evaluated
  objects (false positives per 100 objects).
* ``heading``: found at ``2d@0.70`` and the matched detection's observation angle within
  ``heading_tolerance`` (default 30 deg) of the label's (AOS's matching).
* **error quantile shifts** ``heading p50/p90`` (observation-angle error of the ``2d@0.70``
  match) and ``centre p50/p90`` (3D centre distance of the loose-3D match): found with an
  error at most the *reference's* 50 % / 90 % quantile of that error (over the objects it
  finds). The reference has about 50 % / 90 % of its found objects there by construction; a
  candidate whose errors grow (every heading turned 25 degrees, centres moved) loses them.

Pure numpy; no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.evaluation.kitti_object import DIFFICULTIES, MIN_OVERLAPS, DetectionEvalSet
from gac_jax.guard.paired_proportions import paired_table

HEADING_TOLERANCE_DEG = 30.0
SCORE_THRESHOLDS = (0.3, 0.5, 0.7, 0.9)
QUANTILES = (0.5, 0.9)
_BOX_CRITERIA = (("2d", "bbox", 0), ("bev", "bev", 1), ("3d", "3d", 2))


def criteria(class_name: str) -> list[tuple[str, str, float]]:
    """``(name, devkit metric, min overlap)`` of a class: 2D at the strict threshold, BEV and
    3D at the loose and strict ones (Car: ``2d@0.70, bev@0.50, bev@0.70, 3d@0.50, 3d@0.70``)."""
    strict, loose = MIN_OVERLAPS[class_name]
    out = [(f"2d@{strict[0]:.2f}", "bbox", strict[0])]
    for prefix, metric, k in _BOX_CRITERIA[1:]:
        for thr in sorted({loose[k], strict[k]}):
            out.append((f"{prefix}@{thr:.2f}", metric, thr))
    return out


def score_thresholds(min_score: float, grid: Sequence[float] = SCORE_THRESHOLDS) -> list[float]:
    """The deployed threshold first, then those of ``grid`` above it (ascending)."""
    return [float(min_score), *sorted(float(t) for t in set(grid) if t > min_score)]


def suffix(threshold: float, min_score: float) -> str:
    """Name suffix of a score threshold: empty for the deployed one."""
    return "" if threshold == min_score else f" s>={threshold:.2f}"


def wrap(angle: np.ndarray) -> np.ndarray:
    """Angle differences in ``[-pi, pi)``."""
    return (np.asarray(angle, np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def take_detections(evalset, metric, thr, ign_g, ign_d, usable):
    """The devkit's statistics pass (one overlap threshold, the ``usable`` detections):
    ``(found (G,), detection (G,), assigned (D,))``: true positives, each ground truth's
    matched detection (-1) and the detections matched to any ground truth."""
    n_gt = len(ign_g)
    found = np.zeros(n_gt, dtype=bool)
    chosen = np.full(n_gt, -1, dtype=np.int64)
    pg, pd, ov = evalset.match_pairs(metric)
    sel = (ov > thr) & (ign_g[pg] != -1) & (ign_d[pd] != -1) & usable[pd]
    pg, pd, ov = pg[sel], pd[sel], ov[sel]
    order = np.lexsort((pd, pg))  # ground truth in label order, detections in index order
    pg, pd, ov = pg[order], pd[order], ov[order]
    assigned = np.zeros(len(ign_d), dtype=bool)
    bounds = np.flatnonzero(np.diff(pg)) + 1
    for g_idx, js, os in zip(
        pg[np.r_[0, bounds]] if pg.size else [],
        np.split(pd, bounds),
        np.split(ov, bounds),
        strict=False,
    ):
        free = ~assigned[js]
        valid = free & (ign_d[js] == 0)
        if valid.any():
            k = int(np.argmax(np.where(valid, os, -1.0)))  # first of equal overlaps
            found[g_idx] = ign_g[g_idx] == 0
        elif (free & (ign_d[js] == 1)).any():
            k = int(np.argmax(free & (ign_d[js] == 1)))
        else:
            continue
        assigned[js[k]] = True
        chosen[g_idx] = js[k]
    return found, chosen, assigned


def frame_outcomes(
    gt: Sequence[KittiObjects],
    dt: Sequence[KittiObjects],
    class_name: str = "Car",
    thresholds: Sequence[float] = (0.0,),
    heading_tolerance_deg: float = HEADING_TOLERANCE_DEG,
) -> dict[str, dict]:
    """One run's outcomes per difficulty (module docstring).

    Args:
      gt: per frame, the labels (DontCare included); the same for every run compared.
      dt: per frame, one run's detections (``score`` set).
      thresholds: score thresholds, the deployed one first (:func:`score_thresholds`).

    Returns:
      ``{difficulty: {'frame': (N_d,) frame index of each evaluated object (frame and label
      order, so two runs pair object by object), 'found': {name: (N_d,) bool}, 'fp': {name:
      (F,) false positives per frame}, 'heading_error': (N_d,) deg, 'centre_error': (N_d,) m
      (NaN where not found at the deployed threshold)}}``.
    """
    evalset = DetectionEvalSet(gt, dt)
    d_all = KittiObjects.concatenate(list(dt)) if len(dt) else None
    g_all = KittiObjects.concatenate(list(gt)) if len(gt) else None
    tol = math.radians(heading_tolerance_deg)
    frames = evalset.num_frames
    min_score = thresholds[0]
    loose_3d = [c for c in criteria(class_name) if c[1] == "3d"][0][0]
    out = {}
    for d, name in enumerate(DIFFICULTIES):
        ign_g, ign_d, _ = evalset.ignore_flags(class_name, d)
        counted = ign_g == 0
        per = {"frame": evalset.gt_frame[counted], "found": {}, "fp": {}}
        for t in thresholds:
            usable = evalset.dt_score >= t
            for crit, metric, thr in criteria(class_name):
                found, chosen, assigned = take_detections(
                    evalset, metric, thr, ign_g, ign_d, usable
                )
                tag = crit + suffix(t, min_score)
                per["found"][tag] = found[counted]
                fp = (ign_d == 0) & usable & ~assigned & ~(evalset.dontcare_overlap(metric) > thr)
                per["fp"][crit + " fp" + suffix(t, min_score)] = np.bincount(
                    evalset.dt_frame[fp], minlength=frames
                )
                hit = found & (chosen >= 0)
                if metric == "bbox":
                    error = np.abs(wrap(evalset.dt_alpha[chosen] - evalset.gt_alpha))
                    per["found"]["heading" + suffix(t, min_score)] = (found & (error <= tol))[
                        counted
                    ]
                    if t == min_score:
                        per["heading_error"] = np.where(hit, np.degrees(error), np.nan)[counted]
                if crit == loose_3d and t == min_score:
                    dist = np.full(len(found), np.nan)
                    if d_all is not None and hit.any():
                        dist[hit] = np.linalg.norm(
                            d_all.location[chosen[hit]] - g_all.location[hit], axis=-1
                        )
                    per["centre_error"] = dist[counted]
        out[name] = per
    return out


def object_outcomes(
    gt: Sequence[KittiObjects],
    dt: Sequence[KittiObjects],
    class_name: str = "Car",
    min_score: float = 0.0,
    heading_tolerance_deg: float = HEADING_TOLERANCE_DEG,
) -> dict[str, dict[str, np.ndarray]]:
    """Found (True) / missed per evaluated object at the deployed threshold only:
    ``{difficulty: {criterion: (N_d,) bool}}`` (criteria of :func:`criteria` and
    ``heading``)."""
    full = frame_outcomes(gt, dt, class_name, (min_score,), heading_tolerance_deg)
    return {d: per["found"] for d, per in full.items()}


def _fp_table(ref_fp: np.ndarray, cand_fp: np.ndarray, frame_n: np.ndarray) -> dict:
    """A paired table of per-frame false-positive counts: fewer = ``ref_only``, more =
    ``cand_only``, out of the evaluated objects ``n``."""
    d = cand_fp.astype(np.int64) - ref_fp.astype(np.int64)
    lost, gained = np.maximum(-d, 0), np.maximum(d, 0)
    return {
        "n": int(frame_n.sum()),
        "both": 0,
        "ref_only": int(lost.sum()),
        "cand_only": int(gained.sum()),
        "neither": 0,
        "kind": "fp",
        "frame_n": frame_n,
        "frame_ref_only": lost,
        "frame_cand_only": gained,
    }


def guard_tables(
    gt: Sequence[KittiObjects],
    ref: Sequence[KittiObjects],
    cand: Sequence[KittiObjects],
    classes: Sequence[str] = ("Car",),
    min_score: float = 0.0,
    heading_tolerance_deg: float = HEADING_TOLERANCE_DEG,
    thresholds: Sequence[float] | None = None,
) -> dict[str, dict]:
    """Paired tables (with per-frame counts) of every class, difficulty and criterion, keyed
    ``"Car moderate 3d@0.70"``, ``"Car moderate 3d@0.70 s>=0.90"``, ``"Car hard bev@0.50
    fp"``, ``"Car easy heading p90"``, ... (module docstring). ``thresholds``: default
    :func:`score_thresholds` of ``min_score``."""
    thresholds = list(thresholds or score_thresholds(min_score))
    frames = len(gt)
    tables = {}
    for cls in classes:
        a = frame_outcomes(gt, ref, cls, thresholds, heading_tolerance_deg)
        b = frame_outcomes(gt, cand, cls, thresholds, heading_tolerance_deg)
        for diff, per in a.items():
            frame = per["frame"]
            frame_n = np.bincount(frame, minlength=frames)
            for crit, found in per["found"].items():
                t = paired_table(found, b[diff]["found"][crit], frame, frames)
                tables[f"{cls} {diff} {crit}"] = t
            for crit, fp in per["fp"].items():
                tables[f"{cls} {diff} {crit}"] = _fp_table(fp, b[diff]["fp"][crit], frame_n)
            for what in ("heading", "centre"):
                err_a, err_b = per[f"{what}_error"], b[diff][f"{what}_error"]
                seen = np.isfinite(err_a)
                if not seen.any():
                    continue
                for q in QUANTILES:
                    limit = float(np.quantile(err_a[seen], q))
                    t = paired_table(
                        np.nan_to_num(err_a, nan=np.inf) <= limit,
                        np.nan_to_num(err_b, nan=np.inf) <= limit,
                        frame,
                        frames,
                    )
                    tables[f"{cls} {diff} {what} p{round(100 * q)}"] = t | {"limit": limit}
    return tables
