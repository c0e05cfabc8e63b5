"""3D MOT metrics of AB3DMOT (Weng et al., IROS 2020) and the velocity error of tracks.

**sAMOTA, AMOTA, AMOTP** with TrackEval's counting (``--mot3d-rule trackeval``; AB3DMOT's own
script counts otherwise: :mod:`.ab3dmot_rules`). The boxes are matched by 3D IoU (threshold
0.25 or 0.5) with the CLEAR rules of :mod:`.clear` and the benchmark's ignore rules of
:mod:`.kitti_rules`. A
track's score is the mean score of its boxes. A first pass with every track gives the
scores of the true positives; as in AB3DMOT, the thresholds are the TP scores closest to
the recalls ``r = 1/40, 2/40, ..., 1`` (the KITTI devkit's ``getThresholds``). At each
threshold the tracks scoring below it are removed and CLEAR MOT is computed:

* ``sMOTA_r = clip(1 - (FN + FP + IDSW - (1 - r) * N) / (r * N), 0, 1)`` (N ground truth),
* ``sAMOTA = Σ_r sMOTA_r / 40``, ``AMOTA = Σ_r MOTA_r / 40``, ``AMOTP = Σ_r MOTP_r / 40``
  (MOTP: mean 3D IoU of TPs); recalls the tracker never reaches count 0.

**Velocity error.** The velocity of a box is the central difference of its track's positions
(bottom-centre, in the bird's-eye view ``x, z``) in the neighbouring frames (one-sided at a
track's ends; none for a single-frame track), times the frame rate. With ego poses
(camera-to-first-frame, ``X_0 = R X_k + t``) positions are in the world frame, so
velocities are over the ground; without, in the moving camera frame (relative to the ego).
The error of a CLEAR match (2D) is the norm of the difference of its two velocities.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.evaluation.kitti_object import get_thresholds
from gac_jax.evaluation.tracking.clear import clear_counts, clear_match
from gac_jax.evaluation.tracking.kitti_rules import (
    CLASS_NAMES,
    ClassSequence,
    prepare_class,
    similarity_3d,
)
from gac_jax.evaluation.tracking.tracking_files import TrackRows

MOT3D_IOUS = (0.25, 0.5)
RECALL_STEPS = 40


def subset_trackers(seq: ClassSequence, keep: np.ndarray) -> ClassSequence:
    """``seq`` with only the tracker boxes where ``keep`` (T,) is True (ids relabelled)."""
    new = np.cumsum(keep) - 1
    pair_keep = keep[seq.pair_tr]
    uniq, tr_id = np.unique(seq.tr_id[keep], return_inverse=True)
    tr_frame = seq.tr_frame[keep]
    return dataclasses.replace(
        seq,
        tr_frame=tr_frame,
        tr_id=tr_id.astype(np.int64),
        tr_row=seq.tr_row[keep],
        tr_start=np.concatenate([[0], np.cumsum(np.bincount(tr_frame, minlength=seq.n_frames))]),
        pair_gt=seq.pair_gt[pair_keep],
        pair_tr=new[seq.pair_tr[pair_keep]],
        pair_sim=seq.pair_sim[pair_keep],
        num_tr_ids=int(uniq.size),
    )


def track_mean_scores(rows: TrackRows, index: np.ndarray, cls: str) -> np.ndarray:
    """Mean score of the track of each row in ``index`` (over the track's rows of the class)."""
    mask = np.isin(rows.type, CLASS_NAMES[cls]) & (rows.track_id >= 0)
    ids, inverse = np.unique(rows.track_id[mask], return_inverse=True)
    sums = np.bincount(inverse, weights=rows.score[mask], minlength=ids.size)
    mean = sums / np.maximum(np.bincount(inverse, minlength=ids.size), 1)
    return mean[np.searchsorted(ids, rows.track_id[index])]


def smota(fn: float, fp: float, idsw: float, n_gt: float, recall: float) -> float:
    """AB3DMOT's scaled MOTA at a recall threshold ``recall`` (0 < recall <= 1)."""
    if n_gt <= 0:
        return 0.0
    value = 1.0 - (fn + fp + idsw - (1.0 - recall) * n_gt) / (recall * n_gt)
    return float(min(1.0, max(0.0, value)))


def _counts(prepared, iou: float, keeps=None) -> dict[str, float]:
    total = dict.fromkeys(("TP", "FN", "FP", "IDSW", "MOTP_sum"), 0.0)
    for i, seq in enumerate(prepared):
        if keeps is not None:
            seq = subset_trackers(seq, keeps[i])
        counts = clear_counts(seq, clear_match(seq, iou))
        for k in total:
            total[k] += counts[k]
    return total


def mot3d_metrics(sequences, cls: str, iou: float) -> dict:
    """sAMOTA, AMOTA, AMOTP (module docstring), MOTA of all tracks and the number of score
    thresholds, for one class at 3D IoU ``iou``, over :class:`TrackingSequence` s."""
    prepared = [
        prepare_class(s.labels, s.results, cls, s.n_frames, similarity=similarity_3d, match_iou=iou)
        for s in sequences
    ]
    scores = [
        track_mean_scores(s.results, p.tr_row, cls)
        for s, p in zip(sequences, prepared, strict=True)
    ]
    tp_scores, n_gt = [], 0.0
    for seq, sc in zip(prepared, scores, strict=True):
        matched = clear_match(seq, iou)
        tp_scores.append(sc[seq.pair_tr[matched]])
        n_gt += seq.gt_frame.size
    all_tracks = _counts(prepared, iou)
    gt = max(1.0, all_tracks["TP"] + all_tracks["FN"])
    mota_all = (all_tracks["TP"] - all_tracks["FP"] - all_tracks["IDSW"]) / gt
    thresholds = get_thresholds(np.concatenate(tp_scores), int(n_gt))[1:] if n_gt else []
    s_sum = a_sum = p_sum = 0.0
    for k, threshold in enumerate(thresholds, start=1):
        recall = k / RECALL_STEPS
        c = _counts(prepared, iou, [sc >= threshold for sc in scores])
        s_sum += smota(c["FN"], c["FP"], c["IDSW"], n_gt, recall)
        a_sum += (c["TP"] - c["FP"] - c["IDSW"]) / max(1.0, n_gt)
        p_sum += c["MOTP_sum"] / max(1.0, c["TP"])
    return {
        "sAMOTA": s_sum / RECALL_STEPS,
        "AMOTA": a_sum / RECALL_STEPS,
        "AMOTP": p_sum / RECALL_STEPS,
        "MOTA": mota_all,
        "thresholds": len(thresholds),
    }


def row_velocities(
    rows: TrackRows, frame_rate: float, poses: np.ndarray | None = None
) -> np.ndarray:
    """(N, 2) BEV velocity ``(vx, vz)`` (m/s) of each row from its track's (id and class)
    neighbours (NaN for rows without a 3D box, a negative id, or a track of one frame)."""
    pos = rows.location.copy()
    if poses is not None:
        pose = poses[rows.frame]
        pos = np.einsum("nij,nj->ni", pose[:, :, :3], pos) + pose[:, :, 3]
    bev = pos[:, [0, 2]]
    out = np.full((len(rows), 2), np.nan)
    ok = np.flatnonzero(rows.has_3d() & (rows.track_id >= 0))
    # a track is an id of one class (trackers may number each class on its own)
    _, type_code = np.unique(rows.type, return_inverse=True)
    track = rows.track_id * (int(type_code.max(initial=0)) + 1) + type_code
    order = ok[np.lexsort((rows.frame[ok], track[ok]))]
    tid, frame, p = track[order], rows.frame[order], bev[order]
    has_prev = np.zeros(order.size, bool)
    has_next = np.zeros(order.size, bool)
    link = (tid[1:] == tid[:-1]) & (frame[1:] == frame[:-1] + 1)
    has_prev[1:] = link
    has_next[:-1] = link
    prev = np.where(has_prev[:, None], np.roll(p, 1, axis=0), p)
    nxt = np.where(has_next[:, None], np.roll(p, -1, axis=0), p)
    span = has_prev.astype(np.float64) + has_next
    v = (nxt - prev) * frame_rate / np.maximum(span, 1.0)[:, None]
    out[order] = np.where((span > 0)[:, None], v, np.nan)
    return out


@dataclasses.dataclass(frozen=True)
class VelocityErrors:
    """Velocity errors (m/s) of matched boxes; ``frame``: ``"world"`` or ``"camera"``."""

    errors: np.ndarray
    frame: str

    @staticmethod
    def combine(parts: list[VelocityErrors]) -> VelocityErrors:
        frames = {p.frame for p in parts}
        frame = frames.pop() if len(frames) == 1 else "mixed"
        return VelocityErrors(np.concatenate([p.errors for p in parts]), frame)

    def as_dict(self) -> dict:
        e = self.errors
        stat = (lambda f: float(f(e))) if e.size else (lambda f: None)
        return {
            "frame": self.frame,
            "pairs": int(e.size),
            "mean": stat(np.mean),
            "median": stat(np.median),
            "p90": stat(lambda x: np.percentile(x, 90)),
        }


def velocity_errors(sequence, seq: ClassSequence, matched: np.ndarray, frame_rate: float):
    """:class:`VelocityErrors` of the CLEAR matches ``matched`` (P,) of ``seq`` (one class of
    the :class:`TrackingSequence` ``sequence``)."""
    poses = sequence.poses
    v_gt = row_velocities(sequence.labels, frame_rate, poses)
    v_tr = row_velocities(sequence.results, frame_rate, poses)
    m = np.flatnonzero(matched)
    d = v_tr[seq.tr_row[seq.pair_tr[m]]] - v_gt[seq.gt_row[seq.pair_gt[m]]]
    err = np.linalg.norm(d, axis=1)
    return VelocityErrors(err[np.isfinite(err)], "world" if poses is not None else "camera")
