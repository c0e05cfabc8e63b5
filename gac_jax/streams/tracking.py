"""Tracking on a stream: the stage that turns each frame's detections into tracks, and the
files the tracks go to.

* :class:`TrackingStage`: :class:`gac_jax.api.Tracker3D` fed in frame order from the
  pipeline's finish stage (``update(frame, detections) -> tracks``, ``draw(frame, tracks)``).
  A frame's time is its own (``Frame.time``: a video's timestamps, a KITTI raw drive's
  ``timestamps.txt``, a sequence's frame rate, a camera's read times), so a
  variable-frame-rate recording and frames a live stream dropped make longer steps, not faster
  objects. With ``poses`` (camera -> world of every frame, by the frame's index) the tracks
  live in the world frame; a frame past the last pose stops the stream
  (:meth:`TrackingStage.update`), poses left over are reported
  (:meth:`TrackingStage.unused_poses`).
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
from gac_jax.drawing.track_pictures import ImageTrails, track_picture
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
      fps: the stream's frames per second (a frame without a time of its own is at
        ``index / fps``).
      realtime: frame times are when each frame was read (``Frame.t_read``), for a source
        whose frames have no time of their own.
      poses: (N, 3, 4) camera -> world of frame index 0..N-1, or None.
      scale: the annotated picture's size relative to the frame (``--video-scale``).
      poses_name: the pose file, named in errors.
    """

    def __init__(
        self,
        tracker: Tracker3D,
        fps: float,
        realtime: bool = False,
        poses=None,
        scale: float = 1.0,
        poses_name: str = "poses",
    ):
        self.tracker, self.fps, self.realtime, self.scale = tracker, fps, realtime, scale
        self.poses = None if poses is None else np.asarray(poses, np.float64)
        self.trails = ImageTrails()  # the camera view's trails, over the pictures drawn
        self.poses_name = poses_name
        self.last_index = -1

    def update(self, frame: Frame, detections):
        """The tracks after ``frame``; raises :class:`KittiFormatError` naming the pose file at
        the first frame it has no pose for."""
        pose = None
        if self.poses is not None:
            if frame.index >= len(self.poses):
                raise KittiFormatError(
                    self.poses_name,
                    f"no pose for frame {frame.frame_id} (the file has {len(self.poses)} "
                    f"poses, for frames 0 to {len(self.poses) - 1}); the tracks of the frames "
                    "before are written",
                )
            pose = self.poses[frame.index]
        self.last_index = frame.index
        timestamp = self.frame_time(frame)
        return self.tracker.update(detections, pose=pose, timestamp=timestamp, plane=frame.plane)

    def frame_time(self, frame: Frame) -> float:
        """Seconds: the frame's own time, else its read time with ``--realtime``, else its
        index over the frame rate."""
        if frame.time is not None:
            return frame.time
        return frame.t_read if self.realtime else frame.index / self.fps

    def unused_poses(self, frames: int) -> str | None:
        """The warning when the pose file has more poses than the stream's ``frames`` (read
        to its end); None when it has as many."""
        if self.poses is None or len(self.poses) <= frames:
            return None
        return (
            f"warning: {self.poses_name}: {len(self.poses)} poses for the {frames} frames read; "
            f"the last {len(self.poses) - frames} were not used (a pose file of another "
            "recording?)"
        )

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
