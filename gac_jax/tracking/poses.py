"""Ego poses: checking them, reading pose files, and moving points and headings between a
frame's camera and the world.

A pose (3, 4) ``[R | t]`` maps the camera frame of one frame (x right, y down, z forward) to
the world frame, the first frame's camera frame in the KITTI odometry convention:
``X_world = R X_cam + t``. A pose file has one line of 12 numbers (row-major (3, 4)) per
frame (:func:`gac_jax.data.kitti_tracking.parse_poses`).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes
from gac_jax.data.kitti_tracking import parse_poses

ROTATION_TOLERANCE = 1e-3  # |R^T R - I| and |det R - 1| allowed (poses written with 6 digits)


class TrackingInputError(ValueError):
    """Bad input to a tracker: ``<argument>: <problem>`` (one line)."""

    def __init__(self, argument: str, problem: str):
        super().__init__(f"{argument}: {problem}")
        self.argument = argument
        self.problem = problem


def check_pose(pose: Any, name: str = "pose") -> np.ndarray:
    """``pose`` as a (3, 4) float64 ``[R | t]`` (a (4, 4) one with last row ``0 0 0 1`` too).

    Raises:
      TrackingInputError: another shape, a non-finite value, or ``R`` not a rotation.
    """
    arr = np.asarray(pose, dtype=np.float64) if not isinstance(pose, str) else np.zeros(0)
    if arr.shape == (4, 4):
        if not np.allclose(arr[3], [0.0, 0.0, 0.0, 1.0]):
            raise TrackingInputError(
                name, f"a (4, 4) pose must end with the row 0 0 0 1, got {arr[3]}"
            )
        arr = arr[:3]
    if arr.shape != (3, 4):
        raise TrackingInputError(
            name, f"expected a (3, 4) or (4, 4) pose [R | t], got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise TrackingInputError(name, "non-finite value in the pose")
    R = arr[:, :3]
    if (
        np.abs(R.T @ R - np.eye(3)).max() > ROTATION_TOLERANCE
        or abs(np.linalg.det(R) - 1) > ROTATION_TOLERANCE
    ):
        raise TrackingInputError(name, "the pose's (3, 3) part is not a rotation")
    return arr


def read_pose_file(path: str | os.PathLike, frames: int | None = None) -> np.ndarray:
    """(N, 3, 4) poses of a pose file; with ``frames``, N must equal it.

    Raises:
      KittiFormatError: missing or unreadable file, a bad line, a non-rotation, or the wrong
        number of poses (one line naming the file).
    """
    poses = parse_poses(read_bytes(path, "poses file").decode("utf-8", "replace"), path)
    if frames is not None and len(poses) != frames:
        raise KittiFormatError(
            path, f"{len(poses)} poses for {frames} frames (one line of 12 numbers per frame)"
        )
    for k, pose in enumerate(poses):
        try:
            check_pose(pose, f"line {k + 1}")
        except TrackingInputError as e:
            raise KittiFormatError(path, str(e)) from None
    return poses


def to_world(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N, 3) camera-frame points -> world frame (``R X + t``)."""
    return points @ pose[:, :3].T + pose[:, 3]


def to_camera(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(..., 3) world points -> the pose's camera frame (``R^T (X - t)``)."""
    return (points - pose[:, 3]) @ pose[:, :3]


def heading_vectors(yaw: np.ndarray) -> np.ndarray:
    """(N, 3) unit length directions of boxes of yaw ``yaw`` (N,) about y (KITTI: yaw 0 faces
    +x, yaw pi/2 faces -z)."""
    return np.stack([np.cos(yaw), np.zeros_like(yaw), -np.sin(yaw)], axis=-1)


def heading_yaw(vectors: np.ndarray) -> np.ndarray:
    """(N,) yaw about y of directions (N, 3) (their part in the x-z plane)."""
    return np.arctan2(-vectors[:, 2], vectors[:, 0])


def yaw_to_world(rotation_y: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N,) camera-frame yaw -> world-frame yaw (about the world's y axis)."""
    return heading_yaw(heading_vectors(rotation_y) @ pose[:, :3].T)


def yaw_to_camera(yaw: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(N,) world-frame yaw -> the pose's camera-frame ``rotation_y``."""
    return heading_yaw(heading_vectors(yaw) @ pose[:, :3])
