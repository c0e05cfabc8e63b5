"""The 2D baseline (SORT style): image boxes only, a constant-velocity Kalman filter on the
box centre and size, Hungarian assignment on 2D IoU.

As SORT (Bewley et al., ICIP 2016), with the filter on ``(u, v, w, h)`` (pixels) instead of
``(u, v, area, aspect)``: tracks are predicted, matched to detections of their class when
the IoU of the predicted box is at least ``min_iou_2d``, born after ``min_hits`` detections and
ended after ``max_misses`` misses (:class:`~gac_jax.tracking.params.TrackerParams`). A reported
track carries its detection's 3D box unchanged and no velocity (NaN): the baseline for what
the 3D tracker adds.
"""

from __future__ import annotations

import numpy as np

from gac_jax.tracking import association, kalman
from gac_jax.tracking.clock import StreamTracker
from gac_jax.tracking.tracks import DetectionArrays, TrackedObjects

BOX_STD = 0.05  # a detected box's error, as a fraction of its size (plus 1 pixel)
BOX_ACCEL = 2.0  # white acceleration of centre and size, in box sizes per s^2


def boxes_to_state(boxes: np.ndarray) -> np.ndarray:
    """(N, 4) xyxy -> (N, 4) centre u, v and width, height."""
    return np.stack(
        [
            (boxes[:, 0] + boxes[:, 2]) / 2,
            (boxes[:, 1] + boxes[:, 3]) / 2,
            boxes[:, 2] - boxes[:, 0],
            boxes[:, 3] - boxes[:, 1],
        ],
        axis=1,
    )


def state_to_boxes(state: np.ndarray) -> np.ndarray:
    """(N, 4) centre and size -> xyxy."""
    half = np.maximum(state[:, 2:4], 0.0) / 2
    return np.concatenate([state[:, :2] - half, state[:, :2] + half], axis=1)


def _box_covariance(state: np.ndarray) -> np.ndarray:
    size = np.repeat(np.maximum(state[:, 2:4], 1.0), 2, axis=1)[:, [0, 2, 1, 3]]
    std = 1.0 + BOX_STD * size
    return np.einsum("ni,ij->nij", std**2, np.eye(4))


class Sort2DTracker(StreamTracker):
    """SORT-style 2D IoU tracker (module doc); same ``update`` as
    :class:`~gac_jax.tracking.tracker.Tracker` (``pose`` and ``plane`` are not used)."""

    def reset(self) -> None:
        super().reset()
        self.x = np.zeros((0, 8))
        self.P = np.zeros((0, 8, 8))
        self.ids = np.zeros(0, np.int64)
        self.names = np.zeros(0, "<U16")
        self.hits = np.zeros(0, np.int64)
        self.misses = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        self.last = np.zeros(0, np.int64)  # index of the matched detection in this frame

    def update(self, detections, pose=None, timestamp=None, plane=None) -> TrackedObjects:
        p = self.params
        det = DetectionArrays.of(detections)
        det = det.select(det.scores >= p.min_score)
        dt = self.clock.advance(timestamp)
        self.frames += 1
        if dt > 0 and len(self.ids):
            # the noise scales with each box's size: kalman.predict's model, per track
            F = kalman.transition(dt, 4)
            accel = BOX_ACCEL * np.maximum(self.x[:, 2:4].mean(axis=1), 1.0)
            Q = accel[:, None, None] ** 2 * kalman.process_noise(dt, 1.0, 4)
            self.x, self.P = self.x @ F.T, F @ self.P @ F.T + Q
        z = boxes_to_state(det.boxes_2d)
        rows = cols = np.zeros(0, np.int64)
        if len(self.ids) and len(det):
            iou = association.box_iou_matrix(state_to_boxes(self.x[:, :4]), det.boxes_2d)
            same = self.names[:, None] == det.names[None, :]
            rows, cols = association.assign(1.0 - iou, same & (iou >= p.min_iou_2d))
        if len(rows):
            self.x[rows], self.P[rows] = kalman.update(
                self.x[rows], self.P[rows], z[cols], _box_covariance(z[cols])
            )
        matched = np.zeros(len(self.ids), bool)
        matched[rows] = True
        self.hits[rows] += 1
        self.misses[rows] = 0
        self.misses[~matched] += 1
        self.ages += 1
        self.last = np.full(len(self.ids), -1)
        self.last[rows] = cols
        keep = (self.misses == 0) | ((self.hits >= p.min_hits) & (self.misses <= p.max_misses))
        for name in ("x", "P", "ids", "names", "hits", "misses", "ages", "last"):
            setattr(self, name, getattr(self, name)[keep])
        born = np.setdiff1d(np.arange(len(det)), cols)
        if len(born):
            x, P = kalman.initial_state(z[born], _box_covariance(z[born]), 0.5 * z[born, 2:].mean())
            n = len(born)
            add = {
                "x": x,
                "P": P,
                "ids": self.take_ids(n),
                "names": det.names[born],
                "hits": np.ones(n, np.int64),
                "misses": np.zeros(n, np.int64),
                "ages": np.zeros(n, np.int64),
                "last": born,
            }
            for name, value in add.items():
                setattr(self, name, np.concatenate([getattr(self, name), value]))
        needed = min(p.min_hits, self.frames)
        shown = np.flatnonzero((self.misses == 0) & (self.hits >= needed))
        return TrackedObjects.of_detections(
            det, self.last[shown], self.ids[shown], self.ages[shown], self.hits[shown]
        )
