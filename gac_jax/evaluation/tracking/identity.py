"""Identity metrics (Ristani et al., 2016): IDF1, IDP, IDR.

Each ground-truth id is assigned to at most one tracker id for the whole sequence so that the
number of frames where the two are matched (similarity >= 0.5) is maximal. Those frames are
IDTP; the other ground-truth boxes IDFN, the other tracker boxes IDFP.
``IDF1 = IDTP / (IDTP + (IDFP + IDFN) / 2)``, ``IDP = IDTP / (IDTP + IDFP)``,
``IDR = IDTP / (IDTP + IDFN)``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from gac_jax.evaluation.tracking.kitti_rules import ClassSequence

THRESHOLD = 0.5
COUNT_FIELDS = ("IDTP", "IDFN", "IDFP")


def identity_counts(seq: ClassSequence, threshold: float = THRESHOLD) -> dict[str, float]:
    """IDTP, IDFN, IDFP of one sequence."""
    n_gt, n_tr = seq.gt_frame.size, seq.tr_frame.size
    idtp = 0.0
    if n_gt and n_tr:
        hit = seq.pair_sim >= threshold
        together = np.zeros((seq.num_gt_ids, seq.num_tr_ids))
        np.add.at(together, (seq.gt_id[seq.pair_gt[hit]], seq.tr_id[seq.pair_tr[hit]]), 1.0)
        rows, cols = linear_sum_assignment(-together)
        idtp = float(together[rows, cols].sum())
    return {"IDTP": idtp, "IDFN": n_gt - idtp, "IDFP": n_tr - idtp}


def identity_metrics(total: dict[str, float]) -> dict[str, float]:
    """IDF1, IDP, IDR and the counts from summed counts."""
    tp, fn, fp = total["IDTP"], total["IDFN"], total["IDFP"]
    return {
        "IDF1": tp / max(1.0, tp + 0.5 * fp + 0.5 * fn),
        "IDP": tp / max(1.0, tp + fp),
        "IDR": tp / max(1.0, tp + fn),
        "IDTP": int(tp),
        "IDFN": int(fn),
        "IDFP": int(fp),
    }
