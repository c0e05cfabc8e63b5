"""The KITTI tracking benchmark's rules: which boxes of one class and sequence are scored.

For a class (Car or Pedestrian), per frame, as the official evaluation (TrackEval's
``kitti_2d_box``) applies them:

1. Ground truth of the class and of its *distractor* classes (Van for Car; Person, i.e.
   a sitting person, for Pedestrian) is read; tracker boxes of the class only.
   DontCare lines are ignore regions; other lines with a negative track id are dropped.
2. Ground truth and tracker boxes are matched (Hungarian, similarity >= 0.5). A tracker box
   matched to a distractor, to ground truth occluded more than level 2 or truncated more
   than level 0 is removed (neither true nor false positive).
3. An unmatched tracker box is removed if it is at most 25 px high, or lies more than half
   (intersection over its own area) inside a DontCare region.
4. Distractor, occluded and truncated ground truth is dropped.

The similarity is the 2D box IoU (the benchmark's); the 3D MOT metrics use the same rules
with the 3D IoU and their own threshold in step 2 (DontCare and height stay in the image).
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np

from gac_jax.data.files import KittiFormatError
from gac_jax.evaluation.kitti_object import same_frame_pairs
from gac_jax.evaluation.rotated_iou import box2d_overlap_pairs, box3d_overlap_pairs
from gac_jax.evaluation.tracking.frame_matching import EPS, FrameBlocks, starts
from gac_jax.evaluation.tracking.tracking_files import TrackRows

CLASS_NAMES = {"car": ("car", "car_2"), "pedestrian": ("pedestrian",)}
# "person" is the tracking benchmark's sitting person; "person_sitting" the object benchmark's.
DISTRACTORS = {"car": ("van",), "pedestrian": ("person", "person_sitting")}
TRACKING_CLASSES = tuple(CLASS_NAMES)
MAX_OCCLUSION = 2
MAX_TRUNCATION = 0
MIN_HEIGHT = 25.0  # px; unmatched tracker boxes this high or lower are removed
DONTCARE_OVERLAP = 0.5  # intersection over the tracker box's area
MATCH_IOU = 0.5


@dataclasses.dataclass(frozen=True)
class ClassSequence:
    """The scored boxes of one class in one sequence (G ground truth, T tracker boxes, P pairs).

    Boxes are sorted by frame (file order within a frame). Ids are relabelled 0..n-1.

    Attributes:
      n_frames: frames of the sequence.
      gt_frame, gt_id, gt_row: (G,) frame, id, and line index in the label file's rows.
      tr_frame, tr_id, tr_row: (T,) the same for tracker boxes (rows of the result file).
      gt_start, tr_start: (n_frames + 1,) offsets of each frame's boxes.
      pair_gt, pair_tr, pair_sim: (P,) same-frame pairs with a positive similarity
        (indices into the G and T boxes), sorted by frame, and their similarity.
      num_gt_ids, num_tr_ids: distinct ids.
    """

    n_frames: int
    gt_frame: np.ndarray
    gt_id: np.ndarray
    gt_row: np.ndarray
    tr_frame: np.ndarray
    tr_id: np.ndarray
    tr_row: np.ndarray
    gt_start: np.ndarray
    tr_start: np.ndarray
    pair_gt: np.ndarray
    pair_tr: np.ndarray
    pair_sim: np.ndarray
    num_gt_ids: int
    num_tr_ids: int

    @property
    def pair_frame(self) -> np.ndarray:
        return self.gt_frame[self.pair_gt]

    def blocks(self) -> FrameBlocks:
        return FrameBlocks(
            self.gt_start, self.tr_start, self.pair_frame, self.pair_gt, self.pair_tr
        )


def similarity_2d(gt: TrackRows, tr: TrackRows, gi: np.ndarray, ti: np.ndarray) -> np.ndarray:
    """(P,) image box IoU of ground-truth rows ``gi`` and tracker rows ``ti``."""
    return box2d_overlap_pairs(gt.box2d[gi], tr.box2d[ti])


def similarity_3d(gt: TrackRows, tr: TrackRows, gi: np.ndarray, ti: np.ndarray) -> np.ndarray:
    """(P,) 3D box IoU of ground-truth rows ``gi`` and tracker rows ``ti`` (0 without 3D)."""
    iou = box3d_overlap_pairs(gt.boxes3d()[gi], tr.boxes3d()[ti])
    return np.where(gt.has_3d()[gi] & tr.has_3d()[ti], iou, 0.0)


def _by_frame(rows: TrackRows, mask: np.ndarray) -> np.ndarray:
    index = np.flatnonzero(mask)
    return index[np.argsort(rows.frame[index], kind="stable")]


def check_unique(frame, ids, lines, path, what) -> None:
    """Refuses a track id twice in one frame, naming the line of its second occurrence.

    Args:
      frame, ids, lines: (n,) frame, track id and file line of each box (any order).
    """
    if ids.size == 0:
        return
    order = np.lexsort((lines, ids, frame))
    f, i = frame[order], ids[order]
    twice = np.flatnonzero((f[1:] == f[:-1]) & (i[1:] == i[:-1]))
    if twice.size:
        k = twice[np.argmin(lines[order][twice + 1])]  # the earliest second occurrence
        first, second = int(lines[order][k]), int(lines[order][k + 1])
        raise KittiFormatError(
            path,
            f"{what} track id {int(i[k])} appears twice in frame {int(f[k])} "
            f"(also on line {first})",
            second,
        )


def _relabel(ids: np.ndarray) -> tuple[np.ndarray, int]:
    uniq, inverse = np.unique(ids, return_inverse=True)
    return inverse.astype(np.int64), int(uniq.size)


def prepare_class(
    gt: TrackRows,
    tr: TrackRows,
    cls: str,
    n_frames: int,
    similarity=similarity_2d,
    match_iou: float = MATCH_IOU,
    label_path: str | os.PathLike = "<labels>",
    result_path: str | os.PathLike = "<results>",
) -> ClassSequence:
    """Applies the benchmark's rules (module docstring) for class ``cls`` to one sequence.

    Args:
      gt, tr: all rows of the label and result files of the sequence.
      cls: ``"car"`` or ``"pedestrian"``; n_frames: frames of the sequence.
      similarity: ``(gt, tr, gi, ti) -> (P,)`` (:func:`similarity_2d` or :func:`similarity_3d`).
      match_iou: similarity of a match in the distractor step (2).
    """
    names = CLASS_NAMES[cls]
    gt_cand = np.isin(gt.type, names + DISTRACTORS[cls]) & (gt.track_id >= 0)
    gi = _by_frame(gt, gt_cand)
    ti = _by_frame(tr, np.isin(tr.type, names) & (tr.track_id >= 0))
    dc = _by_frame(gt, gt.type == "dontcare")
    a, b = same_frame_pairs(gt.frame[gi], tr.frame[ti], n_frames)
    sim = similarity(gt, tr, gi[a], ti[b]) if a.size else np.zeros(0)
    positive = sim > 0
    a, b, sim = a[positive], b[positive], sim[positive]
    blocks = FrameBlocks(
        starts(gt.frame[gi], n_frames), starts(tr.frame[ti], n_frames), gt.frame[gi][a], a, b
    )
    matched = blocks.match(np.where(sim >= match_iou - EPS, sim, 0.0))

    ignored_gt = (
        np.isin(gt.type[gi], DISTRACTORS[cls])
        | (gt.occlusion[gi] > MAX_OCCLUSION)
        | (gt.truncation[gi] > MAX_TRUNCATION)
    )
    remove = np.zeros(ti.size, bool)
    remove[b[matched & ignored_gt[a]]] = True
    unmatched = np.ones(ti.size, bool)
    unmatched[b[matched]] = False
    box = tr.box2d[ti]
    too_small = box[:, 3] - box[:, 1] <= MIN_HEIGHT + EPS
    c, d = same_frame_pairs(tr.frame[ti], gt.frame[dc], n_frames)
    inside = np.zeros(ti.size, bool)
    if c.size:
        ioa = box2d_overlap_pairs(box[c], gt.box2d[dc[d]], criterion=0)
        inside[c[ioa > DONTCARE_OVERLAP + EPS]] = True
    remove |= unmatched & (too_small | inside)

    keep_gt = ~ignored_gt  # distractors are ignored, so the kept ground truth is of the class
    keep_tr = ~remove
    new_g = np.cumsum(keep_gt) - 1
    new_t = np.cumsum(keep_tr) - 1
    kept_pair = keep_gt[a] & keep_tr[b]
    gi, ti = gi[keep_gt], ti[keep_tr]
    gt_frame, tr_frame = gt.frame[gi], tr.frame[ti]
    check_unique(gt_frame, gt.track_id[gi], gt.line[gi], label_path, "ground-truth")
    check_unique(tr_frame, tr.track_id[ti], tr.line[ti], result_path, cls)
    gt_id, n_gt_ids = _relabel(gt.track_id[gi])
    tr_id, n_tr_ids = _relabel(tr.track_id[ti])
    return ClassSequence(
        n_frames=n_frames,
        gt_frame=gt_frame,
        gt_id=gt_id,
        gt_row=gi,
        tr_frame=tr_frame,
        tr_id=tr_id,
        tr_row=ti,
        gt_start=starts(gt_frame, n_frames),
        tr_start=starts(tr_frame, n_frames),
        pair_gt=new_g[a[kept_pair]],
        pair_tr=new_t[b[kept_pair]],
        pair_sim=sim[kept_pair],
        num_gt_ids=n_gt_ids,
        num_tr_ids=n_tr_ids,
    )
