"""A frame's 3D scene as plain values, for the messages of a recording
(:mod:`gac_jax.streams.mcap_recording`): boxes as posed cubes with a label and metadata, the
ground plane as a flat patch, the camera's pose as a transform and its calibration.

Frames: the camera frame (x right, y down, z forward); boxes are KITTI boxes (``location`` the
bottom-face centre, dimensions ``(h, w, l)``, yaw ``rotation_y`` about the camera's y axis,
the box's length along its own x axis, :func:`gac_jax.geometry.box3d_corners`). Quaternions
are ``(x, y, z, w)``; colours ``(r, g, b, a)`` in [0, 1]. Everything is float64 numpy turned
into Python values, so that either message encoding takes it as it is.
"""

from __future__ import annotations

import functools

import numpy as np

from gac_jax.drawing.boxes import class_color
from gac_jax.drawing.track_pictures import track_color

PLANE_PATCH = (40.0, 0.02, 80.0)  # metres: the ground patch's width, thickness, depth
PLANE_AHEAD = 30.0  # metres ahead of the camera: the patch's centre
PLANE_COLOR = (0.5, 0.5, 0.5, 0.25)
LABEL_ABOVE = 0.3  # metres between a box's top and its label


def matrix_quaternion(R: np.ndarray) -> np.ndarray:
    """(4,) unit quaternion of a (3, 3) rotation matrix (Shepperd's method: the largest of
    ``w, x, y, z`` first, so no division by a small number); ``w >= 0``."""
    R = np.asarray(R, np.float64)
    trace = np.trace(R)
    diagonal = np.diag(R)
    k = int(np.argmax([trace, *diagonal]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + trace)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = k - 1
        j, m = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[m, m])
        q = [0.0, 0.0, 0.0, (R[m, j] - R[j, m]) / s]
        q[i] = s / 4
        q[j] = (R[j, i] + R[i, j]) / s
        q[m] = (R[m, i] + R[i, m]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of a unit quaternion ``(x, y, z, w)``."""
    x, y, z, w = np.asarray(q, np.float64)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def pose_dict(position, orientation) -> dict:
    x, y, z = (float(v) for v in position)
    qx, qy, qz, qw = (float(v) for v in orientation)
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }


def color_dict(rgb: tuple[int, int, int], alpha: float = 1.0) -> dict:
    r, g, b = (c / 255.0 for c in rgb)
    return {"r": r, "g": g, "b": b, "a": float(alpha)}


def box_entities(objects, ids=None, velocities=None, over_ground: bool = False) -> list[dict]:
    """One entity per box: ``{"id", "cube": {"pose", "size", "color"}, "label": {"pose",
    "text"}, "metadata": [(key, value), ...], "name", "score", "track_id", "velocity"}``.

    Args:
      objects: :class:`~gac_jax.data.kitti.KittiObjects` (camera frame).
      ids: (N,) track ids (colours per id), or None (detections: colours per class).
      velocities: (N, 3) m/s in camera axes (NaN: unknown), or None.
      over_ground: the velocities are over the ground (ego motion removed), else relative to
        the camera.

    The arithmetic is done on the (N, ...) arrays at once and the values turned into Python
    numbers together; the colour dictionaries are shared between calls (read-only).
    """
    n = len(objects)
    dims = np.asarray(objects.dimensions, np.float64).reshape(n, 3)
    loc = np.asarray(objects.location, np.float64).reshape(n, 3)
    half = np.asarray(objects.rotation_y, np.float64).reshape(n) / 2
    x, z = loc[:, 0].tolist(), loc[:, 2].tolist()
    centre_y = (loc[:, 1] - dims[:, 0] / 2).tolist()
    label_y = (loc[:, 1] - dims[:, 0] - LABEL_ABOVE).tolist()
    sin, cos = np.sin(half).tolist(), np.cos(half).tolist()
    h, w, l = dims.T.tolist()
    names = [str(name) for name in objects.type]
    scores = np.asarray(objects.score, np.float64).reshape(n).tolist()
    tracks = [None] * n if ids is None else np.asarray(ids, np.int64).reshape(n).tolist()
    moving, speeds = [False] * n, [0.0] * n
    if velocities is not None and n:
        velocities = np.asarray(velocities, np.float64).reshape(n, 3)
        moving = np.all(np.isfinite(velocities), axis=1).tolist()
        speeds = np.hypot(velocities[:, 0], velocities[:, 2]).tolist()
        velocities = velocities.tolist()
    frame = "over the ground" if over_ground else "relative to the camera"
    entities = []
    for i in range(n):
        name, score, track = names[i], scores[i], tracks[i]
        fill, line = _colors(name, track)
        text = f"{name} {score:.2f}" if track is None else f"#{track} {name} {score:.2f}"
        metadata = [("class", name), ("score", f"{score:.4f}")]
        velocity = None
        if track is not None:
            metadata.insert(0, ("id", str(track)))
        if moving[i]:
            velocity = velocities[i]
            metadata += [
                ("velocity", " ".join(f"{v:.3f}" for v in velocity) + f" m/s ({frame})"),
                ("speed", f"{speeds[i]:.2f} m/s"),
            ]
            text += f" {speeds[i]:.1f} m/s" + ("" if over_ground else " rel.")
        entities.append(
            {
                "id": f"track {track}" if track is not None else f"box {i}",
                "name": name,
                "score": score,
                "track_id": track,
                "velocity": velocity,
                "cube": {
                    "pose": {
                        "position": {"x": x[i], "y": centre_y[i], "z": z[i]},
                        "orientation": {"x": 0.0, "y": sin[i], "z": 0.0, "w": cos[i]},
                    },
                    "size": {"x": l[i], "y": h[i], "z": w[i]},
                    "color": fill,
                },
                "label": {
                    "pose": {
                        "position": {"x": x[i], "y": label_y[i], "z": z[i]},
                        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                    },
                    "text": text,
                },
                "color": line,
                "metadata": metadata,
            }
        )
    return entities


@functools.lru_cache(maxsize=4096)
def _colors(name: str, track: int | None) -> tuple[dict, dict]:
    """The cube's (half transparent) and the label's colour of a box (shared, read-only)."""
    rgb = class_color(name) if track is None else track_color(track)
    return color_dict(rgb, 0.5), color_dict(rgb)


def plane_patch(plane: np.ndarray) -> dict:
    """The ground plane ``(a, b, c, d)`` (``a x + b y + c z + d = 0``, camera frame, normal
    up) as a flat cube: ``{"pose", "size", "color"}``, centred under the point
    :data:`PLANE_AHEAD` metres ahead, its y axis along the normal. Shared between calls with
    the same plane (read-only)."""
    return _plane_patch(tuple(np.asarray(plane, np.float64).reshape(4).tolist()))


@functools.lru_cache(maxsize=64)
def _plane_patch(plane: tuple[float, float, float, float]) -> dict:
    plane = np.asarray(plane)
    normal = plane[:3] / np.linalg.norm(plane[:3])
    d = plane[3] / np.linalg.norm(plane[:3])
    ahead = np.array([0.0, 0.0, PLANE_AHEAD])
    centre = ahead - (normal @ ahead + d) * normal
    # the rotation taking the cube's y axis (down in the camera frame) onto -normal (down)
    down = -normal
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(y, down)
    sin, cos = np.linalg.norm(axis), float(y @ down)
    if sin < 1e-12:
        q = np.array([0.0, 0.0, 0.0, 1.0]) if cos > 0 else np.array([1.0, 0.0, 0.0, 0.0])
    else:
        half = np.arctan2(sin, cos) / 2
        q = np.concatenate([axis / sin * np.sin(half), [np.cos(half)]])
    w, t, depth = PLANE_PATCH
    return {
        "pose": pose_dict(centre, q),
        "size": {"x": w, "y": t, "z": depth},
        "color": dict(zip("rgba", PLANE_COLOR, strict=True)),
    }


def camera_transform(pose: np.ndarray) -> tuple[list[float], list[float]]:
    """``(translation, rotation)`` of a (3, 4) camera -> world pose: the camera frame's
    origin and orientation in the world frame."""
    pose = np.asarray(pose, np.float64).reshape(3, 4)
    return [float(v) for v in pose[:, 3]], [float(v) for v in matrix_quaternion(pose[:, :3])]


def calibration(P2: np.ndarray) -> dict:
    """``K`` (9,), ``P`` (12,), ``R`` (9,) row-major of a (3, 4) projection (no distortion:
    KITTI's images are rectified)."""
    P = np.asarray(P2, np.float64).reshape(3, 4)
    return {
        "K": [float(v) for v in P[:, :3].ravel()],
        "P": [float(v) for v in P.ravel()],
        "R": [float(v) for v in np.eye(3).ravel()],
    }
