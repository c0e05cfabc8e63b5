"""What every tracker of a stream shares: the frames' clock and the id counter.

:class:`FrameClock` gives the seconds between frames (given timestamps, checked to increase,
or ``1 / frame_rate``); :class:`StreamTracker` is the base of the trackers (``params``,
``reset``, ``frames`` seen, ids from 0).
"""

from __future__ import annotations

import math

import numpy as np

from gac_jax.tracking.params import TrackerParams
from gac_jax.tracking.poses import TrackingInputError


class FrameClock:
    """Times of the frames of a stream: given timestamps (seconds, increasing) or
    ``1 / frame_rate`` apart."""

    def __init__(self, frame_rate: float):
        self.frame_rate = frame_rate
        self.time: float | None = None

    def advance(self, timestamp) -> float:
        """Seconds since the previous frame (0 for the first one).

        Raises:
          TrackingInputError: ``timestamp`` not a finite number, or not after the previous."""
        if timestamp is None:
            t = 0.0 if self.time is None else self.time + 1.0 / self.frame_rate
        else:
            try:
                t = float(timestamp)
            except (TypeError, ValueError):
                raise TrackingInputError(
                    "timestamp", f"expected seconds (a number), got {timestamp!r}"
                ) from None
            if not math.isfinite(t):
                raise TrackingInputError("timestamp", f"expected a finite number, got {t}")
            if self.time is not None and not t > self.time:
                raise TrackingInputError(
                    "timestamp",
                    f"{t:g} s is not after the previous frame's {self.time:g} s "
                    "(timestamps must increase)",
                )
        dt, self.time = (0.0 if self.time is None else t - self.time), t
        return dt

    def reset(self) -> None:
        self.time = None


class StreamTracker:
    """Base of the trackers: ``update(detections, pose=None, timestamp=None, plane=None)``
    -> :class:`~gac_jax.tracking.tracks.TrackedObjects` in the subclasses."""

    def __init__(self, params: TrackerParams | None = None):
        self.params = params or TrackerParams()
        self.reset()

    def reset(self) -> None:
        """Forget every track (a new stream); ids start again from 0."""
        self.clock = FrameClock(self.params.frame_rate)
        self.frames = 0
        self.next_id = 0

    def take_ids(self, n: int) -> np.ndarray:
        """``n`` new track ids."""
        ids = np.arange(self.next_id, self.next_id + n)
        self.next_id += n
        return ids
