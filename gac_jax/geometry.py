"""Camera geometry for KITTI-style rectified cameras (pure numpy, float64).

Frames and conventions used throughout gac_jax:

* camera frame: x right, y down, z forward (metres), the rectified reference
  camera of KITTI (cam 0). ``P`` (3x4) maps homogeneous camera points to
  homogeneous image points of one camera (``P2`` left colour, ``P3`` right).
* image frame: u right, v down (pixels); pixel ``i`` covers ``[i-0.5, i+0.5]``
  so its centre is at integer coordinate ``i``.
* 3D boxes: KITTI ``location`` is the centre of the *bottom* face, dimensions
  are ``(h, w, l)``, ``rotation_y`` is the yaw about the camera y axis; at
  ``ry = 0`` the object's length points along +x.
* 2D boxes are ``xyxy``.
* ground plane: ``(a, b, c, d)`` of ``a x + b y + c z + d = 0`` in the camera frame with a
  unit normal pointing up (``b < 0``), ``d`` = camera height (:func:`normalize_plane`).
"""

from __future__ import annotations

import numpy as np

# Edges of the 8-corner box of :func:`box3d_corners` (bottom face, top face, pillars).
BOX_EDGES = np.array(
    [[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4], [0, 4], [1, 5], [2, 6], [3, 7]]
)
# Corners of the front face (the face the object heads towards, +x at ry=0).
FRONT_FACE = np.array([0, 1, 5, 4])
# KITTI's camera height above the road (m): the ground plane of a frame that has none.
DEFAULT_CAMERA_HEIGHT = 1.65


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wraps angles (radians) into ``(-pi, pi]``."""
    a = np.asarray(angle, dtype=np.float64)
    wrapped = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    return np.where(wrapped == -np.pi, np.pi, wrapped)


def camera_center(P: np.ndarray) -> np.ndarray:
    """Optical centre ``C`` (3,) of a 3x4 projection ``P`` (``P @ [C, 1] = 0``)."""
    P = np.asarray(P, dtype=np.float64)
    return -np.linalg.solve(P[:, :3], P[:, 3])


def project(points: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Projects camera-frame points.

    Args:
      points: (..., 3) points in the reference camera frame.
      P: (3, 4) projection matrix.

    Returns:
      uv: (..., 2) image coordinates; depth: (...) homogeneous depth
      ``w = P[2] @ [X, 1]`` (equals ``z + P[2, 3]`` for KITTI matrices).
    """
    pts = np.asarray(points, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    hom = pts @ P[:, :3].T + P[:, 3]
    w = hom[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = hom[..., :2] / w[..., None]
    return uv, w


def unproject(uv: np.ndarray, depth: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Inverse of :func:`project`: the 3D point (..., 3) seen at ``uv`` with homogeneous depth."""
    uv = np.asarray(uv, dtype=np.float64)
    w = np.asarray(depth, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    rhs = np.concatenate([uv * w[..., None], w[..., None]], axis=-1) - P[:, 3]
    return rhs @ np.linalg.inv(P[:, :3]).T


def rotation_y_matrix(ry: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation about the camera y axis (x right, y down, z forward)."""
    ry = np.asarray(ry, dtype=np.float64)
    c, s = np.cos(ry), np.sin(ry)
    zeros, ones = np.zeros_like(ry), np.ones_like(ry)
    return np.stack(
        [
            np.stack([c, zeros, s], -1),
            np.stack([zeros, ones, zeros], -1),
            np.stack([-s, zeros, c], -1),
        ],
        axis=-2,
    )


def box3d_corners(
    location: np.ndarray, dimensions: np.ndarray, rotation_y: np.ndarray
) -> np.ndarray:
    """Corners of KITTI 3D boxes in the camera frame.

    Args:
      location: (N, 3) bottom-face centres ``(x, y, z)``.
      dimensions: (N, 3) ``(h, w, l)``.
      rotation_y: (N,) yaw.

    Returns:
      (N, 8, 3): corners 0-3 are the bottom face, 4-7 the top face (same
      order), corners 0, 1, 4, 5 form the front face (+x of the object).
    """
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    dims = np.asarray(dimensions, dtype=np.float64).reshape(-1, 3)
    h, w, l = dims[:, 0:1], dims[:, 1:2], dims[:, 2:3]
    x = np.concatenate([l, l, -l, -l, l, l, -l, -l], axis=1) / 2.0
    y = np.concatenate([np.zeros_like(h)] * 4 + [-h] * 4, axis=1)
    z = np.concatenate([w, -w, -w, w, w, -w, -w, w], axis=1) / 2.0
    local = np.stack([x, y, z], axis=-1)  # (N, 8, 3)
    rot = rotation_y_matrix(np.asarray(rotation_y, dtype=np.float64).reshape(-1))
    return np.einsum("nij,nkj->nki", rot, local) + loc[:, None, :]


def alpha_from_rotation_y(
    rotation_y: np.ndarray, location: np.ndarray, P: np.ndarray | None = None
) -> np.ndarray:
    """Observation angle ``alpha = ry - atan2(x - Cx, z - Cz)``, wrapped to (-pi, pi].

    ``C`` is the optical centre of ``P`` (the reference origin when ``P`` is
    None, which is how the KITTI labels define alpha up to ~1 mrad).
    """
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    c = np.zeros(3) if P is None else camera_center(P)
    ray = np.arctan2(loc[:, 0] - c[0], loc[:, 2] - c[2])
    return wrap_angle(np.asarray(rotation_y, dtype=np.float64).reshape(-1) - ray)


def rotation_y_from_alpha(
    alpha: np.ndarray, location: np.ndarray, P: np.ndarray | None = None
) -> np.ndarray:
    """Inverse of :func:`alpha_from_rotation_y`."""
    loc = np.asarray(location, dtype=np.float64).reshape(-1, 3)
    c = np.zeros(3) if P is None else camera_center(P)
    ray = np.arctan2(loc[:, 0] - c[0], loc[:, 2] - c[2])
    return wrap_angle(np.asarray(alpha, dtype=np.float64).reshape(-1) + ray)


def box2d_from_corners(
    corners: np.ndarray,
    P: np.ndarray,
    image_size: tuple[int, int] | None = None,
    near: float = 0.1,
) -> np.ndarray:
    """2D box ``xyxy`` (N, 4) enclosing the projection of 3D boxes.

    The box's edges are clipped against the plane ``depth = near`` first, so a
    box that extends behind the camera still gets a correct (large) extent.
    With ``image_size = (H, W)`` the result is clipped to ``[0, W-1] x [0, H-1]``
    (pixel-centre extent, as KITTI labels are). Boxes entirely behind the
    near plane give NaN.

    Args:
      corners: (N, 8, 3) from :func:`box3d_corners`.
      P: (3, 4) projection.
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 8, 3)
    P = np.asarray(P, dtype=np.float64)
    _, w = project(corners, P)  # (N, 8)
    a, b = corners[:, BOX_EDGES[:, 0]], corners[:, BOX_EDGES[:, 1]]  # (N, 12, 3)
    wa, wb = w[:, BOX_EDGES[:, 0]], w[:, BOX_EDGES[:, 1]]
    crosses = (wa - near) * (wb - near) < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crosses, (near - wa) / (wb - wa), 0.0)
    cut = a + t[..., None] * (b - a)
    points = np.concatenate([corners, cut], axis=1)  # (N, 20, 3)
    valid = np.concatenate([w > near - 1e-9, crosses], axis=1)
    uv, _ = project(points, P)
    big = np.inf
    x1 = np.where(valid, uv[..., 0], big).min(axis=1)
    y1 = np.where(valid, uv[..., 1], big).min(axis=1)
    x2 = np.where(valid, uv[..., 0], -big).max(axis=1)
    y2 = np.where(valid, uv[..., 1], -big).max(axis=1)
    boxes = np.stack([x1, y1, x2, y2], axis=1)
    boxes[~valid.any(axis=1)] = np.nan
    if image_size is not None:
        height, width = image_size
        boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, width - 1.0)
        boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, height - 1.0)
    return boxes


def level_plane(camera_height: float = DEFAULT_CAMERA_HEIGHT) -> np.ndarray:
    """(4,) plane ``(0, -1, 0, camera_height)``: a level camera ``camera_height`` above the road."""
    return np.array([0.0, -1.0, 0.0, float(camera_height)])


def normalize_plane(plane: np.ndarray) -> np.ndarray:
    """``(a, b, c, d)`` of ``a x + b y + c z + d = 0`` scaled to a unit normal pointing up.

    Up is ``-y`` (y points down), so the result has ``b < 0`` and ``d`` is the camera's height
    above the plane (the height of a point ``X`` above it is ``n . X + d``). Raises ValueError
    for a normal that is zero, not finite or horizontal (``b = 0``: not a ground plane).
    """
    plane = np.asarray(plane, dtype=np.float64)
    norm = np.linalg.norm(plane[..., :3], axis=-1, keepdims=True)
    if not np.all(np.isfinite(plane)) or np.any(norm == 0) or np.any(plane[..., 1] == 0):
        raise ValueError(f"not a ground plane (finite, non-zero normal with b != 0): {plane}")
    return plane / norm * -np.sign(plane[..., 1:2])


def height_above_plane(points: np.ndarray, plane: np.ndarray) -> np.ndarray:
    """Signed height (...) of camera-frame points (..., 3) above a normalised ``plane`` (4,)."""
    plane = np.asarray(plane, dtype=np.float64)
    return np.asarray(points, dtype=np.float64) @ plane[:3] + plane[3]


def ground_depth(
    v: np.ndarray,
    P: np.ndarray,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    *,
    u: np.ndarray | float = 0.0,
    plane: np.ndarray | None = None,
) -> np.ndarray:
    """Depth ``z`` (camera frame) of the road seen at image pixel ``(u, v)``.

    The road is ``plane`` (a normalised ``(a, b, c, d)``, :func:`normalize_plane`) or, when
    None, the level road ``y = camera_height`` (then ``u`` does not matter). Exact for any
    ``P``: the ray from the optical centre ``C`` through the pixel meets the plane at
    ``C + t r``; for a level road and a KITTI ``P`` this solves
    ``v (z + P[2,3]) = fy * EL + cy * z + P[1,3]``. Pixels whose ray does not descend to the
    road (at or above the horizon) return ``inf``.
    """
    P = np.asarray(P, dtype=np.float64)
    plane = level_plane(camera_height) if plane is None else np.asarray(plane, np.float64)
    v = np.asarray(v, dtype=np.float64)
    u = np.broadcast_to(np.asarray(u, dtype=np.float64), v.shape)
    M_inv = np.linalg.inv(P[:, :3])
    C = -M_inv @ P[:, 3]
    r = np.stack([u, v, np.ones_like(v)], axis=-1) @ M_inv.T  # (..., 3) ray directions
    n_r = r @ plane[:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(plane[:3] @ C + plane[3]) / n_r
    z = C[2] + t * r[..., 2]
    return np.where((n_r < 0) & (t > 0) & (z > 0), z, np.inf)


def ground_depth_map(
    image_size: tuple[int, int],
    P: np.ndarray,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    plane: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) road depth (:func:`ground_depth`) at every pixel (inf above the horizon)."""
    height, width = image_size
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return ground_depth(v, P, camera_height, u=u, plane=plane)
