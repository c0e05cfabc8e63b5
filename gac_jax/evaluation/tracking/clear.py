"""CLEAR MOT (Bernardin & Stiefelhagen, 2008) with MT/PT/ML (Li et al., 2009), as the
KITTI tracking benchmark computes them.

Per frame, ground truth and tracker boxes with similarity >= 0.5 are matched (Hungarian),
preferring to continue the previous frame's matches (a continued pair outweighs any
similarity). A frame that has no ground truth or no tracker box of the class is counted
(FN or FP) but does not interrupt "the previous frame" for the matches around it, as in
the official evaluation.

* ``MOTA = (TP - FP - IDSW) / (TP + FN)``, ``MODA`` without IDSW; ``MOTP`` mean similarity
  of TPs; ``sMOTA = (Σ similarity - FP - IDSW) / (TP + FN)``.
* IDSW: a ground-truth id matched to a tracker id other than the one it was last matched to.
* Frag: a ground-truth id becoming tracked again after not being tracked in the previous
  frame (its first start excluded).
* MT / PT / ML: ids tracked in > 80 %, 20-80 %, < 20 % of their frames.
"""

from __future__ import annotations

import numpy as np

from gac_jax.evaluation.tracking.frame_matching import EPS, unambiguous
from gac_jax.evaluation.tracking.kitti_rules import ClassSequence

THRESHOLD = 0.5
CONTINUITY_BONUS = 1000.0
COUNT_FIELDS = ("TP", "FN", "FP", "IDSW", "MT", "PT", "ML", "Frag", "MOTP_sum", "Frames")


def clear_match(seq: ClassSequence, threshold: float = THRESHOLD) -> np.ndarray:
    """(P,) bool: the CLEAR matches among the sequence's pairs (see the module docstring)."""
    valid = seq.pair_sim >= threshold - EPS
    n_gt, n_tr = seq.gt_frame.size, seq.tr_frame.size
    matched = unambiguous(seq.pair_gt, seq.pair_tr, valid, n_gt, n_tr)
    blocks = seq.blocks()
    ambiguous = blocks.ambiguous_frames(valid)
    if ambiguous.size == 0:
        return matched
    processed = np.flatnonzero((np.diff(seq.gt_start) > 0) & (np.diff(seq.tr_start) > 0))
    last_tracker = np.full(seq.num_gt_ids, -1, np.int64)
    for frame in ambiguous:
        frame = int(frame)
        lo, hi = blocks.pair_start[frame], blocks.pair_start[frame + 1]
        matched[lo:hi] = False
        k = np.searchsorted(processed, frame)
        last_tracker[:] = -1
        if k > 0:
            p = processed[k - 1]
            m = np.flatnonzero(matched[blocks.pair_start[p] : blocks.pair_start[p + 1]])
            m += blocks.pair_start[p]
            last_tracker[seq.gt_id[seq.pair_gt[m]]] = seq.tr_id[seq.pair_tr[m]]
        weight = np.zeros_like(seq.pair_sim)
        g, t = seq.pair_gt[lo:hi], seq.pair_tr[lo:hi]
        cont = last_tracker[seq.gt_id[g]] == seq.tr_id[t]
        weight[lo:hi] = np.where(valid[lo:hi], CONTINUITY_BONUS * cont + seq.pair_sim[lo:hi], 0.0)
        matched[blocks.assign(frame, weight)] = True
    return matched


def clear_counts(seq: ClassSequence, matched: np.ndarray | None = None) -> dict[str, float]:
    """CLEAR counts of one sequence (``COUNT_FIELDS``); ``matched`` from :func:`clear_match`."""
    n_gt, n_tr = seq.gt_frame.size, seq.tr_frame.size
    out = dict.fromkeys(COUNT_FIELDS, 0.0)
    out["Frames"] = float(seq.n_frames)
    if matched is None:
        matched = clear_match(seq) if n_gt and n_tr else np.zeros(seq.pair_sim.size, bool)
    m = np.flatnonzero(matched)
    gid = seq.gt_id[seq.pair_gt[m]]
    tid = seq.tr_id[seq.pair_tr[m]]
    frame = seq.gt_frame[seq.pair_gt[m]]
    order = np.lexsort((frame, gid))
    gid, tid, frame = gid[order], tid[order], frame[order]
    same = gid[1:] == gid[:-1]
    processed = (np.diff(seq.gt_start) > 0) & (np.diff(seq.tr_start) > 0)
    rank = np.cumsum(processed) - 1  # index of each frame among the processed frames
    continued = same & (rank[frame[1:]] == rank[frame[:-1]] + 1)
    starts = np.bincount(gid, minlength=seq.num_gt_ids) - np.bincount(
        gid[1:][continued], minlength=seq.num_gt_ids
    )
    n_tracked = np.bincount(seq.gt_id, minlength=seq.num_gt_ids)
    ratio = np.bincount(gid, minlength=seq.num_gt_ids) / np.maximum(n_tracked, 1)
    mt = int((ratio > 0.8).sum())
    pt = int((ratio >= 0.2).sum()) - mt
    out.update(
        TP=float(m.size),
        FN=float(n_gt - m.size),
        FP=float(n_tr - m.size),
        IDSW=float((same & (tid[1:] != tid[:-1])).sum()),
        MT=float(mt),
        PT=float(pt),
        ML=float(seq.num_gt_ids - mt - pt),
        Frag=float(np.maximum(starts - 1, 0).sum()),
        MOTP_sum=float(seq.pair_sim[m].sum()),
    )
    return out


def clear_metrics(total: dict[str, float]) -> dict[str, float]:
    """MOTA, MOTP, MODA, sMOTA, CLR_Re, CLR_Pr, CLR_F1, MTR, PTR, MLR from summed counts,
    with the counts (``TP FN FP IDSW MT PT ML Frag``)."""
    tp, fn, fp, idsw = total["TP"], total["FN"], total["FP"], total["IDSW"]
    n_ids = max(1.0, total["MT"] + total["PT"] + total["ML"])
    gt = max(1.0, tp + fn)
    out = {
        "MOTA": (tp - fp - idsw) / gt,
        "MOTP": total["MOTP_sum"] / max(1.0, tp),
        "MODA": (tp - fp) / gt,
        "sMOTA": (total["MOTP_sum"] - fp - idsw) / gt,
        "CLR_Re": tp / gt,
        "CLR_Pr": tp / max(1.0, tp + fp),
        "CLR_F1": tp / max(1.0, tp + 0.5 * fn + 0.5 * fp),
        "MTR": total["MT"] / n_ids,
        "PTR": total["PT"] / n_ids,
        "MLR": total["ML"] / n_ids,
    }
    for k in ("TP", "FN", "FP", "IDSW", "MT", "PT", "ML", "Frag"):
        out[k] = int(total[k])
    return out
