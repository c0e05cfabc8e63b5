"""Per-frame maximum-weight matching of ground truth and tracker boxes, done once per evaluation.

Pairs are the same-frame (ground truth, tracker) pairs of a sequence with a positive
similarity, sorted by frame. A frame whose candidate pairs (positive weight) touch every box
at most once has only one optimal matching: all its candidates. Only the other frames need
the Hungarian algorithm, run on the frame's full weight matrix (rows: its ground truth in
file order, columns: its tracker boxes in file order; zero where no candidate), as the
official evaluation runs it, so that ties are broken the same way.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

EPS = float(np.finfo(np.float64).eps)


def starts(frame: np.ndarray, n_frames: int) -> np.ndarray:
    """(F + 1,) offsets of each frame's block in an array sorted by ``frame`` (F = n_frames)."""
    return np.concatenate([[0], np.cumsum(np.bincount(frame, minlength=n_frames))]).astype(np.int64)


def unambiguous(
    pair_gt: np.ndarray, pair_tr: np.ndarray, candidate: np.ndarray, n_gt: int, n_tr: int
) -> np.ndarray:
    """(P,) bool: candidate pairs none of whose boxes is in another candidate pair."""
    deg_g = np.bincount(pair_gt[candidate], minlength=n_gt)
    deg_t = np.bincount(pair_tr[candidate], minlength=n_tr)
    return candidate & (deg_g[pair_gt] == 1) & (deg_t[pair_tr] == 1)


class FrameBlocks:
    """Index blocks of the boxes and pairs of each frame of one sequence.

    Args:
      gt_start, tr_start: (F + 1,) offsets of each frame's ground truth / tracker boxes.
      pair_frame, pair_gt, pair_tr: (P,) frame and box indices of the pairs (sorted by frame).
    """

    def __init__(self, gt_start, tr_start, pair_frame, pair_gt, pair_tr):
        self.gt_start, self.tr_start = gt_start, tr_start
        self.pair_gt, self.pair_tr = pair_gt, pair_tr
        self.pair_frame = pair_frame
        self.pair_start = starts(pair_frame, len(gt_start) - 1)

    def ambiguous_frames(self, candidate: np.ndarray) -> np.ndarray:
        """Sorted frames with a box in two or more candidate pairs."""
        n_gt, n_tr = int(self.gt_start[-1]), int(self.tr_start[-1])
        single = unambiguous(self.pair_gt, self.pair_tr, candidate, n_gt, n_tr)
        return np.unique(self.pair_frame[candidate & ~single])

    def assign(self, frame: int, weight: np.ndarray) -> np.ndarray:
        """Pair indices matched in ``frame`` by the Hungarian algorithm on ``weight`` (P,)
        (pairs with weight <= EPS are never kept)."""
        lo, hi = self.pair_start[frame], self.pair_start[frame + 1]
        g0, t0 = self.gt_start[frame], self.tr_start[frame]
        rows = self.pair_gt[lo:hi] - g0
        cols = self.pair_tr[lo:hi] - t0
        shape = (self.gt_start[frame + 1] - g0, self.tr_start[frame + 1] - t0)
        dense = np.zeros(shape)
        dense[rows, cols] = weight[lo:hi]
        index = np.full(shape, -1, np.int64)
        index[rows, cols] = np.arange(lo, hi)
        r, c = linear_sum_assignment(-dense)
        keep = dense[r, c] > EPS
        return index[r[keep], c[keep]]

    def match(self, weight: np.ndarray) -> np.ndarray:
        """(P,) bool: the pairs of a maximum-weight matching in every frame (weights fixed)."""
        candidate = weight > EPS
        n_gt, n_tr = int(self.gt_start[-1]), int(self.tr_start[-1])
        matched = unambiguous(self.pair_gt, self.pair_tr, candidate, n_gt, n_tr)
        for frame in self.ambiguous_frames(candidate):
            lo, hi = self.pair_start[frame], self.pair_start[frame + 1]
            matched[lo:hi] = False
            matched[self.assign(int(frame), weight)] = True
        return matched
