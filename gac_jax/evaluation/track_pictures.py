"""Pictures of tracks: each object's box with its id and speed, a trail of its last positions
and an arrow of its velocity (where it will be in :data:`ARROW_SECONDS`), on the camera view
and on the bird's-eye view beside it (the layout of
:func:`gac_jax.evaluation.detection_pictures.detection_picture`).

``tracks`` is any object with ``to_kitti_objects()`` (the boxes, camera frame), ``ids`` (N,),
``velocities`` (N, 3) m/s in camera axes (NaN: none) and ``trails`` (N arrays (K, 3), camera
frame, oldest first), as :class:`gac_jax.tracking.TrackedObjects`.
"""

from __future__ import annotations

import colorsys

import cv2
import numpy as np

from gac_jax import geometry
from gac_jax.data import transforms
from gac_jax.evaluation import viz
from gac_jax.evaluation.detection_pictures import bev_grid_for_height

ARROW_SECONDS = 1.0  # a velocity arrow ends where the object will be this much later
NEAR = 0.5  # metres: trail points and arrows closer to the camera plane are not drawn
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def track_color(track_id: int) -> tuple[int, int, int]:
    """A bright colour per id (golden-ratio hues: neighbouring ids differ)."""
    hue = (int(track_id) * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.85, 1.0)
    return int(255 * r), int(255 * g), int(255 * b)


def _polyline(canvas, points: np.ndarray, color, thickness: int) -> None:
    if len(points) >= 2:
        pts = np.round(np.clip(points, -(1 << 14), 1 << 14)).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(canvas, [pts], False, color, thickness, cv2.LINE_AA)


def _arrow(canvas, start: np.ndarray, end: np.ndarray, color, thickness: int) -> None:
    if np.all(np.isfinite(start)) and np.all(np.isfinite(end)):
        p, q = tuple(int(round(v)) for v in start), tuple(int(round(v)) for v in end)
        if p != q and max(abs(v) for v in (*p, *q)) < 1 << 15:
            cv2.arrowedLine(canvas, p, q, color, thickness, cv2.LINE_AA, tipLength=0.25)


def _label(canvas, text: str, at: np.ndarray, color) -> None:
    h, w = canvas.shape[:2]
    (tw, th), base = cv2.getTextSize(text, _FONT, 0.45, 1)
    x = int(np.clip(at[0], 0, max(w - tw - 2, 0)))
    y = int(np.clip(at[1] - th - base - 2, 0, max(h - th - base - 2, 0)))
    cv2.rectangle(canvas, (x, y), (x + tw + 2, y + th + base + 2), color, cv2.FILLED)
    cv2.putText(canvas, text, (x + 1, y + th + 1), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)


def _image_points(points: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """(K, 2) pixels of camera-frame points (K, 3); NaN for those behind :data:`NEAR`."""
    uv, depth = geometry.project(points, P2)
    return np.where((depth > NEAR)[:, None], uv, np.nan)


def draw_tracks_camera(
    canvas: np.ndarray, tracks, P2: np.ndarray, thickness: int = 2, objects=None
) -> None:
    """Ids, trails and velocity arrows on the camera view ``canvas`` (in place; ``objects``:
    the tracks' boxes in ``canvas`` pixels, default ``tracks.to_kitti_objects()``)."""
    objects = tracks.to_kitti_objects() if objects is None else objects
    for i, track_id in enumerate(tracks.ids.tolist()):
        color = track_color(track_id)
        trail = _image_points(tracks.trails[i], P2)
        _polyline(canvas, trail[np.all(np.isfinite(trail), axis=1)], color, thickness)
        v = tracks.velocities[i]
        text = f"#{track_id}"
        if np.all(np.isfinite(v)):
            text += f" {np.linalg.norm(v[[0, 2]]):.1f} m/s"
            ends = _image_points(
                np.stack([objects.location[i], objects.location[i] + ARROW_SECONDS * v]), P2
            )
            _arrow(canvas, ends[0], ends[1], color, thickness)
        _label(canvas, text, objects.bbox[i, :2], color)


def draw_tracks_bev(canvas: np.ndarray, tracks, grid: viz.BevGrid, scale: float = 1.0) -> None:
    """Trails, velocity arrows and ids on a bird's-eye view ``canvas`` of ``grid`` (in place;
    ``scale``: the canvas's size over the grid's)."""
    for i, track_id in enumerate(tracks.ids.tolist()):
        color = track_color(track_id)
        trail = tracks.trails[i]
        _polyline(canvas, scale * grid.to_pixels(trail[:, 0], trail[:, 2]), color, 2)
        centre = tracks.locations[i]
        at = scale * grid.to_pixels(centre[0], centre[2])
        v = tracks.velocities[i]
        if np.all(np.isfinite(v)):
            end = centre + ARROW_SECONDS * v
            _arrow(canvas, at, scale * grid.to_pixels(end[0], end[2]), color, 2)
        cv2.putText(
            canvas,
            str(track_id),
            (int(at[0]) + 6, int(at[1]) - 6),
            _FONT,
            0.4,
            color,
            1,
            cv2.LINE_AA,
        )


def track_picture(image: np.ndarray, P2: np.ndarray, tracks, *, scale: float = 1.0) -> np.ndarray:
    """Camera view | bird's-eye view of ``tracks`` (module doc).

    Args:
      image: (H, W, 3) uint8 RGB; P2: (3, 4) its projection.
      scale: size of the picture relative to the image (< 1: the image is shrunk first and
        the tracks drawn on the small one), as ``detection_picture``'s.

    Returns:
      (h, w + Wb, 3) uint8 RGB with ``(h, w) = round(scale (H, W))``, as
      :func:`~gac_jax.evaluation.detection_pictures.detection_picture`.
    """
    objects = tracks.to_kitti_objects()
    if scale != 1.0:
        h, w = image.shape[:2]
        size = (max(round(h * scale), 2), max(round(w * scale), 2))
        A = transforms.resize_affine((h, w), size)
        image = cv2.resize(image, size[::-1], interpolation=cv2.INTER_AREA)
        P2 = A @ np.asarray(P2, np.float64)
        objects = objects.replace(bbox=transforms.transform_boxes(objects.bbox, A))
    camera = viz.draw_detections(image, P2, objects, show_labels=False)
    draw_tracks_camera(camera, tracks, P2, objects=objects)
    grid = bev_grid_for_height(image.shape[0])
    bev = viz.draw_bev(objects, grid=grid)
    scale = 1.0
    if bev.shape[0] != camera.shape[0]:  # rounding of the grid size
        scale = camera.shape[0] / bev.shape[0]
        bev = cv2.resize(bev, (round(bev.shape[1] * scale), camera.shape[0]))
    bev = np.ascontiguousarray(bev)
    draw_tracks_bev(bev, tracks, grid, scale)
    return np.concatenate([camera, bev], axis=1)
