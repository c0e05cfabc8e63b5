"""The trivial baseline: every detection of every frame is a new track (no association), what
per-frame detection gives a tracking evaluation."""

from __future__ import annotations

import numpy as np

from gac_jax.tracking.clock import StreamTracker
from gac_jax.tracking.tracks import DetectionArrays, TrackedObjects


class NewIdTracker(StreamTracker):
    """A new id for every detection; same ``update`` as
    :class:`~gac_jax.tracking.tracker.Tracker` (only ``min_score`` and the timestamps'
    checks apply)."""

    def update(self, detections, pose=None, timestamp=None, plane=None) -> TrackedObjects:
        det = DetectionArrays.of(detections)
        det = det.select(det.scores >= self.params.min_score)
        self.clock.advance(timestamp)
        n = len(det)
        zeros = np.zeros(n, np.int64)
        return TrackedObjects.of_detections(det, np.arange(n), self.take_ids(n), zeros, zeros + 1)
