"""HOTA (Luiten et al., IJCV 2021): detection, association and localisation accuracy.

For each localisation threshold alpha in 0.05, 0.10, ..., 0.95:

* Per frame, ground truth and tracker boxes are matched (Hungarian) maximising
  ``A(g, t) * S(g, t)``, where S is the box similarity and A the global alignment of the
  two ids over the sequence: ``A = Σ_f s'(g, t) / (n_g + n_t - Σ_f s'(g, t))``, with
  ``s' = S / (row sum + column sum - S)`` in each frame (a soft count of co-occurrences)
  and n the number of boxes of each id. A matched pair with ``S >= alpha`` is a TP.
* ``DetA = TP / (TP + FN + FP)``; per TP, the association IoU of its two ids,
  ``TPA / (TPA + FNA + FPA) = c / (n_g + n_t - c)`` with c the TPs of that id pair;
  ``AssA`` = mean over TPs; ``HOTA = sqrt(DetA * AssA)``; ``LocA`` = mean S over TPs.

Reported figures are means over the 19 alphas. Sequences combine by summing TP/FN/FP and
the per-TP sums (association, localisation), i.e. weighted by TPs.
"""

from __future__ import annotations

import numpy as np

from gac_jax.evaluation.tracking.frame_matching import EPS
from gac_jax.evaluation.tracking.kitti_rules import ClassSequence

ALPHAS = np.arange(0.05, 0.99, 0.05)  # the 19 thresholds, as the official code spells them
SUM_FIELDS = ("tp", "fn", "fp", "loc", "ass", "ass_re", "ass_pr")


def hota_sums(seq: ClassSequence) -> dict[str, np.ndarray]:
    """Per-alpha sums (each (19,)) of one sequence: TP, FN, FP and, over TPs, the
    similarity (``loc``), association IoU (``ass``), recall (``ass_re``), precision (``ass_pr``)."""
    n_a = ALPHAS.size
    out = {k: np.zeros(n_a) for k in SUM_FIELDS}
    n_gt, n_tr = seq.gt_frame.size, seq.tr_frame.size
    if n_gt == 0 or n_tr == 0:
        out["fn"][:] = n_gt
        out["fp"][:] = n_tr
        return out
    g, t, s = seq.pair_gt, seq.pair_tr, seq.pair_sim
    row = np.bincount(g, weights=s, minlength=n_gt)
    col = np.bincount(t, weights=s, minlength=n_tr)
    denom = row[g] + col[t] - s
    soft = np.where(denom > EPS, s / np.where(denom > EPS, denom, 1.0), 0.0)
    gid, tid = seq.gt_id[g], seq.tr_id[t]
    potential = np.zeros((seq.num_gt_ids, seq.num_tr_ids))
    np.add.at(potential, (gid, tid), soft)
    n_g = np.bincount(seq.gt_id, minlength=seq.num_gt_ids).astype(np.float64)
    n_t = np.bincount(seq.tr_id, minlength=seq.num_tr_ids).astype(np.float64)
    alignment = potential / (n_g[:, None] + n_t[None, :] - potential)
    matched = seq.blocks().match(alignment[gid, tid] * s)

    ms, mg, mt = s[matched], gid[matched], tid[matched]
    hit = ms[None, :] >= ALPHAS[:, None] - EPS  # (19, M)
    tp = hit.sum(axis=1).astype(np.float64)
    out["tp"] = tp
    out["fn"] = n_gt - tp
    out["fp"] = n_tr - tp
    out["loc"] = (hit * ms[None, :]).sum(axis=1)
    # TPs per (alpha, id pair): count c, then each TP contributes c / (n_g + n_t - c) etc.
    pair_code = mg * seq.num_tr_ids + mt
    codes, inverse = np.unique(pair_code, return_inverse=True)
    a_idx = np.nonzero(hit)[0]
    key = a_idx * codes.size + inverse[np.nonzero(hit)[1]]
    counts = np.bincount(key, minlength=n_a * codes.size).reshape(n_a, codes.size)
    cg, ct = n_g[codes // seq.num_tr_ids], n_t[codes % seq.num_tr_ids]
    out["ass"] = (counts * counts / np.maximum(1.0, cg + ct - counts)).sum(axis=1)
    out["ass_re"] = (counts * counts / np.maximum(1.0, cg)).sum(axis=1)
    out["ass_pr"] = (counts * counts / np.maximum(1.0, ct)).sum(axis=1)
    return out


def combine_hota(sums: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Sums the per-sequence sums of :func:`hota_sums`."""
    return {k: np.sum([s[k] for s in sums], axis=0) for k in SUM_FIELDS} if sums else None


def hota_metrics(total: dict[str, np.ndarray]) -> dict:
    """HOTA figures from (combined) sums: ``HOTA, DetA, AssA, DetRe, DetPr, AssRe, AssPr,
    LocA`` (means over alpha, in [0, 1]), ``HOTA(0)``, ``LocA(0)`` (alpha 0.05), and the
    per-alpha curves under ``"curves"``."""
    tp, fn, fp = total["tp"], total["fn"], total["fp"]
    curves = {
        "DetRe": tp / np.maximum(1.0, tp + fn),
        "DetPr": tp / np.maximum(1.0, tp + fp),
        "DetA": tp / np.maximum(1.0, tp + fn + fp),
        "AssA": total["ass"] / np.maximum(1.0, tp),
        "AssRe": total["ass_re"] / np.maximum(1.0, tp),
        "AssPr": total["ass_pr"] / np.maximum(1.0, tp),
        "LocA": np.maximum(1e-10, total["loc"]) / np.maximum(1e-10, tp),
    }
    curves["HOTA"] = np.sqrt(curves["DetA"] * curves["AssA"])
    out = {k: float(np.mean(v)) for k, v in curves.items()}
    out["HOTA(0)"] = float(curves["HOTA"][0])
    out["LocA(0)"] = float(curves["LocA"][0])
    out["curves"] = {
        "alpha": [round(float(a), 2) for a in ALPHAS],
        **{k: v.tolist() for k, v in curves.items()},
    }
    return out
