"""Post-optimisation of the observation angle by hill climbing (paper, "Post Optimization").

The network predicts a 2D box and a 3D box independently. The 3D box's yaw is
refined so that the axis-aligned box of its projection (clipped to the image)
matches the predicted 2D box as well as possible (2D IoU). Following the paper
(and the reference code) only the angle moves: location and dimensions are
left untouched, because optimising depth as well overfits to the sparse 2D-3D
constraint.

Search (reference schedule): step ``s = initial_step``; while ``s > min_step``
evaluate ``ry + s`` and ``ry - s``: move to ``ry + s`` when
``IoU(ry + s) > IoU(ry)`` and ``IoU(ry + s) > IoU(ry - s)``, otherwise to
``ry - s`` when ``IoU(ry - s) > IoU(ry)``, otherwise halve ``s``. The step is
kept after a move. The result is wrapped to ``(-pi, pi]``.

All functions are numpy (float64) host code; :func:`optimize_rotation_y_batch`
advances every detection of an image together, one vectorised projection per
iteration (:func:`consistency_objective`: the corner offsets, 2D boxes and their
areas are set up once per image, and an iteration whose boxes lie in front of the
near plane projects only the 8 corners; the IoUs are bit-identical to
:func:`consistency_iou`'s).
"""

from __future__ import annotations

import numpy as np

from gac_jax import geometry


def projected_box(
    location: np.ndarray,
    dims: np.ndarray,
    ry: np.ndarray | float,
    P2: np.ndarray,
    image_size: tuple[int, int],
) -> np.ndarray:
    """Axis-aligned 2D box of a projected 3D box, clipped to ``[0, W] x [0, H]``.

    Edges crossing the camera's near plane are cut there first
    (:func:`gac_jax.geometry.box2d_from_corners`). The clip bounds are the
    image size, as the network's own boxes are clipped (the reference
    hard-codes its 1280x288 input).

    Args:
      location: (3,) or (N, 3) bottom-face centres, camera frame (metres).
      dims: (3,) or (N, 3) ``(h, w, l)``.
      ry: scalar or (N,) yaw about the camera y axis.
      P2: (3, 4) projection of the image the boxes live in.
      image_size: ``(H, W)`` of that image.

    Returns:
      (4,) xyxy for a single box (1-D ``location``), else (N, 4). NaN when the
      box lies entirely behind the near plane.
    """
    single = np.ndim(location) == 1
    loc = np.asarray(location, np.float64).reshape(-1, 3)
    dim = np.asarray(dims, np.float64).reshape(-1, 3)
    ry = np.broadcast_to(np.asarray(ry, np.float64).reshape(-1), (loc.shape[0],))
    corners = geometry.box3d_corners(loc, dim, ry)
    boxes = geometry.box2d_from_corners(corners, P2)
    height, width = image_size
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, float(width))
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, float(height))
    return boxes[0] if single else boxes


def box_area(boxes: np.ndarray) -> np.ndarray:
    """Areas (N,) of xyxy boxes (N, 4); 0 for inverted boxes, NaN for NaN boxes."""
    b = np.asarray(boxes, np.float64).reshape(-1, 4)
    return np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)


def paired_iou(
    boxes_a: np.ndarray, boxes_b: np.ndarray, area_a: np.ndarray | None = None
) -> np.ndarray:
    """IoU of corresponding xyxy boxes: (N, 4), (N, 4) -> (N,); 0 for empty or NaN boxes.

    ``area_a``: :func:`box_area` of ``boxes_a`` when the caller has it already.
    """
    a = np.asarray(boxes_a, np.float64).reshape(-1, 4)
    b = np.asarray(boxes_b, np.float64).reshape(-1, 4)
    area_a = box_area(a) if area_a is None else area_a
    iw = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    ih = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    union = area_a + box_area(b) - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = inter / union
    return np.where((union > 0) & np.isfinite(iou), iou, 0.0)


def consistency_iou(
    box2d: np.ndarray,
    location: np.ndarray,
    dims: np.ndarray,
    ry: np.ndarray | float,
    P2: np.ndarray,
    image_size: tuple[int, int],
) -> np.ndarray:
    """2D-3D consistency: IoU between ``box2d`` (N, 4) and :func:`projected_box`; (N,)."""
    loc = np.asarray(location, np.float64).reshape(-1, 3)
    proj = projected_box(loc, np.reshape(dims, (-1, 3)), ry, P2, image_size)
    return paired_iou(box2d, proj)


NEAR = 0.1  # metres: the near plane of geometry.box2d_from_corners


def consistency_objective(
    boxes2d: np.ndarray,
    locations: np.ndarray,
    dims: np.ndarray,
    P2: np.ndarray,
    image_size: tuple[int, int],
):
    """``iou(rows, ry) -> (len(rows),)``: :func:`consistency_iou` of detections ``rows`` at ``ry``.

    The hill climbing's objective with everything that does not depend on the yaw
    computed once: the corners' offsets in the object frame, the bottom/top corner
    heights, and the 2D boxes and their areas. Each call performs the same float64
    operations per element as :func:`consistency_iou` (corners as
    :func:`gac_jax.geometry.box3d_corners` computes them, the same ``@ P2.T``
    projection, clip and IoU), so the values are bit-identical; when every corner
    lies in front of the near plane (no edge to cut) it projects only the 8 corners,
    otherwise it runs :func:`gac_jax.geometry.box2d_from_corners` on them.

    Args:
      boxes2d: (N, 4) xyxy network 2D boxes in the pixels of ``P2``'s image.
      locations: (N, 3) bottom-face centres, camera frame (metres).
      dims: (N, 3) ``(h, w, l)``.
      P2: (3, 4) projection; image_size: ``(H, W)``.
    """
    boxes2d = np.asarray(boxes2d, np.float64).reshape(-1, 4)
    loc = np.asarray(locations, np.float64).reshape(-1, 3)
    dim = np.asarray(dims, np.float64).reshape(-1, 3)
    P = np.asarray(P2, np.float64)
    height, width = float(image_size[0]), float(image_size[1])
    bounds = np.array([width, height, width, height])  # projected_box's clip, as one array
    area2d = box_area(boxes2d)
    h, w, l = dim[:, 0:1], dim[:, 1:2], dim[:, 2:3]
    # Object-frame corner offsets (N, 8) in box3d_corners' order; y does not rotate.
    x = np.concatenate([l, l, -l, -l, l, l, -l, -l], axis=1) / 2.0
    z = np.concatenate([w, -w, -w, w, w, -w, -w, w], axis=1) / 2.0
    y = np.concatenate([np.zeros_like(h)] * 4 + [-h] * 4, axis=1) + loc[:, 1:2]
    loc_x, loc_z = loc[:, 0:1], loc[:, 2:3]

    gathered: dict = {}  # the last rows' yaw-independent arrays (rows change rarely)

    def iou(rows: np.ndarray, ry: np.ndarray) -> np.ndarray:
        if gathered.get("rows") is None or not np.array_equal(gathered["rows"], rows):
            gathered.update(
                rows=rows.copy(),
                x=x[rows],
                z=z[rows],
                y=y[rows],
                loc_x=loc_x[rows],
                loc_z=loc_z[rows],
                box=boxes2d[rows],
                area=area2d[rows],
            )
        g = gathered
        c, s = np.cos(ry)[:, None], np.sin(ry)[:, None]
        xr, zr = g["x"], g["z"]
        corners = np.stack(
            [(c * xr + s * zr) + g["loc_x"], g["y"], (c * zr - s * xr) + g["loc_z"]], axis=-1
        )
        hom = corners @ P[:, :3].T + P[:, 3]  # (M, 8, 3)
        depth = hom[..., 2]
        if (depth > NEAR).all():
            uv = hom[..., :2] / depth[..., None]
            boxes = np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)
        else:
            boxes = geometry.box2d_from_corners(corners, P, near=NEAR)
        # paired_iou(box, clip(boxes, 0, bounds), area) with the same float operations
        # (clip as maximum/minimum: equal, NaN included) and fewer calls
        b = np.minimum(np.maximum(boxes, 0.0), bounds)
        a = g["box"]
        iw = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
        ih = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
        inter = np.maximum(iw, 0.0) * np.maximum(ih, 0.0)
        area_b = np.maximum(b[:, 2] - b[:, 0], 0.0) * np.maximum(b[:, 3] - b[:, 1], 0.0)
        union = g["area"] + area_b - inter
        with np.errstate(invalid="ignore", divide="ignore"):
            out = inter / union
        return np.where((union > 0) & np.isfinite(out), out, 0.0)

    return iou


def optimize_rotation_y_batch(
    boxes2d: np.ndarray,
    locations: np.ndarray,
    dims: np.ndarray,
    ry: np.ndarray,
    P2: np.ndarray,
    image_size: tuple[int, int],
    *,
    initial_step: float = 0.4,
    min_step: float = 0.01,
    max_iterations: int = 1000,
) -> np.ndarray:
    """Hill-climbs the yaw of N detections of one image at once.

    Each detection follows the reference schedule independently (its own step
    and stop condition); the loop only shares the vectorised projection of the
    ``ry +- s`` candidates of the detections still searching
    (:func:`consistency_objective`). Every move strictly increases the IoU, so the
    search ends; ``max_iterations`` is only a guard against pathological float
    cycles (never reached in practice).

    Args:
      boxes2d: (N, 4) xyxy network 2D boxes in the pixels of ``P2``'s image.
      locations: (N, 3) bottom-face centres (unchanged).
      dims: (N, 3) ``(h, w, l)`` (unchanged).
      ry: (N,) initial yaw.
      P2: (3, 4) projection; image_size: ``(H, W)``.

    Returns:
      (N,) optimised yaw wrapped to ``(-pi, pi]``.
    """
    boxes2d = np.asarray(boxes2d, np.float64).reshape(-1, 4)
    loc = np.asarray(locations, np.float64).reshape(-1, 3)
    dim = np.asarray(dims, np.float64).reshape(-1, 3)
    ry = np.asarray(ry, np.float64).reshape(-1).copy()
    n = ry.shape[0]
    if not (boxes2d.shape[0] == loc.shape[0] == dim.shape[0] == n):
        raise ValueError(
            f"hill climbing needs matching counts, got boxes {boxes2d.shape}, "
            f"locations {loc.shape}, dims {dim.shape}, ry {ry.shape}"
        )
    if n == 0:
        return ry
    objective = consistency_objective(boxes2d, loc, dim, P2, image_size)
    step = np.full(n, float(initial_step))
    best = objective(np.arange(n), ry)
    for _ in range(max_iterations):
        act = np.flatnonzero(step > min_step)
        if act.size == 0:
            break
        m = act.size
        cur_ry, cur_step = ry[act], step[act]
        cand = np.concatenate([cur_ry + cur_step, cur_ry - cur_step])
        iou = objective(np.concatenate([act, act]), cand)
        plus, minus, cur = iou[:m], iou[m:], best[act]
        go_plus = (plus > cur) & (plus > minus)
        go_minus = ~go_plus & (minus > cur)
        ry[act] = np.where(go_plus, cand[:m], np.where(go_minus, cand[m:], cur_ry))
        best[act] = np.where(go_plus, plus, np.where(go_minus, minus, cur))
        step[act] = np.where(go_plus | go_minus, cur_step, cur_step / 2.0)
    return geometry.wrap_angle(ry)


def optimize_rotation_y(
    box2d: np.ndarray,
    location: np.ndarray,
    dims: np.ndarray,
    ry: float,
    P2: np.ndarray,
    image_size: tuple[int, int],
    *,
    initial_step: float = 0.4,
    min_step: float = 0.01,
) -> float:
    """Hill-climbs one detection's yaw (see :func:`optimize_rotation_y_batch`).

    Args:
      box2d: (4,) xyxy network box (input-image pixels).
      location: (3,) bottom-face centre; dims: (3,) ``(h, w, l)``; ry: yaw.
      P2: (3, 4) projection of the input image; image_size: ``(H, W)``.

    Returns:
      The optimised yaw in ``(-pi, pi]``.
    """
    out = optimize_rotation_y_batch(
        np.reshape(box2d, (1, 4)),
        np.reshape(location, (1, 3)),
        np.reshape(dims, (1, 3)),
        np.reshape(ry, (1,)),
        P2,
        image_size,
        initial_step=initial_step,
        min_step=min_step,
    )
    return float(out[0])
