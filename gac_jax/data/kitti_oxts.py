"""OXTS packets (KITTI's GPS/IMU) and the camera poses the KITTI devkit makes of them.

An OXTS packet is one line of the 30 numbers of :data:`FIELDS` (the devkit's
``dataformat.txt``): a raw drive has one packet per frame in ``oxts/data/NNNNNNNNNN.txt``,
a tracking sequence one line per frame in ``oxts/SSSS.txt``. Latitude and longitude are in
degrees, altitude in metres, roll/pitch/yaw in radians (yaw 0: east, counter-clockwise).

Poses as the devkit's ``convertOxtsToPose`` makes them: a Mercator projection scaled by the
first packet's latitude (``s = cos(lat0 pi / 180)``, ``t = [s r lon pi / 180,
s r log(tan((90 + lat) pi / 360)), alt]``, ``r = 6378137`` m), the rotation
``Rz(yaw) Ry(pitch) Rx(roll)``, each relative to the first packet: IMU (x forward, y left,
z up) of frame k -> IMU of frame 0. :func:`camera_poses` carries them into the rectified
camera-0 frame (x right, y down, z forward) through the calibration, IMU -> velodyne ->
camera -> rectified camera: ``T = R0_rect Tr_velo_to_cam Tr_imu_to_velo`` and
``pose_cam = T pose_imu T^-1``. That is the pose convention of the tracker and of
``poses/SSSS.txt`` (KITTI odometry): camera of frame k -> camera of frame 0,
``X_0 = R X_k + t``.
"""

from __future__ import annotations

import math
import os

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes
from gac_jax.data.kitti_calib import Calibration

FIELDS = (
    *("lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu"),
    *("ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu"),
    *("pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode"),
)
EARTH_RADIUS = 6378137.0  # metres (the devkit's latlonToMercator)


def parse_oxts(text: str, path: str | os.PathLike = "<oxts>") -> np.ndarray:
    """(N, 30) float64 packets of an OXTS file, one per non-empty line (:data:`FIELDS`).

    Raises:
      KittiFormatError: a line without 30 numbers, a non-finite position or angle, a latitude
        outside (-90, 90) (naming the line and field), or no packet at all.
    """
    rows = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) != len(FIELDS):
            raise KittiFormatError(
                path, f"an OXTS packet has {len(FIELDS)} numbers, found {len(fields)}", lineno
            )
        row = []
        for name, f in zip(FIELDS, fields, strict=True):
            try:
                row.append(float(f))
            except ValueError:
                raise KittiFormatError(path, f"{name}: non-numeric value {f!r}", lineno) from None
        for name, v in zip(FIELDS[:6], row[:6], strict=True):
            if not math.isfinite(v):
                raise KittiFormatError(path, f"{name}: non-finite value", lineno)
        if not -90.0 < row[0] < 90.0:
            raise KittiFormatError(path, f"lat: {row[0]:g} is not a latitude", lineno)
        rows.append(row)
    if not rows:
        raise KittiFormatError(path, "no OXTS packet in this file")
    return np.array(rows, np.float64)


def read_oxts(path: str | os.PathLike) -> np.ndarray:
    """(N, 30) packets of an OXTS file (:func:`parse_oxts`)."""
    return parse_oxts(read_bytes(path, "OXTS file").decode("utf-8", "replace"), path)


def rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)`` of (N,) angles in radians."""
    c, s = np.cos, np.sin
    one, zero = np.ones_like(roll), np.zeros_like(roll)
    Rx = np.stack([one, zero, zero, zero, c(roll), -s(roll), zero, s(roll), c(roll)], -1)
    Ry = np.stack([c(pitch), zero, s(pitch), zero, one, zero, -s(pitch), zero, c(pitch)], -1)
    Rz = np.stack([c(yaw), -s(yaw), zero, s(yaw), c(yaw), zero, zero, zero, one], -1)
    shape = (*np.shape(roll), 3, 3)
    return Rz.reshape(shape) @ Ry.reshape(shape) @ Rx.reshape(shape)


def imu_world_poses(packets: np.ndarray, scale: float | None = None) -> np.ndarray:
    """(N, 4, 4) IMU -> Mercator world (east, north, up; metres) of (N, 30) packets;
    ``scale``: the Mercator scale (default: ``cos`` of the first packet's latitude)."""
    packets = np.asarray(packets, np.float64)
    lat, lon, alt = packets[:, 0], packets[:, 1], packets[:, 2]
    if scale is None:
        scale = math.cos(lat[0] * math.pi / 180.0)
    poses = np.zeros((len(packets), 4, 4))
    poses[:, :3, :3] = rotation(packets[:, 3], packets[:, 4], packets[:, 5])
    poses[:, 0, 3] = scale * EARTH_RADIUS * lon * math.pi / 180.0
    poses[:, 1, 3] = scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * math.pi / 360.0))
    poses[:, 2, 3] = alt
    poses[:, 3, 3] = 1.0
    return poses


def imu_poses(packets: np.ndarray) -> np.ndarray:
    """(N, 4, 4) IMU of frame k -> IMU of frame 0 (the devkit's ``convertOxtsToPose``)."""
    world = imu_world_poses(packets)
    return np.linalg.inv(world[0]) @ world


def _homogeneous(transform: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: transform.shape[0], : transform.shape[1]] = transform
    return out


def imu_to_camera(calib: Calibration) -> np.ndarray:
    """(4, 4) IMU -> rectified camera 0: ``R0_rect Tr_velo_to_cam Tr_imu_to_velo``.

    Raises:
      KittiFormatError: one of the three is missing (naming the file and its key there).
    """
    why = "needed for the OXTS poses"
    return (
        _homogeneous(calib.require("R0_rect", why))
        @ _homogeneous(calib.require("Tr_velo_to_cam", why))
        @ _homogeneous(calib.require("Tr_imu_to_velo", why))
    )


def camera_poses(packets: np.ndarray, calib: Calibration) -> np.ndarray:
    """(N, 3, 4) poses of the rectified camera 0 (module docstring): camera of frame k ->
    camera of frame 0 (``X_0 = R X_k + t``) for (N, 30) packets, frame 0 the first."""
    T = imu_to_camera(calib)
    return (T @ imu_poses(packets) @ np.linalg.inv(T))[:, :3, :]
