"""Exact box overlaps of the KITTI object benchmark: 2D, bird's-eye-view (rotated) and 3D.

Pure numpy, float64, vectorised over box pairs (no numba, no GPU). The rotated
overlap is the exact area of the intersection of two convex quadrilaterals,
obtained by Sutherland-Hodgman clipping, so it agrees with the official devkit
(``evaluate_object.cpp``, boost::geometry in double precision) to rounding.

Box encodings (camera frame: x right, y down, z forward):

* 2D boxes: ``(N, 4)`` ``xyxy`` image pixels.
* BEV boxes: ``(N, 5)`` ``(x, z, l, w, ry)``: centre on the ground plane, length
  along the heading, width across it, yaw about camera y. The heading of a box
  is ``(cos ry, -sin ry)`` in ``(x, z)``, exactly as the devkit's ``toPolygon``.
* 3D boxes: ``(N, 7)`` ``(x, y, z, h, w, l, ry)``: KITTI location (bottom-face
  centre) then dimensions ``(h, w, l)`` then yaw. A box spans ``[y - h, y]``
  along camera y (y points down, so the top is at ``y - h``).

The overlap ``criterion`` is the devkit's:

* ``-1``: intersection over union;
* ``0``: intersection over the area (volume) of the *first* box (the devkit
  uses it with the detection first and a DontCare region second);
* ``1``: intersection over the area (volume) of the second box.

A zero denominator gives overlap 0 (the devkit would divide 0 by 0).
"""

from __future__ import annotations

import numpy as np

_CRITERIA = (-1, 0, 1)


def _check_criterion(criterion: int) -> None:
    if criterion not in _CRITERIA:
        raise ValueError(f"overlap criterion must be -1 (union), 0 or 1, got {criterion!r}")


def _ratio(inter: np.ndarray, denom: np.ndarray) -> np.ndarray:
    out = np.zeros(np.broadcast(inter, denom).shape, dtype=np.float64)
    np.divide(inter, denom, out=out, where=denom > 0)
    return out


def _as_boxes(boxes, width: int, name: str) -> np.ndarray:
    arr = np.asarray(boxes, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != width:
        raise ValueError(f"{name} must have shape (N, {width}), got {arr.shape}")
    return arr


# --------------------------------------------------------------------------------------------
# 2D image boxes
# --------------------------------------------------------------------------------------------


def box2d_overlap_pairs(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """Overlap of paired 2D boxes ``a[i]`` and ``b[i]``; ``a``, ``b``: (P, 4) xyxy. Returns (P,).

    As the devkit's ``imageBoxOverlap``: an intersection with non-positive
    width or height is 0 (so degenerate or inverted boxes never overlap).
    """
    _check_criterion(criterion)
    a = _as_boxes(a, 4, "a")
    b = _as_boxes(b, 4, "b")
    iw = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    ih = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    hit = (iw > 0) & (ih > 0)
    inter = np.where(hit, iw * ih, 0.0)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    if criterion == -1:
        denom = area_a + area_b - inter
    elif criterion == 0:
        denom = area_a
    else:
        denom = area_b
    return np.where(hit, _ratio(inter, denom), 0.0)


def box2d_overlap(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """All-pairs 2D overlap: ``a`` (N, 4), ``b`` (K, 4) xyxy -> (N, K)."""
    a = _as_boxes(a, 4, "a")
    b = _as_boxes(b, 4, "b")
    ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
    return box2d_overlap_pairs(a[ia.ravel()], b[ib.ravel()], criterion).reshape(len(a), len(b))


# --------------------------------------------------------------------------------------------
# Rotated rectangles in the ground plane
# --------------------------------------------------------------------------------------------


def bev_boxes(location: np.ndarray, dimensions: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """(N, 5) BEV boxes from KITTI ``location`` (N, 3), ``dimensions`` (N, 3) hwl and ``ry``."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=np.float64).reshape(-1)
    return np.stack([loc[:, 0], loc[:, 2], dims[:, 2], dims[:, 1], ry], axis=1)


def boxes3d(location: np.ndarray, dimensions: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """KITTI ``location`` (N, 3), ``dimensions`` (N, 3), ``rotation_y`` (N,) -> (N, 7) 3D boxes."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=np.float64).reshape(-1, 1)
    return np.concatenate([loc, dims, ry], axis=1)


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """Corners (N, 4, 2) in ``(x, z)`` of BEV boxes (N, 5), counter-clockwise in the (x, z) plane.

    Corner ``k`` is ``centre + R(ry) @ (±l/2, ±w/2)`` with ``R = [[c, s], [-s, c]]``
    (the devkit's ``toPolygon``); the sizes enter by absolute value, so the
    DontCare placeholder size -1 gives a 1 m square as in the devkit.
    """
    boxes = _as_boxes(boxes, 5, "boxes")
    x, z, l, w, ry = boxes.T
    hl, hw = np.abs(l)[:, None] / 2.0, np.abs(w)[:, None] / 2.0
    # Counter-clockwise in (x, z) with x to the right and z up.
    px = np.array([1.0, -1.0, -1.0, 1.0])[None, :] * hl
    pz = np.array([1.0, 1.0, -1.0, -1.0])[None, :] * hw
    c, s = np.cos(ry)[:, None], np.sin(ry)[:, None]
    cx = c * px + s * pz + x[:, None]
    cz = -s * px + c * pz + z[:, None]
    return np.stack([cx, cz], axis=-1)


def _clip(poly: np.ndarray, count: np.ndarray, a: np.ndarray, b: np.ndarray):
    """One Sutherland-Hodgman step: keeps the part of each polygon left of the directed edge a->b.

    Args:
      poly: (P, M, 2) vertices, the first ``count`` of each row valid.
      count: (P,) number of vertices.
      a, b: (P, 2) edge end points (the clip polygon is counter-clockwise).

    Returns:
      (P, M', 2) clipped polygons and their (P,) vertex counts.
    """
    num, width = poly.shape[:2]
    idx = np.arange(width)
    valid = idx[None, :] < count[:, None]
    nxt = np.where(idx[None, :] + 1 < count[:, None], idx[None, :] + 1, 0)
    p_next = np.take_along_axis(poly, nxt[..., None], axis=1)
    ex, ey = (b - a)[:, 0:1], (b - a)[:, 1:2]
    side = ex * (poly[..., 1] - a[:, 1:2]) - ey * (poly[..., 0] - a[:, 0:1])
    side_next = np.take_along_axis(side, nxt, axis=1)
    inside = side >= 0.0
    crossing = valid & (inside != (side_next >= 0.0))
    denom = np.where(crossing, side - side_next, 1.0)
    t = np.where(crossing, side / denom, 0.0)[..., None]
    inter = poly + t * (p_next - poly)
    cand = np.stack([poly, inter], axis=2).reshape(num, 2 * width, 2)
    emit = np.stack([inside & valid, crossing], axis=2).reshape(num, 2 * width)
    new_count = emit.sum(axis=1)
    out_width = max(int(new_count.max(initial=0)), 1)
    out = np.zeros((num, out_width, 2), dtype=np.float64)
    rows, cols = np.nonzero(emit)
    slot = (np.cumsum(emit, axis=1) - 1)[rows, cols]
    out[rows, slot] = cand[rows, cols]
    return out, new_count


def _polygon_area(poly: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Shoelace area (P,) of polygons (P, M, 2) with ``count`` valid vertices (>= 0 for CCW)."""
    width = poly.shape[1]
    if width == 0:
        return np.zeros(poly.shape[0])
    idx = np.arange(width)
    # Unused slots repeat vertex 0, which adds zero-area terms to the shoelace sum.
    filled = np.where((idx[None, :] < count[:, None])[..., None], poly, poly[:, :1, :])
    rolled = np.roll(filled, -1, axis=1)
    cross = filled[..., 0] * rolled[..., 1] - filled[..., 1] * rolled[..., 0]
    area = 0.5 * cross.sum(axis=1)
    return np.where(count >= 3, np.maximum(area, 0.0), 0.0)


def convex_quad_intersection_area(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Exact intersection area (P,) of paired convex quadrilaterals (P, 4, 2), counter-clockwise."""
    qa = np.asarray(qa, dtype=np.float64)
    qb = np.asarray(qb, dtype=np.float64)
    # Work relative to qb's first corner: smaller coordinates, less cancellation.
    origin = qb[:, :1, :]
    poly, clip = qa - origin, qb - origin
    count = np.full(len(qa), 4, dtype=np.int64)
    for k in range(4):
        poly, count = _clip(poly, count, clip[:, k], clip[:, (k + 1) % 4])
    return _polygon_area(poly, count)


def _bev_maybe_overlapping(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Conservative test (P,) on paired BEV boxes: False only where the circumcircles are apart."""
    ra = 0.5 * np.hypot(a[:, 2], a[:, 3])
    rb = 0.5 * np.hypot(b[:, 2], b[:, 3])
    d2 = (a[:, 0] - b[:, 0]) ** 2 + (a[:, 1] - b[:, 1]) ** 2
    reach = (ra + rb) * (1.0 + 1e-9) + 1e-9
    return d2 <= reach * reach


def bev_intersection_area_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection area (P,) of paired BEV boxes ``a``, ``b`` (P, 5)."""
    a = _as_boxes(a, 5, "a")
    b = _as_boxes(b, 5, "b")
    inter = np.zeros(len(a), dtype=np.float64)
    near = np.flatnonzero(_bev_maybe_overlapping(a, b))
    if near.size:
        inter[near] = convex_quad_intersection_area(bev_corners(a[near]), bev_corners(b[near]))
    return inter


def bev_overlap_pairs(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """Overlap (P,) of paired BEV boxes (P, 5): the devkit's ``groundBoxOverlap``."""
    _check_criterion(criterion)
    a = _as_boxes(a, 5, "a")
    b = _as_boxes(b, 5, "b")
    inter = bev_intersection_area_pairs(a, b)
    area_a = np.abs(a[:, 2] * a[:, 3])
    area_b = np.abs(b[:, 2] * b[:, 3])
    denom = {-1: area_a + area_b - inter, 0: area_a, 1: area_b}[criterion]
    return _ratio(inter, denom)


def bev_overlap(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """All-pairs BEV overlap: ``a`` (N, 5), ``b`` (K, 5) -> (N, K)."""
    a = _as_boxes(a, 5, "a")
    b = _as_boxes(b, 5, "b")
    ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
    return bev_overlap_pairs(a[ia.ravel()], b[ib.ravel()], criterion).reshape(len(a), len(b))


def box3d_overlap_from_bev(
    a: np.ndarray, b: np.ndarray, bev_inter: np.ndarray, criterion: int = -1
) -> np.ndarray:
    """3D overlap (P,) of paired 3D boxes (P, 7) given their BEV intersection areas (P,).

    The devkit's ``box3DOverlap``: intersection volume = BEV intersection area x
    overlap of the y extents ``[y - h, y]``; volumes are ``h * w * l``.
    """
    _check_criterion(criterion)
    a = _as_boxes(a, 7, "a")
    b = _as_boxes(b, 7, "b")
    y_max = np.minimum(a[:, 1], b[:, 1])
    y_min = np.maximum(a[:, 1] - a[:, 3], b[:, 1] - b[:, 3])
    inter = np.asarray(bev_inter, dtype=np.float64) * np.maximum(0.0, y_max - y_min)
    vol_a = a[:, 3] * a[:, 4] * a[:, 5]
    vol_b = b[:, 3] * b[:, 4] * b[:, 5]
    denom = {-1: vol_a + vol_b - inter, 0: vol_a, 1: vol_b}[criterion]
    return _ratio(inter, denom)


def box3d_overlap_pairs(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """3D overlap (P,) of paired 3D boxes (P, 7)."""
    a = _as_boxes(a, 7, "a")
    b = _as_boxes(b, 7, "b")
    inter = bev_intersection_area_pairs(a[:, [0, 2, 5, 4, 6]], b[:, [0, 2, 5, 4, 6]])
    return box3d_overlap_from_bev(a, b, inter, criterion)


def box3d_overlap(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """All-pairs 3D overlap: ``a`` (N, 7), ``b`` (K, 7) -> (N, K)."""
    a = _as_boxes(a, 7, "a")
    b = _as_boxes(b, 7, "b")
    ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
    return box3d_overlap_pairs(a[ia.ravel()], b[ib.ravel()], criterion).reshape(len(a), len(b))
