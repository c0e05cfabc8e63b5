"""Objects over time: multi-object tracking of a detector's per-frame results (numpy/scipy).

    from gac_jax.tracking import Tracker, TrackerParams

    tracker = Tracker(TrackerParams.from_config(config))
    for detections, pose, t in frames:          # pose (3, 4) camera -> world, or None
        tracks = tracker.update(detections, pose=pose, timestamp=t)

* :mod:`~gac_jax.tracking.tracker`: the 3D tracker (Kalman filter per track, world frame with
  poses; two-stage Hungarian association).
* :mod:`~gac_jax.tracking.sort2d`, :mod:`~gac_jax.tracking.new_ids`: the baselines (2D IoU
  SORT-style; a new id per detection).
* :mod:`~gac_jax.tracking.kalman`, :mod:`~gac_jax.tracking.association`,
  :mod:`~gac_jax.tracking.poses`: the parts; :mod:`~gac_jax.tracking.tracks`: the result
  (:class:`TrackedObjects`, KITTI tracking lines); :mod:`~gac_jax.tracking.params`: the
  config's ``track`` section.
"""

from gac_jax.tracking.new_ids import NewIdTracker
from gac_jax.tracking.params import TrackerParams, track_config
from gac_jax.tracking.poses import TrackingInputError, read_pose_file
from gac_jax.tracking.sort2d import Sort2DTracker
from gac_jax.tracking.tracker import Tracker
from gac_jax.tracking.tracks import TrackedObject, TrackedObjects

METHODS = {"kalman3d": Tracker, "sort2d": Sort2DTracker, "new_ids": NewIdTracker}

__all__ = [
    "METHODS",
    "NewIdTracker",
    "Sort2DTracker",
    "TrackedObject",
    "TrackedObjects",
    "Tracker",
    "TrackerParams",
    "TrackingInputError",
    "read_pose_file",
    "track_config",
]
