"""The trivial baseline: every detection of every frame is a new track (no association), what
per-frame detection gives a tracking evaluation."""

from __future__ import annotations

import numpy as np

from gac_jax.tracking.params import TrackerParams
from gac_jax.tracking.tracker import FrameClock
from gac_jax.tracking.tracks import DetectionArrays, TrackedObjects


class NewIdTracker:
    """A new id for every detection; same ``update`` as
    :class:`~gac_jax.tracking.tracker.Tracker` (only ``min_score`` and the timestamps'
    checks apply)."""

    def __init__(self, params: TrackerParams | None = None):
        self.params = params or TrackerParams()
        self.reset()

    def reset(self) -> None:
        self.clock = FrameClock(self.params.frame_rate)
        self.next_id = 0

    def update(self, detections, pose=None, timestamp=None, plane=None) -> TrackedObjects:
        det = DetectionArrays.of(detections)
        det = det.select(det.scores >= self.params.min_score)
        self.clock.advance(timestamp)
        n = len(det)
        ids = np.arange(self.next_id, self.next_id + n)
        self.next_id += n
        zeros = np.zeros(n, np.int64)
        return TrackedObjects.of_detections(det, np.arange(n), ids, zeros, zeros + 1)
