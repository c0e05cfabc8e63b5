"""Pictures of tracks: each track's box, label and trail in its own colour, on the camera view
and on the bird's-eye view beside it (the layout of
:func:`gac_jax.drawing.detection_pictures.detection_picture`).

* camera view: the 3D box in the track's colour (:func:`track_color`, the same for a track
  in every frame), a label ``#id Car 12.3 m/s``, and a trail: where the box's bottom centre
  was drawn in the pictures of the last :data:`TRAIL_SECONDS` (:class:`ImageTrails`; points
  that were behind the camera are not drawn), so a car ahead leaves a short line behind it;
* bird's-eye view: footprints in the same colours, the track's last positions and a velocity
  arrow to where it will be in :data:`ARROW_SECONDS`, and a caption saying whether speeds are
  over the ground (the tracker had ego poses) or relative to the camera.

``tracks`` is any object with ``to_kitti_objects()`` (the boxes, camera frame), ``ids`` (N,),
``velocities`` (N, 3) m/s in camera axes (NaN: none) and ``trails`` (N arrays (K, 3), camera
frame, oldest first), as :class:`gac_jax.tracking.TrackedObjects`.
"""

from __future__ import annotations

import colorsys
from collections import deque

import cv2
import numpy as np

from gac_jax import geometry
from gac_jax.data import transforms
from gac_jax.drawing import boxes
from gac_jax.drawing.detection_pictures import bev_grid_for_height

ARROW_SECONDS = 0.5  # a velocity arrow ends where the object will be this much later
TRAIL_SECONDS = 1.0  # a camera-view trail covers this much of the past
TRAIL_FRAMES = 10  # without frame times: this many past pictures
NEAR = 0.5  # metres: points closer to the camera plane are not drawn
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


def _image_points(points: np.ndarray, P2: np.ndarray) -> np.ndarray:
    """(K, 2) pixels of camera-frame points (K, 3); NaN for those behind :data:`NEAR`."""
    uv, depth = geometry.project(points, P2)
    return np.where((depth > NEAR)[:, None], uv, np.nan)


class ImageTrails:
    """Where each track's bottom centre was drawn in the last pictures (one per stream; the
    picture's pixels, so a trail follows the box in the image).

    Args:
      seconds: the trails' length in time (frames with a time); frames: in pictures (without).
    """

    def __init__(self, seconds: float = TRAIL_SECONDS, frames: int = TRAIL_FRAMES):
        self.seconds, self.frames = seconds, frames
        self._points: dict[int, deque] = {}
        self._count = 0

    def update(self, ids, uv: np.ndarray, timestamp: float | None = None) -> list[np.ndarray]:
        """Adds this picture's points ``uv`` (N, 2; NaN: behind the camera, not added) of
        tracks ``ids`` (N,); returns each track's trail (K, 2), oldest first. Tracks not in
        ``ids`` are forgotten."""
        now = self._count if timestamp is None else float(timestamp)
        span = self.frames - 0.5 if timestamp is None else self.seconds
        self._count += 1
        ids = [int(i) for i in ids]
        self._points = {i: self._points.get(i, deque()) for i in ids}
        out = []
        for i, point in zip(ids, np.asarray(uv, np.float64).reshape(-1, 2), strict=True):
            trail = self._points[i]
            if np.all(np.isfinite(point)):
                trail.append((now, point))
            while trail and trail[0][0] < now - span:
                trail.popleft()
            out.append(np.array([p for _, p in trail]).reshape(-1, 2))
        return out


def draw_tracks_camera(
    canvas: np.ndarray,
    tracks,
    P2: np.ndarray,
    thickness: int = 2,
    objects=None,
    trails: list[np.ndarray] | None = None,
) -> None:
    """Boxes, trails and labels (``#id class speed``) on the camera view ``canvas`` (in place;
    ``objects``: the tracks' boxes in ``canvas`` pixels, default ``tracks.to_kitti_objects()``;
    ``trails``: (K, 2) pixels per track, :class:`ImageTrails`, or None: none)."""
    objects = tracks.to_kitti_objects() if objects is None else objects
    ids = tracks.ids.tolist()
    colors = [track_color(i) for i in ids]
    boxes.draw_objects_into(canvas, objects, P2, color=colors, thickness=thickness,
                          show_labels=False)  # fmt: skip
    texts = []
    for k, track_id in enumerate(ids):
        if trails is not None:
            _polyline(canvas, trails[k], colors[k], thickness)
        v = tracks.velocities[k]
        text = f"#{track_id} {objects.type[k]}"
        if np.all(np.isfinite(v)):
            text += f" {np.linalg.norm(v[[0, 2]]):.1f} m/s"
        texts.append(text)
    # labels inside the boxes' top-left corners, the surest first; one that would cover
    # another moves below it or is left out (boxes.place_labels, as for detection labels)
    order = np.argsort(-np.nan_to_num(objects.score, nan=-np.inf), kind="stable")
    corners = np.asarray(objects.bbox, np.float64)[order, :2]
    spots = boxes.place_labels([texts[k] for k in order], corners, canvas.shape[:2], 0.4)
    for k, spot in zip(order, spots, strict=True):
        if spot is not None:
            boxes.draw_label(canvas, texts[k], spot, colors[k])


def draw_tracks_bev(
    canvas: np.ndarray,
    tracks,
    grid: boxes.BevGrid,
    scale: float = 1.0,
    over_ground: bool | None = None,
) -> None:
    """Trails, velocity arrows (:data:`ARROW_SECONDS`) and ids on a bird's-eye view ``canvas``
    of ``grid`` (in place; ``scale``: the canvas's size over the grid's; ``over_ground``:
    the caption says the speeds are over the ground (True) or relative to the camera
    (False); None: no caption)."""
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
        cv2.putText(canvas, str(track_id), (int(at[0]) + 6, int(at[1]) - 6), _FONT, 0.4, color,
                    1, cv2.LINE_AA)  # fmt: skip
    if over_ground is not None:
        text = "speed over the ground" if over_ground else "speed relative to the camera"
        text += f", arrows {ARROW_SECONDS:g} s"
        (tw, th), _ = cv2.getTextSize(text, _FONT, 0.4, 1)
        x = max(canvas.shape[1] - tw - 4, 0)
        cv2.putText(canvas, text, (x, th + 4), _FONT, 0.4, (220, 220, 220), 1, cv2.LINE_AA)


def track_picture(
    image: np.ndarray,
    P2: np.ndarray,
    tracks,
    *,
    scale: float = 1.0,
    trails: ImageTrails | None = None,
    timestamp: float | None = None,
    over_ground: bool | None = None,
) -> np.ndarray:
    """Camera view | bird's-eye view of ``tracks`` (module doc).

    Args:
      image: (H, W, 3) uint8 RGB; P2: (3, 4) its projection.
      scale: size of the picture relative to the image (< 1: the image is shrunk first and
        the tracks drawn on the small one), as ``detection_picture``'s.
      trails: the stream's :class:`ImageTrails` (this picture is added to them), or None: no
        trails on the camera view; timestamp: the frame's time in seconds (None: trails
        count pictures).
      over_ground: the velocities are over the ground (the tracker had poses) or relative to
        the camera; said in the bird's-eye view (None: not said).

    Returns:
      (h, w + Wb, 3) uint8 RGB with ``(h, w) = round(scale (H, W))``, as
      :func:`~gac_jax.drawing.detection_pictures.detection_picture`.
    """
    objects = tracks.to_kitti_objects()
    if scale != 1.0:
        h, w = image.shape[:2]
        size = (max(round(h * scale), 2), max(round(w * scale), 2))
        A = transforms.resize_affine((h, w), size)
        image = cv2.resize(image, size[::-1], interpolation=cv2.INTER_AREA)
        P2 = A @ np.asarray(P2, np.float64)
        objects = objects.replace(bbox=transforms.transform_boxes(objects.bbox, A))
    camera = np.array(image, np.uint8, copy=True)
    paths = None
    if trails is not None:
        feet = _image_points(np.asarray(objects.location, np.float64).reshape(-1, 3), P2)
        paths = trails.update(tracks.ids, feet, timestamp)
    draw_tracks_camera(camera, tracks, P2, objects=objects, trails=paths)
    grid = bev_grid_for_height(image.shape[0])
    bev = np.empty((*grid.size, 3), np.uint8)
    boxes.draw_bev_into(bev, objects, grid=grid, colors=[track_color(i) for i in tracks.ids])
    bev_scale = 1.0
    if bev.shape[0] != camera.shape[0]:  # rounding of the grid size
        bev_scale = camera.shape[0] / bev.shape[0]
        bev = cv2.resize(bev, (round(bev.shape[1] * bev_scale), camera.shape[0]))
    bev = np.ascontiguousarray(bev)
    draw_tracks_bev(bev, tracks, grid, bev_scale, over_ground)
    return np.concatenate([camera, bev], axis=1)
