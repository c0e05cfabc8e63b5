"""Boxes drawn on a picture (OpenCV; RGB uint8 in, RGB uint8 out).

* :func:`draw_detections` / :func:`draw_objects`: 3D boxes as projected
  wireframes (edges cut at the camera's near plane, then clipped to the image)
  with a cross on the front face (corners 0, 1, 5, 4 of
  :func:`gac_jax.geometry.box3d_corners`, the object's +x side), 2D boxes and
  "class score" labels; ground truth in its own colour.
* :func:`draw_bev` on a :class:`BevGrid`: top-down view (camera x to the
  right, z up the picture) with a metre grid, boxes as rotated rectangles and a
  heading mark from the centre to the front edge.

Tiles of several pictures and the PNG writer: :mod:`gac_jax.drawing.picture_grid`; depth
maps: :mod:`gac_jax.drawing.depth_pictures`. Nothing here writes files.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence

import cv2
import numpy as np

from gac_jax import geometry
from gac_jax.data.kitti import KittiObjects
from gac_jax.drawing.picture_grid import check_image as _check_image

Color = tuple[int, int, int]

GT_COLOR: Color = (0, 255, 0)
CLASS_COLORS: dict[str, Color] = {
    "Car": (255, 128, 0),
    "Van": (255, 200, 0),
    "Truck": (255, 80, 80),
    "Pedestrian": (255, 0, 255),
    "Person_sitting": (200, 0, 255),
    "Cyclist": (0, 200, 255),
}
DEFAULT_COLOR: Color = (255, 255, 0)

# Segments of a box wireframe: the 12 edges, then the front-face cross (diagonals 0-5, 1-4).
WIREFRAME = np.concatenate([geometry.BOX_EDGES, [[0, 5], [1, 4]]])
_SHIFT = 4  # cv2 fixed-point bits: sub-pixel line end points
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def class_color(name: str) -> Color:
    """Colour of a predicted class (:data:`CLASS_COLORS`, else :data:`DEFAULT_COLOR`)."""
    return CLASS_COLORS.get(str(name), DEFAULT_COLOR)


def drawable(objects: KittiObjects) -> np.ndarray:
    """(N,) mask of objects with a 3D box (not DontCare, positive dimensions, finite)."""
    ok = (objects.type != "DontCare") & np.all(objects.dimensions > 0, axis=1)
    return ok & np.all(np.isfinite(objects.location), axis=1) & np.isfinite(objects.rotation_y)


# --------------------------------------------------------------------------- segment geometry


def box3d_segments(
    location: np.ndarray,
    dims: np.ndarray,
    ry: np.ndarray,
    P: np.ndarray,
    near: float = 0.1,
) -> tuple[np.ndarray, np.ndarray]:
    """Image segments of 3D-box wireframes, cut at the plane ``depth = near``.

    Args:
      location: (N, 3) bottom-face centres (camera frame); dims: (N, 3) ``(h, w, l)``;
      ry: (N,) yaw; P: (3, 4) projection.

    Returns:
      segments (N, 14, 2, 2) end points ``(u, v)`` of the :data:`WIREFRAME`
      segments (12 edges, then the 2 front-face diagonals), and valid (N, 14),
      False for segments entirely behind the near plane. Not clipped to an image.
    """
    corners = geometry.box3d_corners(location, dims, ry)  # (N, 8, 3)
    a, b = corners[:, WIREFRAME[:, 0]], corners[:, WIREFRAME[:, 1]]  # (N, 14, 3)
    _, wa = geometry.project(a, P)
    _, wb = geometry.project(b, P)
    valid = (wa >= near) | (wb >= near)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((near - wa) / (wb - wa), 0.0, 1.0)
    cut = a + t[..., None] * (b - a)
    a = np.where((wa < near)[..., None], cut, a)
    b = np.where((wb < near)[..., None], cut, b)
    uv_a, _ = geometry.project(a, P)
    uv_b, _ = geometry.project(b, P)
    segments = np.stack([uv_a, uv_b], axis=-2)
    segments = np.where(valid[..., None, None], segments, 0.0)
    return segments, valid


def clip_segments(
    segments: np.ndarray, image_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Liang-Barsky clipping of (..., 2, 2) segments to ``[0, W-1] x [0, H-1]``.

    Returns the clipped segments and a mask of those with a visible part.
    """
    seg = np.asarray(segments, np.float64)
    height, width = image_size
    p0, d = seg[..., 0, :], seg[..., 1, :] - seg[..., 0, :]
    t0 = np.zeros(seg.shape[:-2])
    t1 = np.ones(seg.shape[:-2])
    inside = np.all(np.isfinite(seg), axis=(-1, -2))
    for axis, hi in ((0, width - 1.0), (1, height - 1.0)):
        for p, q in ((-d[..., axis], p0[..., axis]), (d[..., axis], hi - p0[..., axis])):
            with np.errstate(divide="ignore", invalid="ignore"):
                r = q / p
            parallel = p == 0
            inside &= ~(parallel & (q < 0))
            t0 = np.where(~parallel & (p < 0), np.maximum(t0, r), t0)
            t1 = np.where(~parallel & (p > 0), np.minimum(t1, r), t1)
    inside &= t0 <= t1
    out = np.stack([p0 + t0[..., None] * d, p0 + t1[..., None] * d], axis=-2)
    return np.where(inside[..., None, None], out, 0.0), inside


def _fixed(point: np.ndarray) -> tuple[int, int]:
    return (int(round(point[0] * (1 << _SHIFT))), int(round(point[1] * (1 << _SHIFT))))


def _fixed_points(points: np.ndarray) -> np.ndarray:
    """(..., 2) float pixels -> int32 fixed point of :data:`_SHIFT` bits (as :func:`_fixed`:
    round half to even)."""
    return np.round(np.asarray(points, np.float64) * (1 << _SHIFT)).astype(np.int32)


def _colour_runs(colors: Sequence[Color]) -> list[tuple[Color, int, int]]:
    """``(colour, start, stop)`` of consecutive items of one colour: one OpenCV call each,
    drawn in the items' order."""
    runs: list[tuple[Color, int, int]] = []
    for i, c in enumerate(colors):
        if runs and runs[-1][0] == c:
            runs[-1] = (c, runs[-1][1], i + 1)
        else:
            runs.append((c, i, i + 1))
    return runs


def _polylines(canvas, points: np.ndarray, closed: bool, color, thickness) -> None:
    """All (M, K, 2) float polylines in one ``cv2.polylines`` call (anti-aliased, sub-pixel):
    the same pixels as ``cv2.line`` / ``cv2.rectangle`` one by one in that order."""
    if len(points):
        pts = list(_fixed_points(points))
        cv2.polylines(canvas, pts, closed, color, thickness, cv2.LINE_AA, _SHIFT)


def place_labels(
    texts: Sequence[str], corners: np.ndarray, image_size: tuple[int, int], scale: float
) -> list[tuple[int, int, int, int, int] | None]:
    """Where each label goes: ``(x, y, w, h, baseline)`` inside the top-left corner of its box
    (kept within the image), or None when it cannot be placed without covering another.

    Labels are placed in the given order (callers pass the highest score first); one that
    would overlap a placed label moves down below it, up to a few times, and is dropped when
    it still overlaps (so nearby boxes keep readable labels)."""
    height, width = image_size
    taken = np.zeros((height, width), bool)  # pixels under a placed label
    out: list[tuple[int, int, int, int, int] | None] = []
    for text, corner in zip(texts, corners, strict=True):
        (tw, th), base = cv2.getTextSize(text, _FONT, scale, 1)
        w, h = tw + 2, th + base + 2  # the filled strip, both ends inclusive
        x = min(max(math.floor(corner[0]), 0), max(width - w, 0))
        y = min(max(math.floor(corner[1]), 0), max(height - h, 0))
        spot = None
        for _ in range(4):
            rows = np.flatnonzero(taken[y : y + h, x : x + w].any(axis=1))
            if not len(rows):
                spot = (x, y, w, h, base)
                taken[y : y + h, x : x + w] = True
                break
            y += int(rows[-1]) + 1  # just below the label in the way
            if y + h > height:
                break
        out.append(spot)
    return out


def draw_label(canvas, text, spot, color, scale=0.4):
    """Text on a filled strip at ``spot`` (:func:`place_labels`)."""
    x, y, w, h, _ = spot
    cv2.rectangle(canvas, (x, y), (x + w - 1, y + h - 1), color, cv2.FILLED)
    luma = 0.299 * color[0] + 0.587 * color[1] + 0.114 * color[2]
    ink = (0, 0, 0) if luma > 128 else (255, 255, 255)
    th = h - 2 - spot[4]
    cv2.putText(canvas, text, (x + 1, y + th + 1), _FONT, scale, ink, 1, cv2.LINE_AA)


# --------------------------------------------------------------------------- camera view


def draw_objects(image: np.ndarray, objects: KittiObjects, P2: np.ndarray, **options) -> np.ndarray:
    """Draws objects on a copy of ``image`` ((H, W, 3) uint8 RGB; ``options`` as
    :func:`draw_objects_into`); returns the (H, W, 3) uint8 RGB picture."""
    canvas = _check_image(image).copy()
    draw_objects_into(canvas, objects, P2, **options)
    return canvas


def draw_objects_into(
    canvas: np.ndarray,
    objects: KittiObjects,
    P2: np.ndarray,
    *,
    color: Color | None = None,
    thickness: int = 2,
    draw_3d: bool = True,
    draw_2d: bool = False,
    show_labels: bool = True,
    near: float = 0.1,
) -> None:
    """Draws objects on ``canvas`` itself ((H, W, 3) uint8 RGB; a view into a larger picture
    is fine): all wireframes in one ``cv2.polylines`` call per run of one colour, then the 2D
    boxes likewise, then the labels (highest score placed first, none covering another:
    :func:`place_labels`).

    Args:
      canvas: the picture; P2: (3, 4) projection of this image.
      objects: boxes in this image's camera frame; ``bbox`` in its pixels.
      color: one colour for all, a list of one per object, or None: :func:`class_color`.
      draw_3d: projected wireframes with the front-face cross (DontCare and
        boxes without dimensions are skipped; edges behind ``near`` are cut).
      draw_2d: the ``bbox`` rectangles (thin).
      show_labels: "type score" (score when finite) inside the top-left corner
        of the object's 2D extent (projected 3D box, or ``bbox`` without 3D).
    """
    size = canvas.shape[:2]
    kept = objects.type != "DontCare"
    objects = objects.select(kept)
    if isinstance(color, list):  # one per object
        colors = [c for c, k in zip(color, kept, strict=True) if k]
    else:
        colors = [color if color is not None else class_color(t) for t in objects.type]
    has_3d = drawable(objects)
    drawn_3d = np.zeros(len(objects), bool)
    extent = objects.bbox.copy()
    if draw_3d and has_3d.any():
        idx = np.flatnonzero(has_3d)
        segments, valid = box3d_segments(
            objects.location[idx], objects.dimensions[idx], objects.rotation_y[idx], P2, near
        )
        clipped, visible = clip_segments(segments, size)
        visible &= valid
        for c, start, stop in _colour_runs([colors[i] for i in idx]):
            _polylines(canvas, clipped[start:stop][visible[start:stop]], False, c, thickness)
        shown = visible.any(axis=1)
        lo = np.where(visible[..., None, None], clipped, np.inf).min(axis=(1, 2))
        hi = np.where(visible[..., None, None], clipped, -np.inf).max(axis=(1, 2))
        extent[idx[shown]] = np.concatenate([lo, hi], axis=1)[shown]
        drawn_3d[idx[shown]] = True
    if draw_2d:
        box = objects.bbox
        ok = np.all(np.isfinite(box), axis=1) & (box[:, 2] > box[:, 0]) & (box[:, 3] > box[:, 1])
        x1, y1, x2, y2 = box.T
        rects = np.stack(
            [np.stack(p, axis=-1) for p in ((x1, y1), (x2, y1), (x2, y2), (x1, y2))], 1
        )
        for c, start, stop in _colour_runs(colors):
            _polylines(canvas, rects[start:stop][ok[start:stop]], True, c, 1)
    if not show_labels:
        return
    labelled = np.flatnonzero(drawn_3d | draw_2d)
    score = objects.score[labelled]
    order = labelled[np.argsort(-np.where(np.isfinite(score), score, -np.inf), kind="stable")]
    texts = {
        i: str(objects.type[i])
        + (f" {objects.score[i]:.2f}" if np.isfinite(objects.score[i]) else "")
        for i in order
    }
    spots = dict(
        zip(order, place_labels([texts[i] for i in order], extent[order], size, 0.4), strict=True)
    )
    for i in labelled:  # in the objects' order, as before
        if spots[i] is not None:
            draw_label(canvas, texts[i], spots[i], colors[i])


def draw_detections(image: np.ndarray, P2: np.ndarray, *objects, **options) -> np.ndarray:
    """:func:`draw_detections_into` on a copy of ``image`` ((H, W, 3) uint8 RGB);
    ``objects``: ``predictions[, ground_truth]``."""
    canvas = _check_image(image).copy()
    draw_detections_into(canvas, P2, *objects, **options)
    return canvas


def draw_detections_into(
    canvas: np.ndarray,
    P2: np.ndarray,
    predictions: KittiObjects | None = None,
    ground_truth: KittiObjects | None = None,
    *,
    draw_2d: bool = True,
    show_labels: bool = True,
    thickness: int = 2,
) -> None:
    """Ground truth (thin, :data:`GT_COLOR`) under predictions (class colours, with scores),
    on ``canvas`` itself ((H, W, 3) uint8 RGB, may be a view).

    Args:
      P2: (3, 4) projection of the picture.
      predictions, ground_truth: :class:`KittiObjects` in this image's frame, or None.
    """
    if ground_truth is not None:
        thin = max(thickness - 1, 1)
        draw_objects_into(
            canvas, ground_truth, P2, color=GT_COLOR, thickness=thin, show_labels=False
        )
    if predictions is not None:
        draw_objects_into(
            canvas, predictions, P2, thickness=thickness, draw_2d=draw_2d, show_labels=show_labels
        )


# --------------------------------------------------------------------------- bird's-eye view


@dataclasses.dataclass(frozen=True)
class BevGrid:
    """Metric frame of a bird's-eye-view picture.

    Camera ``x`` (right) maps to columns, camera ``z`` (forward) to rows
    upwards: ``u = (x - x_range[0]) * pixels_per_metre``,
    ``v = (z_range[1] - z) * pixels_per_metre``; both range ends are inside.
    """

    x_range: tuple[float, float] = (-30.0, 30.0)
    z_range: tuple[float, float] = (0.0, 70.0)
    pixels_per_metre: float = 10.0
    grid_step: float = 10.0

    @property
    def size(self) -> tuple[int, int]:
        """``(H, W)`` of the picture."""
        ppm = self.pixels_per_metre
        h = round((self.z_range[1] - self.z_range[0]) * ppm) + 1
        w = round((self.x_range[1] - self.x_range[0]) * ppm) + 1
        return int(h), int(w)

    def to_pixels(self, x: np.ndarray, z: np.ndarray) -> np.ndarray:
        """(..., 2) pixel ``(u, v)`` of ground points ``(x, z)`` (metres)."""
        u = (np.asarray(x, np.float64) - self.x_range[0]) * self.pixels_per_metre
        v = (self.z_range[1] - np.asarray(z, np.float64)) * self.pixels_per_metre
        return np.stack([u, v], axis=-1)


@functools.lru_cache(maxsize=8)
def _bev_background_cached(grid: BevGrid, background: Color, line: Color) -> np.ndarray:
    h, w = grid.size
    canvas = np.empty((h, w, 3), np.uint8)
    canvas[:] = background
    step = grid.grid_step
    for x in np.arange(math.ceil(grid.x_range[0] / step) * step, grid.x_range[1] + 1e-9, step):
        u = grid.to_pixels(x, grid.z_range[0])[0]
        cv2.line(canvas, (round(u), 0), (round(u), h - 1), line, 1)
        (tw, _), _ = cv2.getTextSize(f"{x:g}", _FONT, 0.35, 1)
        # x along the bottom row, except at the camera and where the text would leave the
        # picture or sit on the z labels' column (the left edge: "0 m" is there)
        if x != 0 and u > 0 and round(u) + 3 + tw < w:
            cv2.putText(canvas, f"{x:g}", (round(u) + 3, h - 4), _FONT, 0.35, line, 1, cv2.LINE_AA)
    for z in np.arange(math.ceil(grid.z_range[0] / step) * step, grid.z_range[1] + 1e-9, step):
        v = grid.to_pixels(grid.x_range[0], z)[1]
        cv2.line(canvas, (0, round(v)), (w - 1, round(v)), line, 1)
        (_, th), _ = cv2.getTextSize(f"{z:g} m", _FONT, 0.35, 1)
        if round(v) - 3 - th >= 0:  # a label that fits under the top edge
            cv2.putText(canvas, f"{z:g} m", (3, round(v) - 3), _FONT, 0.35, line, 1, cv2.LINE_AA)
    # Camera at the origin: a small triangle pointing forward (+z, up the picture).
    o = grid.to_pixels(0.0, 0.0)
    tri = np.array([o + [-6, 0], o + [6, 0], o + [0, -10]])
    cv2.fillPoly(
        canvas, [np.round(tri * (1 << _SHIFT)).astype(np.int32)], line, cv2.LINE_AA, _SHIFT
    )
    canvas.flags.writeable = False  # shared by every caller: they draw on copies
    return canvas


def _bev_boxes(canvas, grid, objects, color, thickness):
    """Footprints (one ``cv2.polylines`` per run of one colour) and heading marks (``color``:
    one, one per object, or None: per class)."""
    shown = drawable(objects)
    if isinstance(color, list):
        color = [c for c, k in zip(color, shown, strict=True) if k]
    objects = objects.select(shown)
    if not len(objects):
        return
    corners = geometry.box3d_corners(objects.location, objects.dimensions, objects.rotation_y)
    footprint = grid.to_pixels(corners[:, :4, 0], corners[:, :4, 2])  # (N, 4, 2)
    centre = footprint.mean(axis=1)
    front = footprint[:, :2].mean(axis=1)  # corners 0, 1: the front (+x) edge
    heading = np.stack([centre, front], axis=1)  # (N, 2, 2)
    colors = color if isinstance(color, list) else [color or class_color(t) for t in objects.type]
    for c, start, stop in _colour_runs(colors):
        _polylines(canvas, footprint[start:stop], True, c, thickness)
        _polylines(canvas, heading[start:stop], False, c, thickness)


def draw_bev(*objects, grid: BevGrid | None = None, **options) -> np.ndarray:
    """Bird's-eye view: footprints (bottom faces) with heading marks; GT under predictions.

    ``objects``: ``predictions[, ground_truth]``; ``options`` as :func:`draw_bev_into`.
    Returns an (H, W, 3) uint8 RGB picture of ``grid.size`` (default 701 x 601
    for x in [-30, 30] m, z in [0, 70] m at 10 px/m). Ground truth is drawn in
    :data:`GT_COLOR`, predictions in their class colours; the heading mark
    runs from the footprint's centre to the middle of its front edge.
    """
    grid = grid or BevGrid()
    canvas = np.empty((*grid.size, 3), np.uint8)
    draw_bev_into(canvas, *objects, grid=grid, **options)
    return canvas


def draw_bev_into(
    canvas: np.ndarray,
    predictions: KittiObjects | None = None,
    ground_truth: KittiObjects | None = None,
    grid: BevGrid | None = None,
    *,
    thickness: int = 2,
    background: Color = (24, 24, 24),
    grid_color: Color = (80, 80, 80),
    colors: list[Color] | None = None,
) -> None:
    """:func:`draw_bev` into ``canvas`` ((H, W, 3) uint8 of ``grid.size``, may be a view):
    the grid picture, then the boxes (``colors``: one per prediction, default per class)."""
    grid = grid or BevGrid()
    canvas[:] = _bev_background_cached(grid, tuple(background), tuple(grid_color))
    if ground_truth is not None:
        _bev_boxes(canvas, grid, ground_truth, GT_COLOR, thickness)
    if predictions is not None:
        _bev_boxes(canvas, grid, predictions, colors, thickness)
