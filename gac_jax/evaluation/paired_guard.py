"""Paired per-object accuracy guard: float32 vs a candidate precision on the same frames.

AP|R40 of a few thousand frames moves in ~2 AP steps when a detection or two cross an IoU
threshold, so an AP difference cannot say whether a precision is within a small tolerance.
This module decides on *paired per-object outcomes* instead. Both runs are scored on the same
frames; every ground-truth object that the devkit evaluates for a class and difficulty
(:meth:`~gac_jax.evaluation.kitti_object.DetectionEvalSet.ignore_flags`: ``ignored_gt == 0``)
is *found* or *missed* by each run at each criterion:

* ``2d@0.70``, ``bev@0.50``, ``bev@0.70``, ``3d@0.50``, ``3d@0.70`` (Car thresholds; other
  classes use theirs): the devkit's statistics pass at the deployed score threshold (every
  detection of the result files scoring at least ``min_score``): each ground truth in label
  order takes the free non-ignored detection of largest overlap above the threshold, else a
  free ignored one (too small: found by neither); found = a true positive.
* ``heading``: found at ``2d@0.70`` *and* the matched detection's observation angle within
  ``heading_tolerance`` (default 30 deg) of the label's (AOS's matching; AOS weighs the
  same error by ``(1 + cos d) / 2``).

Per criterion the outcomes form a 2x2 table: ``both`` found, ``ref_only`` (lost by the
candidate), ``cand_only`` (gained), ``neither``. The difference of found-rates is
``delta = (cand_only - ref_only) / n`` (points = percent of the objects). Its confidence
interval is *discordance-based and exact*: ``delta = q (2 p - 1)`` with ``q`` the share of
discordant objects (``ref_only + cand_only`` of ``n``) and ``p`` the share of discordant
objects the candidate found; Clopper-Pearson intervals for ``q`` and ``p``, each at half the
error level, bound ``delta`` together (Bonferroni, so the interval's coverage is at least the
stated one). With no discordant object it is ``+-q_hi``, e.g. ``+-0.50`` points for 736
objects in the "within" test below: *agreement on few objects is no evidence of equivalence*.

The rule (``margin`` default 0.5 points, ``alpha`` default 0.05):

* **within** (a positive claim): every criterion's interval at ``1 - 2 alpha`` (each side at
  ``alpha``: two one-sided tests) lies inside ``[-margin, +margin]``. By the
  intersection-union principle this decides "all within" at level ``alpha`` without a
  multiplicity correction.
* **beyond**: some criterion's interval at ``1 - alpha / K`` (Bonferroni over the ``K``
  criteria) lies entirely outside ``[-margin, +margin]``; the verdict names it and the
  difference.
* **undecided** otherwise: the objects are too few; :func:`objects_needed` says how many
  objects (and :func:`decide` how many frames, at this set's objects per frame) would decide
  each open criterion if its observed rates held.

Also reported, not deciding: the exact McNemar test of ``delta = 0`` (binomial test on the
discordant objects, Holm-adjusted over the criteria: "changed" even if within the margin),
and :func:`matched_differences`: the candidate's detections matched to float32's (same
class, 2D IoU >= 0.5, greedy by score) with the median / p95 / max of the score, 3D centre,
dimension and heading (``rotation_y``) differences and the heading flips (> 90 deg).

Pure numpy and file reading; no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.detection.nms import box_iou_matrix
from gac_jax.evaluation.kitti_object import DIFFICULTIES, MIN_OVERLAPS, DetectionEvalSet

MARGIN = 0.5  # points (percent of the objects) of found-rate
ALPHA = 0.05
HEADING_TOLERANCE_DEG = 30.0
MATCH_IOU = 0.5  # candidate detection <-> float32 detection, for the paired distributions
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


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angle differences in ``[-pi, pi)``."""
    return (np.asarray(angle, np.float64) + np.pi) % (2.0 * np.pi) - np.pi


def _take_detections(evalset, metric, thr, ign_g, ign_d, usable) -> tuple[np.ndarray, np.ndarray]:
    """The devkit's statistics pass (one threshold): ``(found (G,), detection (G,))`` where
    ``found`` marks true positives and ``detection`` the matched detection's index (-1)."""
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
    return found, chosen


def object_outcomes(
    gt: Sequence[KittiObjects],
    dt: Sequence[KittiObjects],
    class_name: str = "Car",
    min_score: float = 0.0,
    heading_tolerance_deg: float = HEADING_TOLERANCE_DEG,
) -> dict[str, dict[str, np.ndarray]]:
    """Found (True) / missed per evaluated ground-truth object, per difficulty and criterion.

    Args:
      gt: per frame, the labels (DontCare included); the same for every run compared.
      dt: per frame, one run's detections (``score`` set).
      min_score: detections scoring lower are not used (the deployed threshold).

    Returns:
      ``{difficulty: {criterion: (N_d,) bool}}``: ``N_d`` the objects that difficulty
      evaluates, in frame and label order (so two runs' arrays pair object by object);
      criteria of :func:`criteria` plus ``"heading"``.
    """
    evalset = DetectionEvalSet(gt, dt)
    usable = evalset.dt_score >= min_score
    tol = math.radians(heading_tolerance_deg)
    out = {}
    for d, name in enumerate(DIFFICULTIES):
        ign_g, ign_d, _ = evalset.ignore_flags(class_name, d)
        counted = ign_g == 0
        per = {}
        for crit, metric, thr in criteria(class_name):
            found, chosen = _take_detections(evalset, metric, thr, ign_g, ign_d, usable)
            per[crit] = found[counted]
            if metric == "bbox":
                error = np.abs(_wrap(evalset.dt_alpha[chosen] - evalset.gt_alpha))
                per["heading"] = (found & (error <= tol))[counted]
        out[name] = per
    return out


# ----------------------------------------------------------------------------- statistics


_LOG_FACTORIALS = np.zeros(1)


def _log_factorials(n: int) -> np.ndarray:
    """``log k!`` for ``k = 0..n`` (cached, grown on demand)."""
    global _LOG_FACTORIALS
    if len(_LOG_FACTORIALS) <= n:
        k = np.arange(1, 2 * n + 2, dtype=np.float64)
        _LOG_FACTORIALS = np.concatenate([[0.0], np.cumsum(np.log(k))])
    return _LOG_FACTORIALS[: n + 1]


def binom_cdf(x: int, n: int, p: float) -> float:
    """``P(X <= x)`` for ``X ~ Binomial(n, p)``."""
    if x < 0:
        return 0.0
    if x >= n or p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0
    lf = _log_factorials(n)
    k = np.arange(x + 1)
    logs = lf[n] - lf[k] - lf[n - k] + k * math.log(p) + (n - k) * math.log1p(-p)
    top = logs.max()
    return float(min(1.0, math.exp(top) * np.exp(logs - top).sum()))


def _bisect(f, target: float, increasing: bool) -> float:
    """``p`` in [0, 1] with ``f(p) = target`` for a monotone ``f``."""
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        below = f(mid) < target
        lo, hi = (mid, hi) if below == increasing else (lo, mid)
    return 0.5 * (lo + hi)


def clopper_pearson(x: int, n: int, alpha_each_side: float) -> tuple[float, float]:
    """Exact binomial interval for ``x`` successes of ``n``: each bound has error
    ``alpha_each_side`` (``(0, 1)`` for ``n = 0``)."""
    if n == 0:
        return 0.0, 1.0
    a = alpha_each_side
    lower = 0.0 if x == 0 else _bisect(lambda p: 1.0 - binom_cdf(x - 1, n, p), a, True)
    upper = 1.0 if x == n else _bisect(lambda p: binom_cdf(x, n, p), a, False)
    return lower, upper


def difference_interval(
    ref_only: int, cand_only: int, n: int, alpha_each_side: float
) -> tuple[float, float]:
    """Bounds (points) of the found-rate difference ``candidate - float32`` (module
    docstring); each bound holds with error at most ``alpha_each_side``."""
    if n == 0:
        return -100.0, 100.0
    m = ref_only + cand_only
    q_lo, q_hi = clopper_pearson(m, n, alpha_each_side / 2)
    p_lo, p_hi = clopper_pearson(cand_only, m, alpha_each_side / 2)
    low = min(q * (2 * p_lo - 1) for q in (q_lo, q_hi))
    high = max(q * (2 * p_hi - 1) for q in (q_lo, q_hi))
    return 100.0 * low, 100.0 * high


def mcnemar_p(ref_only: int, cand_only: int) -> float:
    """Exact two-sided McNemar p-value (binomial test of the discordant objects at 1/2)."""
    m = ref_only + cand_only
    if m == 0:
        return 1.0
    return min(1.0, 2.0 * binom_cdf(min(ref_only, cand_only), m, 0.5))


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm step-down adjusted p-values (same order)."""
    order = np.argsort(p_values)
    k = len(p_values)
    adjusted, running = [0.0] * k, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (k - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def paired_table(ref: np.ndarray, cand: np.ndarray) -> dict[str, int]:
    """The 2x2 table of paired outcomes (same objects, same order)."""
    ref, cand = np.asarray(ref, bool), np.asarray(cand, bool)
    if ref.shape != cand.shape:
        raise ValueError(f"paired outcomes need the same objects: {ref.shape} vs {cand.shape}")
    return {
        "n": int(ref.size),
        "both": int(np.sum(ref & cand)),
        "ref_only": int(np.sum(ref & ~cand)),
        "cand_only": int(np.sum(~ref & cand)),
        "neither": int(np.sum(~ref & ~cand)),
    }


def _scaled(table: dict[str, int], n: int) -> tuple[int, int]:
    """``(ref_only, cand_only)`` of ``n`` objects at ``table``'s discordance rates."""
    m = round(n * (table["ref_only"] + table["cand_only"]) / max(table["n"], 1))
    m_obs = table["ref_only"] + table["cand_only"]
    cand = round(m * table["cand_only"] / m_obs) if m_obs else 0
    return m - cand, cand


def objects_needed(
    table: dict[str, int], margin: float, alpha_each_side: float, limit: int = 10_000_000
) -> int | None:
    """The fewest objects at which this criterion's interval (``alpha_each_side``) would lie
    inside ``+-margin`` (observed difference within it) or outside it (beyond), if the
    observed discordance rates held; None if even ``limit`` objects would not decide."""
    n = max(table["n"], 1)
    delta = 100.0 * (table["cand_only"] - table["ref_only"]) / n
    if table["n"] and abs(delta) == margin:
        return None

    def decided(k: int) -> bool:
        lo, hi = difference_interval(*_scaled(table, k), k, alpha_each_side)
        if abs(delta) < margin or not table["n"]:
            return -margin <= lo and hi <= margin
        return lo > margin or hi < -margin

    lo, hi = n, n
    while not decided(hi):
        lo, hi = hi, hi * 2
        if hi > limit:
            return None
    while hi - lo > max(1, lo // 100):  # to 1 %
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if decided(mid) else (mid, hi)
    return hi


def decide(
    tables: dict[str, dict[str, int]],
    frames: int,
    margin: float = MARGIN,
    alpha: float = ALPHA,
) -> dict:
    """The rule of the module docstring over every criterion's paired table.

    Args:
      tables: ``{"moderate 3d@0.70": paired_table(...), ...}`` (one per difficulty and
        criterion; empty tables count as undecided).
      frames: the frames the tables come from (for the frames a decision would need).

    Returns:
      ``{'verdict': 'within'|'beyond'|'undecided', 'reason': one line, 'margin', 'alpha',
      'frames', 'frames_needed' (undecided only), 'criteria': {name: {table..., 'diff',
      'within_interval', 'beyond_interval', 'mcnemar_p', 'holm_p', 'status'}}}`` with
      ``status`` one of within / beyond / undecided and ``diff`` in points.
    """
    k = len(tables)
    rows = {}
    for name, t in tables.items():
        n = t["n"]
        diff = 100.0 * (t["cand_only"] - t["ref_only"]) / n if n else 0.0
        within_iv = difference_interval(t["ref_only"], t["cand_only"], n, alpha)
        beyond_iv = difference_interval(t["ref_only"], t["cand_only"], n, alpha / (2 * k))
        if n and (beyond_iv[0] > margin or beyond_iv[1] < -margin):
            status = "beyond"
        elif n and -margin <= within_iv[0] and within_iv[1] <= margin:
            status = "within"
        else:
            status = "undecided"
        rows[name] = {
            **t,
            "diff": diff,
            "within_interval": list(within_iv),
            "beyond_interval": list(beyond_iv),
            "mcnemar_p": mcnemar_p(t["ref_only"], t["cand_only"]),
            "status": status,
        }
    for name, p in zip(rows, holm([r["mcnemar_p"] for r in rows.values()]), strict=True):
        rows[name]["holm_p"] = p
    out = {"margin": margin, "alpha": alpha, "frames": frames, "criteria": rows}
    beyond = {n: r for n, r in rows.items() if r["status"] == "beyond"}
    if beyond:
        worst = max(beyond, key=lambda n: abs(beyond[n]["diff"]))
        r = beyond[worst]
        moved = ", ".join(f"{n} {beyond[n]['diff']:+.2f}" for n in beyond)
        out |= {
            "verdict": "beyond",
            "deciding": worst,
            "reason": f"found-rate moved beyond {margin} points: {moved} (points; {worst}: "
            f"{r['ref_only']} objects lost, {r['cand_only']} gained of {r['n']})",
        }
        return out
    open_ = [n for n, r in rows.items() if r["status"] == "undecided"]
    if not open_:
        widest = max(rows, key=lambda n: max(map(abs, rows[n]["within_interval"])))
        iv = rows[widest]["within_interval"]
        out |= {
            "verdict": "within",
            "deciding": widest,
            "reason": f"every criterion within {margin} points (widest: {widest} "
            f"[{iv[0]:+.2f}, {iv[1]:+.2f}])",
        }
        return out
    needs = {}
    for name in open_:
        r = rows[name]
        alpha_side = alpha if abs(r["diff"]) < margin or not r["n"] else alpha / (2 * k)
        need = objects_needed(r, margin, alpha_side)
        per_frame = r["n"] / frames if frames and r["n"] else None
        needs[name] = (
            None if need is None or per_frame is None else math.ceil(need / per_frame),
            need,
        )
    known = {n: v for n, v in needs.items() if v[0] is not None}
    deciding = max(known, key=lambda n: known[n][0]) if known else open_[0]
    frames_needed = known[deciding][0] if len(known) == len(needs) else None
    r = rows[deciding]
    needed_text = (
        f"about {frames_needed} frames ({known[deciding][1]} objects) would decide it"
        if frames_needed is not None
        else "no affordable number of frames would decide it at the observed rates"
    )
    out |= {
        "verdict": "undecided",
        "deciding": deciding,
        "frames_needed": frames_needed,
        "objects_needed": {n: v[1] for n, v in needs.items()},
        "reason": f"too few objects for {len(open_)} criteria; {deciding}: {r['n']} objects, "
        f"diff {r['diff']:+.2f} [{r['within_interval'][0]:+.2f}, "
        f"{r['within_interval'][1]:+.2f}]; {needed_text}",
    }
    return out


def guard_tables(
    gt: Sequence[KittiObjects],
    ref: Sequence[KittiObjects],
    cand: Sequence[KittiObjects],
    classes: Sequence[str] = ("Car",),
    min_score: float = 0.0,
    heading_tolerance_deg: float = HEADING_TOLERANCE_DEG,
) -> dict[str, dict[str, int]]:
    """Paired tables of every class, difficulty and criterion, keyed
    ``"Car moderate 3d@0.70"`` (:func:`object_outcomes` of both runs)."""
    tables = {}
    for cls in classes:
        a = object_outcomes(gt, ref, cls, min_score, heading_tolerance_deg)
        b = object_outcomes(gt, cand, cls, min_score, heading_tolerance_deg)
        for diff, per in a.items():
            for crit, found in per.items():
                tables[f"{cls} {diff} {crit}"] = paired_table(found, b[diff][crit])
    return tables


# ----------------------------------------------------------------------------- detections


def match_detections(ref: KittiObjects, cand: KittiObjects) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i, j)`` of matched detections of one frame: same class, 2D IoU >= 0.5,
    greedily in ``ref``'s score order (each detection used once)."""
    if not len(ref) or not len(cand):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    iou = box_iou_matrix(ref.bbox, cand.bbox)
    iou[ref.type[:, None] != cand.type[None, :]] = 0.0
    free = np.ones(len(cand), bool)
    pairs = []
    for i in np.argsort(-ref.score, kind="stable"):
        j = int(np.argmax(np.where(free, iou[i], -1.0)))
        if free[j] and iou[i, j] >= MATCH_IOU:
            free[j] = False
            pairs.append((i, j))
    a = np.array([p[0] for p in pairs], np.int64)
    b = np.array([p[1] for p in pairs], np.int64)
    return a, b


def _spread(values: list[np.ndarray]) -> dict[str, float]:
    v = np.abs(np.concatenate(values)) if values else np.zeros(0)
    if not v.size:
        return {"median": 0.0, "p95": 0.0, "max": 0.0}
    return {
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


def matched_differences(ref: Sequence[KittiObjects], cand: Sequence[KittiObjects]) -> dict:
    """Paired distributions of the candidate's detections against float32's (all frames).

    Returns ``{'reference_detections', 'detections', 'matched', 'score', 'centre_m',
    'dimensions_m', 'heading_deg': {'median', 'p95', 'max'} (absolute differences; centre:
    3D distance, dimensions: largest of h/w/l, heading: wrapped ``rotation_y``),
    'heading_flips' (matched pairs > 90 deg apart), 'heading_flip_share'}``."""
    score, centre, dims, heading = [], [], [], []
    n_ref = n_cand = 0
    for a, b in zip(ref, cand, strict=True):
        n_ref, n_cand = n_ref + len(a), n_cand + len(b)
        i, j = match_detections(a, b)
        score.append(a.score[i] - b.score[j])
        centre.append(np.linalg.norm(a.location[i] - b.location[j], axis=-1))
        dims.append(np.abs(a.dimensions[i] - b.dimensions[j]).max(axis=-1, initial=0.0))
        heading.append(np.degrees(_wrap(a.rotation_y[i] - b.rotation_y[j])))
    matched = int(sum(len(h) for h in heading))
    flips = int(sum(np.sum(np.abs(h) > 90.0) for h in heading))
    return {
        "reference_detections": n_ref,
        "detections": n_cand,
        "matched": matched,
        "score": _spread(score),
        "centre_m": _spread(centre),
        "dimensions_m": _spread(dims),
        "heading_deg": _spread(heading),
        "heading_flips": flips,
        "heading_flip_share": flips / matched if matched else 0.0,
    }
