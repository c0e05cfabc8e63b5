"""The 3D multi-object tracker: a constant-velocity Kalman filter per track, two-stage
Hungarian association, birth after ``min_hits`` detections, death after ``max_misses`` misses.

Each :meth:`Tracker.update` takes one frame's detections (camera frame), optionally the
frame's ego pose (camera -> world, :mod:`gac_jax.tracking.poses`), its time and its ground
plane:

1. The tracks are predicted to the frame's time (``dt`` from the timestamps, or
   ``1 / frame_rate``). They live in the world frame when poses are given, so a parked car
   stays put while the ego drives; in the camera frame otherwise (velocities then relative).
2. Stage 1: detected bottom centres against predicted ones, squared Mahalanobis distance
   ``d2`` under the innovation covariance (the track's uncertainty plus a monocular
   detection's, long along the viewing ray and growing with distance), gated at
   ``gate_chi2``, same class only; Hungarian on ``d2 / gate_chi2 + iou_weight (1 - IoU)``,
   the IoU of the detection's 2D box with the track's last one (of two detections in the
   gate, a track keeps the one its image box continues: a detector's duplicates at two
   depths do not swap tracks). Stage 2: tracks and detections left over, on that 2D IoU
   alone (``>= min_iou_2d``), Hungarian.
3. Matched tracks take the detection (Kalman update of the position; the heading is turned
   by 180 degrees first when it points more than 90 degrees away from the track's, so a
   detector's front/back confusion never flips a track; with poses, a track moving surely
   faster than :data:`MOVING_SPEED` faces its motion; sizes are running means). Unmatched
   detections start tracks; tracks not matched for more than ``max_misses`` frames end (a
   track not yet reported ends at its first miss).
4. Reported: tracks matched in this frame with ``min_hits`` detections (fewer in the
   stream's first frames), in the frame's camera frame, standing on its ground plane when
   one is given.
"""

from __future__ import annotations

import numpy as np

from gac_jax.geometry import wrap_angle
from gac_jax.tracking import association, kalman
from gac_jax.tracking.clock import StreamTracker
from gac_jax.tracking.poses import (
    TrackingInputError,
    check_pose,
    to_camera,
    to_world,
    yaw_to_camera,
    yaw_to_world,
)
from gac_jax.tracking.tracks import DetectionArrays, TrackedObjects

IDENTITY_POSE = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
VERTICAL_ACCEL = 0.2  # share of accel_std along y: road users move over the ground
MOVING_SPEED = 2.0  # m/s over the ground above which a track's heading follows its motion


def check_plane(plane, name: str = "plane") -> np.ndarray:
    """(4,) ``(a, b, c, d)`` of the ground ``a x + b y + c z + d = 0`` with ``b != 0``."""
    arr = np.asarray(plane, np.float64).reshape(-1) if not isinstance(plane, str) else None
    if arr is None or arr.shape != (4,) or not np.all(np.isfinite(arr)):
        raise TrackingInputError(name, "expected 4 finite numbers (a, b, c, d)")
    if abs(arr[1]) < 1e-6:
        raise TrackingInputError(name, "the plane is vertical (b = 0): not a ground plane")
    return arr


def on_plane(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame ``points`` moved along y onto ``plane``."""
    a, b, c, d = plane
    out = points.copy()
    out[:, 1] = -(a * points[:, 0] + c * points[:, 2] + d) / b
    return out


class Tracker(StreamTracker):
    """3D multi-object tracker (module doc). ``params``: :class:`TrackerParams`."""

    def reset(self) -> None:
        """Forget every track (a new stream); ids start again from 0."""
        super().reset()
        self.uses_poses: bool | None = None
        self.ids = np.zeros(0, np.int64)
        self.names = np.zeros(0, "<U16")
        self.x = np.zeros((0, 6))
        self.P = np.zeros((0, 6, 6))
        self.yaw = np.zeros(0)
        self.yaw_var = np.zeros(0)
        self.dims = np.zeros((0, 3))
        self.size_count = np.zeros(0, np.int64)
        self.scores = np.zeros(0)
        self.boxes = np.zeros((0, 4))
        self.hits = np.zeros(0, np.int64)
        self.misses = np.zeros(0, np.int64)
        self.ages = np.zeros(0, np.int64)
        # ring buffers of each track's last trail_length positions; trail_count: positions
        # written so far (the next goes to slot trail_count % trail_length)
        self.trail = np.zeros((0, self.params.trail_length, 3))
        self.trail_count = np.zeros(0, np.int64)
        self._steps: dict = {}  # (dt, accel) -> (F, Q) of the last time steps

    @property
    def num_tracks(self) -> int:
        """Tracks alive (reported or not)."""
        return len(self.ids)

    def _frame_pose(self, pose) -> np.ndarray:
        given = pose is not None
        if self.uses_poses is not None and given != self.uses_poses:
            said = "missing" if self.uses_poses else "given"
            raise TrackingInputError(
                "pose",
                f"{said} here but {'given' if self.uses_poses else 'missing'} for the earlier "
                "frames (poses for every frame or none)",
            )
        checked = check_pose(pose) if given else IDENTITY_POSE
        self.uses_poses = given
        return checked

    def update(self, detections, pose=None, timestamp=None, plane=None) -> TrackedObjects:
        """Tracks after one frame (module doc).

        Args:
          detections: the frame's :class:`gac_jax.api.Detections` or
            :class:`~gac_jax.data.kitti.KittiObjects` (camera frame).
          pose: (3, 4) or (4, 4) camera -> world of this frame, for every frame or none.
          timestamp: seconds (increasing); None: ``1 / frame_rate`` after the previous frame.
          plane: (4,) ground plane in this frame's camera frame, or None.

        Raises:
          TrackingInputError: a bad pose, timestamp or plane (named).
        """
        p = self.params
        det = DetectionArrays.of(detections)
        pose = self._frame_pose(pose)
        plane = None if plane is None else check_plane(plane)
        dt = self.clock.advance(timestamp)
        self.frames += 1
        det = det.select(det.scores >= p.min_score)
        z = to_world(det.locations, pose)
        R_cam = association.measurement_covariance(det.locations, p)
        Rw = pose[:, :3] @ R_cam @ pose[:, :3].T
        det_yaw = yaw_to_world(det.rotation_y, pose)

        if dt > 0 and self.num_tracks:
            self.x, self.P = self._predict(dt)
            self.yaw_var = self.yaw_var + (p.yaw_rate_std * dt) ** 2
        rows, cols = self._associate(det, z, pose)

        matched = np.zeros(self.num_tracks, bool)
        matched[rows] = True
        if len(rows):
            self._take(rows, cols, det, z, Rw, det_yaw)
        self.misses[~matched] += 1
        self.ages += 1
        keep = (self.misses == 0) | ((self.hits >= p.min_hits) & (self.misses <= p.max_misses))
        self._keep(keep)
        born = np.ones(len(det), bool)
        born[cols] = False
        self._birth(det.select(born), z[born], Rw[born], det_yaw[born])
        seen = np.flatnonzero(self.misses == 0)
        self.trail[seen, self.trail_count[seen] % p.trail_length] = self.x[seen, :3]
        self.trail_count[seen] += 1
        return self._report(pose, plane)

    def _predict(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """The filters ``dt`` seconds on (:func:`kalman.predict`; ``F`` and ``Q`` kept for
        the stream's usual steps)."""
        if dt not in self._steps:
            if len(self._steps) > 16:
                self._steps.clear()
            accel = self.params.accel_std * np.array([1.0, VERTICAL_ACCEL, 1.0])
            self._steps[dt] = (kalman.transition(dt, 3), kalman.process_noise(dt, accel, 3))
        F, Q = self._steps[dt]
        return kalman.predict_with(self.x, self.P, F, Q)

    def _associate(self, det: DetectionArrays, z: np.ndarray, pose: np.ndarray):
        """Matched ``(track rows, detection columns)``: stage 1 (3D), then stage 2 (2D)."""
        p = self.params
        if not self.num_tracks or not len(det):
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        same_class = self.names[:, None] == det.names[None, :]
        predicted_cam = to_camera(self.x[:, :3], pose)
        R_track = association.measurement_covariance(predicted_cam, p)
        S = self.P[:, :3, :3] + pose[:, :3] @ R_track @ pose[:, :3].T
        d2 = association.mahalanobis_costs(self.x[:, :3], S, z)
        iou = association.box_iou_matrix(self.boxes, det.boxes_2d)
        cost = d2 / p.gate_chi2 + p.iou_weight * (1.0 - iou)
        rows, cols = association.assign(cost, same_class & (d2 <= p.gate_chi2))
        free_t = np.flatnonzero(~np.isin(np.arange(self.num_tracks), rows))
        free_d = np.flatnonzero(~np.isin(np.arange(len(det)), cols))
        if len(free_t) and len(free_d):
            iou = iou[free_t][:, free_d]
            ok = same_class[free_t][:, free_d] & (iou >= p.min_iou_2d)
            r2, c2 = association.assign(1.0 - iou, ok)
            rows = np.concatenate([rows, free_t[r2]])
            cols = np.concatenate([cols, free_d[c2]])
        return rows, cols

    def _take(self, rows, cols, det, z, Rw, det_yaw) -> None:
        """Kalman, heading and size updates of tracks ``rows`` with detections ``cols``."""
        p = self.params
        self.x[rows], self.P[rows] = kalman.update(self.x[rows], self.P[rows], z[cols], Rw[cols])
        yaw = self.yaw[rows]
        measured = det_yaw[cols]
        flip = np.abs(wrap_angle(measured - yaw)) > np.pi / 2
        measured = np.where(flip, measured + np.pi, measured)
        var = self.yaw_var[rows]
        gain = var / (var + p.yaw_std**2)
        self.yaw[rows] = wrap_angle(yaw + gain * wrap_angle(measured - yaw))
        self.yaw_var[rows] = (1 - gain) * var
        n = np.minimum(self.size_count[rows] + 1, p.size_window)
        self.dims[rows] += (det.dimensions[cols] - self.dims[rows]) / n[:, None]
        self.size_count[rows] = n
        self.scores[rows] = det.scores[cols]
        self.boxes[rows] = det.boxes_2d[cols]
        self.hits[rows] += 1
        self.misses[rows] = 0
        if self.uses_poses:  # over the ground, a moving object faces where it goes
            self._face_motion(rows)

    def _face_motion(self, rows: np.ndarray) -> None:
        """Turns by 180 degrees the heading of tracks ``rows`` moving surely (speed above
        :data:`MOVING_SPEED` by two standard deviations) against their heading."""
        v = self.x[rows][:, [3, 5]]
        speed = np.linalg.norm(v, axis=1)
        var = self.P[rows][:, 3, 3] + self.P[rows][:, 5, 5]
        sure = speed - 2 * np.sqrt(var) > MOVING_SPEED
        motion = np.arctan2(-v[:, 1], v[:, 0])  # yaw of the direction of motion
        against = sure & (np.abs(wrap_angle(motion - self.yaw[rows])) > np.pi / 2)
        self.yaw[rows[against]] = wrap_angle(self.yaw[rows[against]] + np.pi)

    def _keep(self, keep: np.ndarray) -> None:
        for name in ("ids", "names", "x", "P", "yaw", "yaw_var", "dims", "size_count"):
            setattr(self, name, getattr(self, name)[keep])
        for name in ("scores", "boxes", "hits", "misses", "ages", "trail", "trail_count"):
            setattr(self, name, getattr(self, name)[keep])

    def _birth(self, det: DetectionArrays, z, Rw, det_yaw) -> None:
        n = len(det)
        if not n:
            return
        x, P = kalman.initial_state(z, Rw, self.params.initial_speed_std)
        new = {
            "ids": self.take_ids(n),
            "names": det.names,
            "x": x,
            "P": P,
            "yaw": det_yaw,
            "yaw_var": np.full(n, self.params.yaw_std**2),
            "dims": det.dimensions,
            "size_count": np.ones(n, np.int64),
            "scores": det.scores,
            "boxes": det.boxes_2d,
            "hits": np.ones(n, np.int64),
            "misses": np.zeros(n, np.int64),
            "ages": np.zeros(n, np.int64),
            "trail": np.zeros((n, self.params.trail_length, 3)),
            "trail_count": np.zeros(n, np.int64),
        }
        for name, value in new.items():
            setattr(self, name, np.concatenate([getattr(self, name), value]))

    def _report(self, pose: np.ndarray, plane: np.ndarray | None) -> TrackedObjects:
        """The tracks matched in this frame with enough hits, in the camera frame."""
        needed = min(self.params.min_hits, self.frames)
        shown = np.flatnonzero((self.misses == 0) & (self.hits >= needed))
        if not len(shown):
            return TrackedObjects.empty()
        R = pose[:, :3]
        locations = to_camera(self.x[shown, :3], pose)
        if plane is not None:
            locations = on_plane(locations, plane)
        velocities = self.x[shown, 3:] @ R  # R^T v
        cov = R.T @ self.P[shown, 3:, 3:] @ R
        length = self.params.trail_length
        count = self.trail_count[shown]
        oldest_first = (count[:, None] + np.arange(length)) % length  # (S, L) slots
        trail = to_camera(self.trail[shown[:, None], oldest_first], pose)  # (S, L, 3)
        if plane is not None:
            trail = on_plane(trail.reshape(-1, 3), plane).reshape(trail.shape)
        kept = np.minimum(count, length).tolist()
        trails = [trail[i, length - c :] for i, c in enumerate(kept)]
        return TrackedObjects(
            ids=self.ids[shown],
            names=self.names[shown],
            scores=self.scores[shown],
            boxes_2d=self.boxes[shown],
            dimensions=self.dims[shown],
            locations=locations,
            rotation_y=yaw_to_camera(self.yaw[shown], pose),
            velocities=velocities,
            velocity_covariances=cov,
            ages=self.ages[shown],
            hits=self.hits[shown],
            trails=tuple(trails),
        )
