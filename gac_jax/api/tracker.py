"""Objects over time as a Python object: :class:`Tracker3D`, one frame's detections in, the
frame's tracks (:class:`~gac_jax.tracking.tracks.TrackedObjects`) out.

    det = Detector3D.from_workdir("runs/detect3d_default")
    tracker = Tracker3D(det.config)                  # the config's ``track`` section
    for image, P2, pose, t in frames:
        tracks = tracker.update(det.predict(image, P2), pose=pose, timestamp=t)
        for obj in tracks: print(obj.track_id, obj.name, obj.location, obj.speed)

``pose`` (3, 4) maps this frame's camera frame to the world (KITTI odometry convention,
``X_world = R X_cam + t``): with poses the tracks live in the world frame and velocities are
over the ground; without, in the camera frame (velocities relative to the camera).
"""

from __future__ import annotations

import os
from typing import Any

from gac_jax.api.inputs import InputError
from gac_jax.tracking import METHODS, TrackedObjects, TrackerParams, TrackingInputError


class Tracker3D:
    """A multi-object tracker over a stream of :class:`~gac_jax.api.Detections`.

    Args:
      config: a run config (its ``track`` section; defaults where it has none), a ``track``
        section or mapping, :class:`~gac_jax.tracking.TrackerParams`, or None (defaults).
      method: ``kalman3d`` (the 3D tracker), ``sort2d`` (2D IoU baseline, SORT style) or
        ``new_ids`` (a new id per detection; the per-frame baseline).
      **params: overrides of single parameters (``min_hits=2``, ``max_misses=6``, ...).

    Raises:
      InputError: an unknown method or parameter, or a bad value (named).
    """

    def __init__(self, config: Any = None, *, method: str = "kalman3d", **params):
        if method not in METHODS:
            raise InputError("method", f"unknown tracker {method!r} (one of {', '.join(METHODS)})")
        try:
            self.params = TrackerParams.from_config(config, **params)
        except ValueError as e:
            raise InputError("config", str(e)) from None
        self.method = method
        self._tracker = METHODS[method](self.params)

    @classmethod
    def from_workdir(cls, workdir: str | os.PathLike, **kwargs) -> Tracker3D:
        """The tracker of a training workdir's ``config.json`` (``track`` section)."""
        from gac_jax.data.files import KittiFormatError
        from gac_jax.trained.run_config import load_run_config

        try:
            config = load_run_config(workdir)
        except KittiFormatError as e:
            raise InputError("workdir", str(e)) from None
        return cls(config, **kwargs)

    def update(self, detections, pose=None, timestamp=None, plane=None) -> TrackedObjects:
        """The tracks after one frame.

        Args:
          detections: the frame's :class:`~gac_jax.api.Detections` (or
            :class:`~gac_jax.data.kitti.KittiObjects`), camera frame.
          pose: (3, 4) or (4, 4) camera -> world of this frame; for every frame or for none.
          timestamp: the frame's time in seconds, increasing (a live stream's real times: a
            dropped frame is a longer step); None: ``1 / frame_rate`` after the previous one.
          plane: (4,) the frame's ground plane (camera frame): reported boxes stand on it.

        Raises:
          InputError: a bad ``detections``, ``pose``, ``timestamp`` or ``plane`` (named).
        """
        try:
            return self._tracker.update(detections, pose=pose, timestamp=timestamp, plane=plane)
        except TrackingInputError as e:
            raise InputError(e.argument, e.problem) from None
        except (TypeError, ValueError) as e:
            raise InputError("detections", str(e)) from None

    def reset(self) -> None:
        """Forgets every track (a new stream); ids start again from 0."""
        self._tracker.reset()

    def __repr__(self) -> str:
        return f"Tracker3D(method={self.method!r}, {self.params})"
