"""The paired accuracy guard's rule: does a candidate precision keep float32's detector?

AP|R40 of a few thousand frames moves in ~2 AP steps when a detection or two cross an IoU
threshold, so an AP difference alone cannot say whether a precision is within a small
tolerance. The guard decides on paired outcomes of the two runs on the same frames
(:mod:`gac_jax.evaluation.guard_criteria`: recall at several score thresholds, false positives
per frame above each, heading within 30 degrees, heading and centre error quantile shifts;
per class and difficulty) **and** on the paired AP difference itself
(:mod:`gac_jax.evaluation.ap_bootstrap`: AP|R11 and AP|R40, 2D, BEV, 3D and AOS, every
difficulty, with a paired frame-bootstrap standard error).

Intervals (:mod:`gac_jax.evaluation.paired_proportions`): a count criterion's interval is the
conservative discordance interval of its counts divided by the frames' design effect (frames
as the unit); an AP entry's is ``diff -+ z se`` with the bootstrap's ``se`` (approximate: AP
is not a mean over frames). Margins: ``margin`` (default 0.5 points of the objects: found-rate
or false positives per 100 objects) for the count criteria, ``ap_margin`` (default 1.0 AP
point) for the AP entries.

The rule, at look ``k`` (the k-th guard run of this model and candidate; ``alpha_k = alpha /
2^k``, so all looks together spend at most ``alpha``):

* **within** (a positive claim): every criterion's interval at ``1 - 2 alpha_k`` (each side
  at ``alpha_k``: two one-sided tests) lies inside ``[-margin, +margin]``. By the
  intersection-union principle this decides "all within" at level ``alpha_k`` without a
  multiplicity correction. What it guarantees: with probability at least ``1 - alpha`` over
  the guard frames, on frames like them the candidate finds no fewer objects (per class,
  difficulty, overlap and score threshold), makes no more false positives, keeps its heading
  and centre errors, and moves no AP entry by more than the margins (the AP entries as far
  as the bootstrap's standard error is right).
* **beyond**: some criterion's interval at ``1 - alpha_k / K`` (Bonferroni over the ``K``
  criteria) lies entirely outside its margin; the verdict names it and the difference.
* **undecided** otherwise: the frames are too few; the verdict says about how many frames
  would decide at the next look if the observed rates held.

Also reported, not deciding: the exact McNemar test of ``delta = 0`` per count criterion
(Holm-adjusted: "changed" even if within the margin) and :func:`matched_differences`.

Pure numpy; no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.special import ndtri

from gac_jax.data.kitti import KittiObjects
from gac_jax.detection.nms import box_iou_matrix
from gac_jax.evaluation.guard_criteria import wrap
from gac_jax.evaluation.paired_proportions import (
    clustered_interval,
    difference_interval,
    holm,
    look_alpha,
    mcnemar_p,
    table_sums,
)

MARGIN = 0.5  # points (percent of the objects) of found-rate / false positives
AP_MARGIN = 1.0  # AP points
ALPHA = 0.05
MATCH_IOU = 0.5  # candidate detection <-> float32 detection, for the paired distributions


def _scaled(table: dict, n: int) -> tuple[int, int]:
    """``(ref_only, cand_only)`` of ``n`` objects at ``table``'s discordance rates."""
    m = round(n * (table["ref_only"] + table["cand_only"]) / max(table["n"], 1))
    m_obs = table["ref_only"] + table["cand_only"]
    cand = round(m * table["cand_only"] / m_obs) if m_obs else 0
    return m - cand, cand


def objects_needed(
    table: dict, margin: float, alpha_each_side: float, limit: int = 10_000_000
) -> int | None:
    """The fewest (independent) objects at which the conservative interval
    (``alpha_each_side``) would lie inside ``+-margin`` (observed difference within it) or
    outside it (beyond), if the observed discordance rates held; None if even ``limit``
    objects would not decide."""
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


def _count_row(t: dict, margin: float, a_within: float, a_beyond: float) -> dict:
    sums = table_sums(t)
    lo, hi, deff = clustered_interval(sums, a_within)
    b_lo, b_hi, _ = clustered_interval(sums, a_beyond)
    n = t["n"]
    row = {k: v for k, v in t.items() if not k.startswith("frame_")}
    return row | {
        "kind": t.get("kind", "recall"),
        "diff": 100.0 * (t["cand_only"] - t["ref_only"]) / n if n else 0.0,
        "margin": margin,
        "deff": deff,
        "within_interval": [lo, hi],
        "beyond_interval": [b_lo, b_hi],
        "mcnemar_p": mcnemar_p(t["ref_only"], t["cand_only"]),
    }


def _ap_row(entry: dict, margin: float, a_within: float, a_beyond: float) -> dict:
    diff, se = float(entry["diff"]), float(entry["se"])
    w, b = float(ndtri(1 - a_within)) * se, float(ndtri(1 - a_beyond)) * se
    return {
        "kind": "ap",
        "diff": diff,
        "se": se,
        "margin": margin,
        "within_interval": [diff - w, diff + w],
        "beyond_interval": [diff - b, diff + b],
    }


def _frames_needed(row: dict, frames: int, a_within: float, a_beyond: float) -> int | None:
    """Frames at which this open criterion would decide (next look's levels), if the
    observed rates (count criteria, at their design effect) or the bootstrap's standard
    error times sqrt(frames) (AP entries) held; None if no affordable number would."""
    margin, diff = row["margin"], row["diff"]
    within = abs(diff) < margin
    if row["kind"] == "ap":
        gap = margin - abs(diff) if within else abs(diff) - margin
        if gap <= 0 or row["se"] == 0:
            return None
        z = ndtri(1 - (a_within if within else a_beyond))
        return math.ceil(frames * (z * row["se"] / gap) ** 2)
    if not row["n"] or not frames:
        return None
    deff = row["deff"]
    eff = {
        "n": round(row["n"] / deff),
        "ref_only": round(row["ref_only"] / deff),
        "cand_only": round(row["cand_only"] / deff),
    }
    need = objects_needed(eff, margin, a_within if within else a_beyond)
    return None if need is None else math.ceil(need * deff / (row["n"] / frames))


def decide(
    tables: dict[str, dict],
    frames: int,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    look: int = 1,
    ap: dict[str, dict] | None = None,
    ap_margin: float = AP_MARGIN,
) -> dict:
    """The rule of the module docstring over every criterion.

    Args:
      tables: ``{"Car moderate 3d@0.70": table, ...}``
        (:func:`~gac_jax.evaluation.guard_criteria.guard_tables`, with per-frame counts).
      frames: the frames the tables come from.
      look: which guard run of this model and candidate this is (1, 2, ...).
      ap: ``{"Car AP40 3d@0.70 moderate": {'diff', 'se'}, ...}``
        (:func:`~gac_jax.evaluation.ap_bootstrap.paired_ap_bootstrap`), or None.

    Returns:
      ``{'verdict': 'within'|'beyond'|'undecided', 'reason': one line, 'deciding', 'margin',
      'ap_margin', 'alpha', 'look', 'alpha_look', 'frames', 'frames_needed' (undecided
      only), 'criteria': {name: {'kind': recall|fp|ap, 'diff', 'margin', 'within_interval',
      'beyond_interval', 'status', ...}}}``; count rows also carry the table, ``deff``,
      ``mcnemar_p`` and ``holm_p``, AP rows ``se``. Differences in points.
    """
    ap = ap or {}
    k = len(tables) + len(ap)
    a = look_alpha(alpha, look)
    rows = {n: _count_row(t, margin, a, a / (2 * k)) for n, t in tables.items()}
    rows |= {n: _ap_row(e, ap_margin, a, a / (2 * k)) for n, e in ap.items()}
    for r in rows.values():
        (lo, hi), (b_lo, b_hi), m = r["within_interval"], r["beyond_interval"], r["margin"]
        empty = r["kind"] != "ap" and not r["n"]
        if not empty and (b_lo > m or b_hi < -m):
            r["status"] = "beyond"
        elif not empty and -m <= lo and hi <= m:
            r["status"] = "within"
        else:
            r["status"] = "undecided"
    counted = [n for n in rows if rows[n]["kind"] != "ap"]
    for name, p in zip(counted, holm([rows[n]["mcnemar_p"] for n in counted]), strict=True):
        rows[name]["holm_p"] = p
    out = {
        "margin": margin,
        "ap_margin": ap_margin,
        "alpha": alpha,
        "look": look,
        "alpha_look": a,
        "frames": frames,
        "criteria": rows,
    }
    beyond = {n: r for n, r in rows.items() if r["status"] == "beyond"}
    if beyond:
        worst = max(beyond, key=lambda n: abs(beyond[n]["diff"]) / beyond[n]["margin"])
        r = beyond[worst]
        moved = ", ".join(f"{n} {beyond[n]['diff']:+.2f}" for n in list(beyond)[:6])
        more = f" and {len(beyond) - 6} more" if len(beyond) > 6 else ""
        detail = (
            f"{r['ref_only']} lost, {r['cand_only']} gained of {r['n']}"
            if r["kind"] != "ap"
            else f"AP moved {r['diff']:+.2f} +- {r['se']:.2f} (bootstrap se)"
        )
        out |= {
            "verdict": "beyond",
            "deciding": worst,
            "reason": f"moved beyond the margins ({margin} points, AP {ap_margin}): "
            f"{moved}{more} (points; {worst}: {detail})",
        }
        return out
    open_ = [n for n, r in rows.items() if r["status"] == "undecided"]
    if not open_:
        widest = max(
            rows, key=lambda n: max(map(abs, rows[n]["within_interval"])) / rows[n]["margin"]
        )
        iv = rows[widest]["within_interval"]
        out |= {
            "verdict": "within",
            "deciding": widest,
            "reason": f"every criterion within its margin ({margin} points, AP {ap_margin}; "
            f"look {look}, alpha {a:.4g}; widest: {widest} [{iv[0]:+.2f}, {iv[1]:+.2f}])",
        }
        return out
    a_next = look_alpha(alpha, look + 1)
    needs = {n: _frames_needed(rows[n], frames, a_next, a_next / (2 * k)) for n in open_}
    known = {n: v for n, v in needs.items() if v is not None}
    deciding = max(known, key=known.get) if known else open_[0]
    frames_needed = known[deciding] if len(known) == len(needs) else None
    r = rows[deciding]
    needed_text = (
        f"about {frames_needed} frames would decide it at look {look + 1}"
        if frames_needed is not None
        else "no affordable number of frames would decide it at the observed rates"
    )
    out |= {
        "verdict": "undecided",
        "deciding": deciding,
        "frames_needed": frames_needed,
        "reason": f"too few frames for {len(open_)} criteria; {deciding}: diff {r['diff']:+.2f} "
        f"[{r['within_interval'][0]:+.2f}, {r['within_interval'][1]:+.2f}] on {frames} frames "
        f"(look {look}); {needed_text}",
    }
    return out


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
        heading.append(np.degrees(wrap(a.rotation_y[i] - b.rotation_y[j])))
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
