"""3D MOT figures as AB3DMOT's own evaluation script counts them: the figures papers report.

sAMOTA, AMOTA, AMOTP and MOTA as ``scripts/KITTI/evaluate.py`` of AB3DMOT (Weng et al., IROS
2020) computes them, the script behind the sAMOTA figures published on KITTI. It builds on the
KITTI tracking devkit's code from before TrackEval; these are its rules, written from what it
does. For one class at a 3D IoU threshold, per sequence:

1. **Lines.** The label and result lines whose class name *contains* one of the class's names
   (car: ``car``, ``van``; pedestrian: ``pedestrian``, ``person_sitting``; cyclist:
   ``cyclist``) or ``dontcare``, except those with track id -1 that are not DontCare. So the
   tracking benchmark's sitting person (``Person``) is not read for pedestrians, and a
   result line of a Van (or DontCare) is matched like a box of the class.
2. **Track scores.** A result track's score is the mean of its lines' scores; a pass at a
   score threshold drops the tracks scoring below it. (The script overwrites the lines'
   scores with that mean and takes the mean again in every pass: in floating point a track
   can fall an ulp below its own score, the threshold, and be dropped at it. Reproduced as
   CPython 3.11's ``sum`` adds; Python 3.12's compensated ``sum`` may change such a case.)
3. **Matching**, per frame: the ground truth (DontCare regions apart) and the result boxes
   with 3D IoU >= the threshold, by the Hungarian algorithm on ``1 - IoU``: the most pairs,
   then the largest IoU sum. No preference for continuing the previous frame's pairs.
4. **Ignored.** Ground truth occluded above level 2, truncated above level 0 or of the
   distractor class (Van; person_sitting). Unmatched result boxes of the distractor class,
   at most 25 px high or more than half (of their own area) inside a DontCare region --
   unless matched in an *earlier pass*: the script marks a matched result box and never
   clears the mark, over its passes in the order below.
5. **Counts.** TP: the matched pairs (also those of ignored ground truth); FN: unmatched
   ground truth not ignored; FP: result boxes neither matched nor ignored; N: ground truth not
   ignored. IDSW: a ground-truth track matched to another result track than at its previous
   appearance, both matched and neither ignored (the first appearance counts as not ignored);
   a switch across a missed or ignored appearance is not counted.
   ``MOTA = 1 - (FN + FP + IDSW) / N``; MOTP: the mean IoU of the TPs;
   ``sMOTA_r = clip(1 - (FN + FP + IDSW - (1 - r) N) / (r N), 0, 1)``.
6. **Passes.** The first, with every track, gives the TP scores and ``TP + FN``; the KITTI
   devkit's ``getThresholds`` takes the TP scores closest to the recalls ``r = 1/40 ... 1``
   (:func:`~gac_jax.evaluation.kitti_object.get_thresholds`). One pass per threshold, in
   that (decreasing) order: ``sAMOTA = Σ sMOTA_r / 40``, ``AMOTA = Σ MOTA_r / 40``,
   ``AMOTP = Σ MOTP_r / 40``. MOTA is the script's "best results with a single threshold":
   a last pass at the threshold of the highest MOTA (every track if none is above 0).

Counts are summed over the sequences. Two departures: a line without a 3D box (dimensions or
location unset) has IoU 0 here, where the script computes an IoU of the unset numbers; a
ground-truth track id twice in one frame is refused (as by the other rule), where the script
reads it (it refuses such result lines only).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.evaluation.kitti_object import get_thresholds, same_frame_pairs
from gac_jax.evaluation.rotated_iou import box2d_overlap_pairs
from gac_jax.evaluation.tracking.frame_matching import FrameBlocks, starts
from gac_jax.evaluation.tracking.kitti_rules import check_unique, similarity_3d
from gac_jax.evaluation.tracking.tracking_files import TrackRows

# names a line's class must contain to be read for a class, and the class's distractor
READ_NAMES = {"car": ("car", "van"), "pedestrian": ("pedestrian", "person_sitting")}
READ_NAMES["cyclist"] = ("cyclist",)
DISTRACTOR = {"car": "van", "pedestrian": "person_sitting", "cyclist": None}
MAX_OCCLUSION, MAX_TRUNCATION, MIN_HEIGHT, DONTCARE_OVERLAP = 2, 0, 25.0, 0.5
RECALL_STEPS = 40
ALL_TRACKS = -10000.0  # the script's threshold of its first pass


def read_rows(rows: TrackRows, cls: str) -> np.ndarray:
    """Indices of the lines of ``rows`` the script reads for ``cls`` (rule 1), file order."""
    names = (*READ_NAMES[cls], "dontcare")
    hit = np.zeros(len(rows), bool)
    for name in names:
        hit |= np.char.find(rows.type.astype(str), name) >= 0
    return np.flatnonzero(hit & ~((rows.track_id == -1) & (rows.type != "dontcare")))


@dataclasses.dataclass
class _Sequence:
    """One sequence of one class: G ground truth, T result boxes (by frame, then file
    order), their P same-frame pairs with a valid IoU."""

    blocks: FrameBlocks
    pair_gt: np.ndarray  # (P,)
    pair_tr: np.ndarray
    pair_iou: np.ndarray
    gt_ignored: np.ndarray  # (G,) bool
    gt_trajectory: np.ndarray  # (G,) order of the boxes by (track id, frame, file order)
    gt_first: np.ndarray  # (G,) bool, in that order: a track's first appearance
    tr_id: np.ndarray  # (T,) raw track id
    tr_score: np.ndarray  # (T,) the score the script holds for the box (rule 2), updated
    tr_track: np.ndarray  # (T,) index of the box's track; track_rows: (K, longest) its boxes
    track_rows: np.ndarray  # (-1 past a track's end), in the script's order
    tr_ignorable: np.ndarray  # (T,) bool: ignored when unmatched and never matched before
    weight_scale: float


def _prepare(seq, cls: str, iou_threshold: float) -> _Sequence:
    gt, tr = seq.labels, seq.results
    g_read, t_read = read_rows(gt, cls), read_rows(tr, cls)
    check_unique(tr.frame[t_read], tr.track_id[t_read], tr.line[t_read], seq.result_path, cls)
    dc = g_read[gt.type[g_read] == "dontcare"]
    g = g_read[gt.type[g_read] != "dontcare"]
    check_unique(gt.frame[g], gt.track_id[g], gt.line[g], seq.label_path, "ground-truth")
    g = g[np.argsort(gt.frame[g], kind="stable")]
    t = t_read[np.argsort(tr.frame[t_read], kind="stable")]
    dc = dc[np.argsort(gt.frame[dc], kind="stable")]
    n = seq.n_frames
    a, b = same_frame_pairs(gt.frame[g], tr.frame[t], n)
    iou = similarity_3d(gt, tr, g[a], t[b]) if a.size else np.zeros(0)
    valid = (1.0 - iou) <= (1.0 - iou_threshold)  # the script's gate on the cost
    distractor = DISTRACTOR[cls]
    gt_ignored = (gt.occlusion[g] > MAX_OCCLUSION) | (gt.truncation[g] > MAX_TRUNCATION)
    gt_ignored |= gt.type[g] == distractor
    box = tr.box2d[t]
    ignorable = (tr.type[t] == distractor) | (np.abs(box[:, 1] - box[:, 3]) <= MIN_HEIGHT)
    c, d = same_frame_pairs(tr.frame[t], gt.frame[dc], n)
    if c.size:
        ioa = box2d_overlap_pairs(box[c], gt.box2d[dc[d]], criterion=0)
        ignorable[c[ioa > DONTCARE_OVERLAP]] = True
    _, track = np.unique(tr.track_id[t], return_inverse=True)
    order = np.argsort(track, kind="stable")  # a track's boxes by frame, then file order
    counts = np.bincount(track)
    rank = np.arange(t.size) - np.repeat(np.cumsum(counts) - counts, counts)
    track_rows = np.full((counts.size, counts.max(initial=0)), -1, np.int64)
    track_rows[track[order], rank] = order
    trajectory = np.lexsort((np.arange(g.size), gt.frame[g], gt.track_id[g]))
    first = np.ones(g.size, bool)
    first[1:] = gt.track_id[g][trajectory][1:] != gt.track_id[g][trajectory][:-1]
    pair_frame = gt.frame[g][a[valid]]
    return _Sequence(
        blocks=FrameBlocks(
            starts(gt.frame[g], n), starts(tr.frame[t], n), pair_frame, a[valid], b[valid]
        ),
        pair_gt=a[valid],
        pair_tr=b[valid],
        pair_iou=iou[valid],
        gt_ignored=gt_ignored,
        gt_trajectory=trajectory,
        gt_first=first,
        tr_id=tr.track_id[t],
        tr_score=tr.score[t].copy(),
        tr_track=track,
        track_rows=track_rows,
        tr_ignorable=ignorable,
        weight_scale=float(g.size + t.size + 1),
    )


COUNTS = ("TP", "FN", "FP", "IDSW", "N", "IoU_sum", "TP_scored")


def _track_means(s: _Sequence) -> None:
    """Sets each box's score to its track's mean score, as every pass of the script does:
    from the scores the previous pass left (it overwrites them), summed one after another in
    the script's order (CPython 3.11's ``sum``), so that a track can fall an ulp below its
    own threshold as it does there."""
    if not s.tr_score.size:
        return
    values = np.where(s.track_rows >= 0, s.tr_score[s.track_rows], 0.0)
    sums = np.cumsum(values, axis=1)[:, -1]  # sequential: adding the 0.0 padding is exact
    s.tr_score = (sums / (s.track_rows >= 0).sum(axis=1))[s.tr_track]


def _pass(s: _Sequence, threshold: float, marked: np.ndarray, means: bool):
    """The counts of one pass at score ``threshold`` (``means``: take the tracks' means again
    first); ``marked`` (T,): boxes matched in an earlier pass, updated in place. Returns
    (counts, the TPs' track scores, which of them are on scored ground truth)."""
    if means:
        _track_means(s)
    keep = ~(s.tr_score < threshold)
    # the most pairs first, then the largest IoU sum (rule 3)
    weight = np.where(keep[s.pair_tr], s.weight_scale + s.pair_iou, 0.0)
    matched = s.blocks.match(weight)
    m_gt, m_tr = s.pair_gt[matched], s.pair_tr[matched]
    marked[m_tr] = True
    tracker = np.full(s.gt_ignored.size, -1, np.int64)
    tracker[m_gt] = s.tr_id[m_tr]
    tp = int(matched.sum())
    unmatched_gt = np.ones(s.gt_ignored.size, bool)
    unmatched_gt[m_gt] = False
    ignored_tr = int((keep & ~marked & s.tr_ignorable).sum())
    # identity switches along each ground-truth track (rule 5)
    g, ign, first = tracker[s.gt_trajectory], s.gt_ignored[s.gt_trajectory], s.gt_first
    prev_ok = first[:-1] | ~ign[:-1]
    switch = (~first[1:]) & (g[1:] != -1) & (g[:-1] != -1) & (g[1:] != g[:-1])
    switch &= ~ign[1:] & prev_ok
    counts = {
        "TP": tp,
        "FN": int((unmatched_gt & ~s.gt_ignored).sum()),
        "FP": int(keep.sum()) - tp - ignored_tr,
        "IDSW": int(switch.sum()),
        "N": int((~s.gt_ignored).sum()),
        "IoU_sum": float(s.pair_iou[matched].sum()),
        "TP_scored": int((~s.gt_ignored[m_gt]).sum()),
    }
    return counts, s.tr_score[m_tr], ~s.gt_ignored[m_gt]


def _run_pass(seqs, marks, threshold: float, means: bool = True):
    total = dict.fromkeys(COUNTS, 0)
    scores, scored = [np.zeros(0)], [np.zeros(0, bool)]
    for s, marked in zip(seqs, marks, strict=True):
        counts, tp_scores, on_scored = _pass(s, threshold, marked, means)
        scores.append(tp_scores)
        scored.append(on_scored)
        for k in COUNTS:
            total[k] += counts[k]
    return total, np.concatenate(scores), np.concatenate(scored)


def _figures(c: dict, recall: float = 1.0) -> tuple[float, float, float]:
    """(MOTA, MOTP, sMOTA at ``recall``) of summed counts (``N`` > 0)."""
    motp = c["IoU_sum"] / c["TP"] if c["TP"] else 0.0
    errors = c["FN"] + c["FP"] + c["IDSW"]
    smota = 1.0 - (errors - (1.0 - recall) * c["N"]) / (recall * c["N"])
    return 1.0 - errors / c["N"], motp, min(1.0, max(0.0, smota))


def ab3dmot_metrics(
    sequences, cls: str, iou: float, *, score_drift: bool = True, scored_recall: bool = False
) -> dict:
    """AB3DMOT's script's figures (module docstring) for ``cls`` (``"car"``, ``"pedestrian"``
    or ``"cyclist"``) at 3D IoU ``iou`` over :class:`TrackingSequence` s.

    Two departures from the script, to measure what its rules cost
    (benchmarks/mot3d_rule_gap.py): ``score_drift=False`` takes the tracks' mean scores once
    (rule 2); ``scored_recall=True`` takes the thresholds over the true positives on scored
    ground truth only, as TrackEval's counting does (rule 6).

    Returns:
      ``{sAMOTA, AMOTA, AMOTP, MOTA, MOTP, thresholds, threshold}``: MOTA and MOTP of the pass
      at the best single score ``threshold`` (None: every track); ``thresholds``: the number
      of score thresholds. Without ground truth to score, every figure is None.
    """
    seqs = [_prepare(s, cls, iou) for s in sequences]
    marks = [np.zeros(s.tr_id.size, bool) for s in seqs]
    first, scores, scored = _run_pass(seqs, marks, ALL_TRACKS)
    if first["N"] == 0:  # no ground truth to score (the script's MOTA would be -inf)
        keys = ("sAMOTA", "AMOTA", "AMOTP", "MOTA", "MOTP", "threshold")
        return {**dict.fromkeys(keys), "thresholds": 0}
    if scored_recall:
        scores, first["TP"] = scores[scored], first["TP_scored"]
    thresholds = get_thresholds(scores, first["TP"] + first["FN"])[1:]
    sums = {"sMOTA": 0.0, "MOTA": 0.0, "MOTP": 0.0}
    best_mota, best = 0.0, ALL_TRACKS
    recall = 0.0
    for threshold in thresholds:
        recall += 1.0 / RECALL_STEPS  # accumulated as the devkit does
        counts = _run_pass(seqs, marks, float(threshold), score_drift)[0]
        mota, motp, smota = _figures(counts, recall)
        sums["sMOTA"] += smota
        sums["MOTA"] += mota
        sums["MOTP"] += motp
        if mota > best_mota:
            best_mota, best = mota, float(threshold)
    mota, motp, _ = _figures(_run_pass(seqs, marks, best, score_drift)[0])
    return {
        "sAMOTA": sums["sMOTA"] / RECALL_STEPS,
        "AMOTA": sums["MOTA"] / RECALL_STEPS,
        "AMOTP": sums["MOTP"] / RECALL_STEPS,
        "MOTA": mota,
        "MOTP": motp,
        "thresholds": int(thresholds.size),
        "threshold": None if best == ALL_TRACKS else best,
    }
