"""Tracking on a stream: the stage that turns each frame's detections into tracks, and the
files the tracks go to.

* :class:`TrackingStage`: :class:`gac_jax.api.Tracker3D` fed in frame order from the
  pipeline's finish stage (``update(frame, detections) -> tracks``, ``draw(frame, tracks)``).
  A frame's time is its own (:attr:`Frame.time`: a KITTI raw drive's ``timestamps.txt``),
  else its index over the stream's fps, or, live (``realtime``), the moment it was read, so
  frames a live stream dropped make a longer step. With ``poses`` (camera ->
  world of every frame, by the frame's index) the tracks live in the world frame.
* :class:`KittiTrackingResults`: ``DIR/SSSS.txt``, one KITTI tracking result line per object
  per frame (``frame id type -1 -1 alpha x1 y1 x2 y2 h w l x y z ry score``), appended and
  flushed as frames finish (``.SSSS.partial.txt`` until closed).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from gac_jax.api.tracker import Tracker3D
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti import KittiObjects
from gac_jax.evaluation.track_pictures import ImageTrails, track_picture
from gac_jax.streams.outputs import JsonlResults
from gac_jax.streams.sources import Frame
from gac_jax.tracking.tracks import kitti_tracking_lines


def frame_number(frame_id: str, index: int) -> int:
    """A frame's number in result files: its id when numeric (``000012``), else its index."""
    return int(frame_id) if frame_id.isdigit() else index


class TrackingStage:
    """Detections -> tracks per frame, in order (one thread calls it).

    Args:
      tracker: the :class:`Tracker3D`.
      fps: the stream's frames per second (frame times ``index / fps`` where a frame has no
        ``time`` of its own).
      realtime: frame times are when each frame was read (``Frame.t_read``).
      poses: (N, 3, 4) camera -> world of frame index 0..N-1, or None.
      scale: the annotated picture's size relative to the frame (``--video-scale``).
    """

    def __init__(
        self,
        tracker: Tracker3D,
        fps: float,
        realtime: bool = False,
        poses=None,
        scale: float = 1.0,
    ):
        self.tracker, self.fps, self.realtime, self.scale = tracker, fps, realtime, scale
        self.poses = None if poses is None else np.asarray(poses, np.float64)
        self.trails = ImageTrails()  # the camera view's trails, over the pictures drawn

    def update(self, frame: Frame, detections):
        pose = None
        if self.poses is not None:
            if frame.index >= len(self.poses):
                raise KittiFormatError(
                    "poses", f"frame {frame.index} has none (they cover 0 to {len(self.poses) - 1})"
                )
            pose = self.poses[frame.index]
        timestamp = self.frame_time(frame)
        return self.tracker.update(detections, pose=pose, timestamp=timestamp, plane=frame.plane)

    def frame_time(self, frame: Frame) -> float:
        """Seconds: the read time with ``--realtime``, else the frame's own time (a raw
        drive's timestamps.txt) or its index over the frame rate."""
        if self.realtime:
            return frame.t_read
        return frame.index / self.fps if frame.time is None else frame.time

    def draw(self, frame: Frame, tracks) -> np.ndarray:
        return track_picture(
            frame.image, frame.P2, tracks, scale=self.scale, trails=self.trails,
            timestamp=self.frame_time(frame), over_ground=self.poses is not None,
        )  # fmt: skip


class KittiTrackingResults(JsonlResults):
    """``folder/<sequence>.txt``: the KITTI tracking result lines of every frame (module doc),
    appended per frame, whole or not at all, as :class:`~gac_jax.streams.outputs.JsonlResults`
    writes its lines. ``write`` takes what the pipeline gives a results writer: the tracks'
    ``objects`` (:class:`KittiObjects`) and ``record`` (their ``to_dict()``, with the ids)."""

    needs_record = True

    def __init__(self, folder: str | os.PathLike, sequence: str):
        super().__init__(Path(folder) / f"{sequence}.txt")

    def write(self, frame_id: str, index: int, objects: KittiObjects, record: dict) -> None:
        ids = np.array([obj["track_id"] for obj in record["objects"]], np.int64)
        lines = kitti_tracking_lines(frame_number(frame_id, index), ids, objects)
        self.append_frame("".join(line + "\n" for line in lines))
