"""The paired accuracy guard's rule: does a candidate precision keep float32's detector?

AP|R40 of a few thousand frames moves in ~2 AP steps when a detection or two cross an IoU
threshold, so an AP difference alone cannot say whether a precision is within a small
tolerance. The guard decides on paired outcomes of the two runs on the same frames
(:mod:`gac_jax.guard.criteria`: recall at several score thresholds, false positives
per frame above each, heading within 30 degrees, heading and centre error quantile shifts;
per class and difficulty) **and** on the paired AP difference itself
(:mod:`gac_jax.guard.ap_bootstrap`: AP|R11 and AP|R40, 2D, BEV, 3D and AOS, every
difficulty, with a paired frame-bootstrap standard error).

Intervals: a count criterion's are tests by betting on its per-frame changes
(:mod:`gac_jax.guard.frame_betting`), the frame as the unit, valid for any distribution
of the changes over frames (bursts, losses only in crowded frames) within a per-frame bound:
a recall row's frame changes at most its objects, and no frame has more than the largest
guard frame; a false-positive row's frame gains or loses at most ``fp_cap`` (default 20)
false positives, which the guard checks (a frame beyond it leaves the criterion undecided,
named). An AP entry's interval is ``diff -+ z se`` with the bootstrap's ``se`` (approximate:
AP is not a mean over frames). Margins: ``margin`` (default 0.5 points of the objects: found-rate
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
  and centre errors (each within the count margin, given the per-frame bounds above), and
  moves no AP entry by more than the AP margin (as far as the bootstrap's standard error is
  right).
* **beyond**: some criterion's interval at ``1 - alpha_k / K`` (each side at
  ``alpha_k / (2 K)``, Bonferroni over the ``K`` criteria) lies entirely outside its margin;
  the verdict names it and the difference.
* **undecided** otherwise: the frames are too few; the verdict says about how many frames
  would decide at the next look if the guard frames came again (count criteria) or the
  bootstrap's standard error shrank as ``1 / sqrt(frames)`` (AP entries).

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
from gac_jax.guard import frame_betting as fb
from gac_jax.guard.criteria import wrap
from gac_jax.guard.frame_betting import FP_CAP, FrameBounds
from gac_jax.guard.paired_proportions import holm, look_alpha, mcnemar_p

MARGIN = 0.5  # points (percent of the objects) of found-rate / false positives
AP_MARGIN = 1.0  # AP points
ALPHA = 0.05
MATCH_IOU = 0.5  # candidate detection <-> float32 detection, for the paired distributions


def frame_changes(table: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(d, n)`` of a count table, ``(F,)`` float64: per frame the candidate's change (gained
    minus lost) and the evaluated objects; a table without per-frame counts counts each object
    as a frame."""
    if "frame_n" in table:
        d = np.asarray(table["frame_cand_only"], np.float64) - table["frame_ref_only"]
        return d, np.asarray(table["frame_n"], np.float64)
    r, c = table["ref_only"], table["cand_only"]
    d = np.r_[-np.ones(r), np.ones(c), np.zeros(table["n"] - r - c)]
    return d, np.ones(table["n"])


def frame_bounds(table: dict, n: np.ndarray, fp_cap: float = FP_CAP) -> FrameBounds:
    """What one frame of this criterion can change (:class:`FrameBounds`): recall rows all
    the objects of a frame, at most the largest guard frame's; false-positive rows ``fp_cap``."""
    return FrameBounds(table.get("kind", "recall"), float(n.max(initial=0.0)), fp_cap)


def _count_row(t: dict, margin: float, a_within: float, a_beyond: float, fp_cap: float) -> dict:
    d, n = frame_changes(t)
    bounds = frame_bounds(t, n, fp_cap)
    row = {k: v for k, v in t.items() if not k.startswith("frame_")}
    row |= {
        "kind": t.get("kind", "recall"),
        "diff": 100.0 * float(d.sum() / n.sum()) if n.sum() else 0.0,
        "margin": margin,
        "bound": bounds.cap if bounds.kind == "fp" else bounds.n_max,
        "mcnemar_p": mcnemar_p(t["ref_only"], t["cand_only"]),
    }
    if bounds.kind == "fp" and np.abs(d).max(initial=0.0) > fp_cap:
        row["over_cap"] = int(np.abs(d).max())
    if not n.sum():
        return row | {
            "within_interval": [-math.inf, math.inf],
            "beyond_interval": [-math.inf, math.inf],
            "status": "undecided",
        }
    x = margin / 100.0
    if bool(fb.rejects(d, n, x, bounds, a_beyond) or fb.rejects(-d, n, x, bounds, a_beyond)):
        status = "beyond"
    elif bool(fb.rejects(d, n, -x, bounds, a_within) and fb.rejects(-d, n, -x, bounds, a_within)):
        status = "within"
    else:
        status = "undecided"
    return row | {
        "within_interval": list(fb.interval(d, n, bounds, a_within, (-margin, margin))),
        "beyond_interval": list(fb.interval(d, n, bounds, a_beyond, (margin, -margin))),
        "status": status,
    }


def _ap_row(entry: dict, margin: float, a_within: float, a_beyond: float) -> dict:
    diff, se = float(entry["diff"]), float(entry["se"])
    w, b = float(ndtri(1 - a_within)) * se, float(ndtri(1 - a_beyond)) * se
    if diff - b > margin or diff + b < -margin:
        status = "beyond"
    elif -margin <= diff - w and diff + w <= margin:
        status = "within"
    else:
        status = "undecided"
    return {
        "kind": "ap",
        "diff": diff,
        "se": se,
        "margin": margin,
        "within_interval": [diff - w, diff + w],
        "beyond_interval": [diff - b, diff + b],
        "status": status,
    }


def _frames_needed(
    row: dict, table: dict | None, frames: int, a_within: float, a_beyond: float, fp_cap: float
) -> int | None:
    """Frames at which this open criterion would decide (next look's levels): count criteria
    if the guard frames came again in the same order (:func:`frame_betting.frames_to_reject`
    of each test that must reject), AP entries if the bootstrap's standard error times
    sqrt(frames) held; None if no affordable number would."""
    margin, diff = row["margin"], row["diff"]
    within = abs(diff) < margin
    if row["kind"] == "ap":
        gap = margin - abs(diff) if within else abs(diff) - margin
        if gap <= 0 or row["se"] == 0:
            return None
        z = ndtri(1 - (a_within if within else a_beyond))
        return math.ceil(frames * (z * row["se"] / gap) ** 2)
    d, n = frame_changes(table)
    if not n.sum() or abs(diff) == margin:
        return None
    bounds, x = frame_bounds(table, n, fp_cap), margin / 100.0
    if within:
        needs = [fb.frames_to_reject(s * d, n, -x, bounds, a_within) for s in (1, -1)]
        return None if None in needs else max(needs)
    return fb.frames_to_reject(np.sign(diff) * d, n, x, bounds, a_beyond)


def decide(
    tables: dict[str, dict],
    frames: int,
    margin: float = MARGIN,
    alpha: float = ALPHA,
    look: int = 1,
    ap: dict[str, dict] | None = None,
    ap_margin: float = AP_MARGIN,
    fp_cap: float = FP_CAP,
) -> dict:
    """The rule of the module docstring over every criterion.

    Args:
      tables: ``{"Car moderate 3d@0.70": table, ...}``
        (:func:`~gac_jax.guard.criteria.guard_tables`, with per-frame counts).
      frames: the frames the tables come from.
      look: which guard run of this model and candidate this is (1, 2, ...).
      ap: ``{"Car AP40 3d@0.70 moderate": {'diff', 'se'}, ...}``
        (:func:`~gac_jax.guard.ap_bootstrap.paired_ap_bootstrap`), or None.
      fp_cap: false positives one frame may gain or lose (:class:`FrameBounds`).

    Returns:
      ``{'verdict': 'within'|'beyond'|'undecided', 'reason': one line, 'deciding', 'margin',
      'ap_margin', 'alpha', 'look', 'alpha_look', 'frames', 'fp_cap', 'frames_needed'
      (undecided only), 'criteria': {name: {'kind': recall|fp|ap, 'diff', 'margin',
      'within_interval', 'beyond_interval', 'status', ...}}}``; count rows also carry the
      table, ``bound`` (the per-frame bound: largest frame or ``fp_cap``), ``over_cap`` (a
      false-positive row with a frame beyond the cap: its largest change), ``mcnemar_p`` and
      ``holm_p``, AP rows ``se``. Differences in points; an interval side is infinite where
      the frames break the bound it needs.
    """
    ap = ap or {}
    k = len(tables) + len(ap)
    a = look_alpha(alpha, look)
    rows = {n: _count_row(t, margin, a, a / (2 * k), fp_cap) for n, t in tables.items()}
    rows |= {n: _ap_row(e, ap_margin, a, a / (2 * k)) for n, e in ap.items()}
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
        "fp_cap": fp_cap,
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
    needs = {
        n: _frames_needed(rows[n], tables.get(n), frames, a_next, a_next / (2 * k), fp_cap)
        for n in open_
    }
    unknown = [n for n in open_ if needs[n] is None]
    if unknown:  # a criterion over the cap first: the user can act on it
        deciding = next((n for n in unknown if "over_cap" in rows[n]), unknown[0])
    else:
        deciding = max(needs, key=needs.get)
    frames_needed = needs[deciding]
    r = rows[deciding]
    if frames_needed is not None:
        needed_text = f"about {frames_needed} frames would decide it at look {look + 1}"
    elif "over_cap" in r:
        needed_text = (
            f"a frame's false positives changed by {r['over_cap']}, more than the {fp_cap} "
            "per frame the guarantee assumes (--fp-cap)"
        )
    else:
        needed_text = "no affordable number of frames would decide it at the observed rates"

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
