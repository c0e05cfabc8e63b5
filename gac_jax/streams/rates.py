"""Sustained frames/s and per-frame latency of a stream (thread-safe).

A frame's latency runs from the moment reading (decoding) of it began, or from the moment the
stream started after the start-up (model loading, export, warm-up) for a frame read before,
to the moment its annotated picture and results were written. The sustained rate is frames
written per second of wall time from the first frame's start to the last frame's write
(pipeline fill included, start-up not: the caller reports that on its own line).
"""

from __future__ import annotations

import threading
import time

import numpy as np


def percentile_ms(seconds: list[float] | np.ndarray, q: float) -> float:
    """The ``q``-th percentile of latencies ``seconds``, in milliseconds (nan when empty)."""
    if len(seconds) == 0:
        return float("nan")
    return float(np.percentile(np.asarray(seconds, np.float64), q) * 1e3)


class StreamRates:
    """Collects ``(t_read, t_written)`` per written frame, plus dropped-frame counts."""

    def __init__(self):
        self._lock = threading.Lock()
        self._read: list[float] = []
        self._done: list[float] = []
        self.dropped = 0  # frames a live source delivered that were never processed

    def frame_written(self, t_read: float, t_done: float | None = None) -> None:
        t_done = time.perf_counter() if t_done is None else t_done
        with self._lock:
            self._read.append(t_read)
            self._done.append(t_done)

    @property
    def frames(self) -> int:
        with self._lock:
            return len(self._done)

    def _arrays(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            return np.array(self._read), np.array(self._done)

    def latencies(self) -> np.ndarray:
        """(N,) seconds from read to written of every frame written so far."""
        read, done = self._arrays()
        return done - read

    def summary(self, last_s: float | None = None) -> dict[str, float]:
        """``frames``, ``fps``, ``latency_median_ms``, ``latency_p95_ms`` and ``wall_s``: of all
        frames written, or of those written in the last ``last_s`` seconds (fps over that
        window)."""
        read, done = self._arrays()
        if last_s is not None:
            now = time.perf_counter()
            keep = done >= now - last_s
            read, done = read[keep], done[keep]
            wall = last_s
        else:
            wall = float(done.max() - read.min()) if len(done) else 0.0
        latency = done - read
        return {
            "frames": int(len(done)),
            "fps": len(done) / wall if wall > 0 else float("nan"),
            "latency_median_ms": percentile_ms(latency, 50),
            "latency_p95_ms": percentile_ms(latency, 95),
            "wall_s": wall,
        }


def format_rates(s: dict[str, float]) -> str:
    """``"12.3 frames/s, latency median 81 ms, p95 95 ms"`` of a :meth:`StreamRates.summary`
    (``"0 frames/s"`` when none was written: no latency to tell)."""
    if not s["frames"]:
        return "0 frames/s"
    return (
        f"{s['fps']:.1f} frames/s, latency median {s['latency_median_ms']:.0f} ms, "
        f"p95 {s['latency_p95_ms']:.0f} ms"
    )
