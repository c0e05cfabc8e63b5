"""Ground-plane anchor filtering: keep only anchors whose 3D proposal lies near the ground.

Each anchor centred at ``(u, v)`` with its bin's per-class prior mean depth
``z`` is back-projected into the camera frame (x right, y down, z forward). An
anchor is kept if, for *some* class, that 3D point ``X`` is a plausible object
centre for the frame's ground ``plane`` ``(a, b, c, d)`` (unit normal ``n``
pointing up, ``d`` the camera height; default the level plane
``(0, -1, 0, camera_height)``). It depends on the image's ``P2`` (after crop /
resize / flip) and plane, so it is computed per image; masked-out anchors are
neither positives nor negatives in training and are dropped before scoring at
test time.

Two modes:

``"reference"`` (visualDet3D ``filter_anchor``): ``x = (u - cx) z / f``,
  ``y = (v - cy) z / fy`` (translations of ``P2`` ignored); keep iff the
  reference's y band (default (-0.5, 1.8) m) holds for the depth of ``X`` below
  a camera ``camera_height`` above the road, ``camera_height - (n . X + d)``,
  and ``|x| < x_limit`` (40 m). For the level plane of ``camera_height`` that
  depth is ``y``: the reference exactly; for any other plane the band moves with
  the road (height above it in ``(camera_height - 1.8, camera_height + 0.5)``).
  The reference divides x by ``fy`` (``x_focal="fy"``); the paper's equation
  uses ``fx`` (``x_focal="fx"``); on KITTI fx = fy.

``"paper"`` (the paper's ground-plane form): exact back-projection through
  ``P2`` (including its translation column, x divided by fx) and the object
  centre's height above the road ``n . X + d`` (``camera_height - y`` for a
  level plane) must lie in ``height_range``. The default band (-0.15, 2.15) m
  is the reference's y band re-expressed relative to the road (1.65 - 1.8,
  1.65 + 0.5), so both modes agree on a level KITTI camera (up to the mm-size
  translation terms) while the paper form adapts to another camera height.
  ``x_limit`` applies as well (``None`` disables it in either mode).

Both follow a tilted plane: for a camera pitched down by 20 degrees the band
moves with the road, where a fixed y band keeps almost no anchor.

Invalid prior bins (:attr:`DetectionConstants.prior_valid` False) keep no anchor
with ``invalid_bins="drop"`` (default). ``invalid_bins="reference"`` reproduces
the reference, which back-projects them with the sentinel mean depth -100 so a
few anchors just above the horizon pass (they can only ever be negatives).

``P2`` is assumed to have KITTI structure: zero skew, third row ``[0, 0, 1, tz]``
(true for every crop / resize / flip of a KITTI projection).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from gac_jax.detection.anchor_priors import INVALID_MEAN, DetectionConstants
from gac_jax.geometry import DEFAULT_CAMERA_HEIGHT, level_plane

FILTER_MODES = ("reference", "paper")


def _check(mode: str, x_focal: str, invalid_bins: str) -> None:
    if mode not in FILTER_MODES:
        raise ValueError(f"ground filter mode must be one of {FILTER_MODES}, got {mode!r}")
    if x_focal not in ("fx", "fy"):
        raise ValueError(f"x_focal must be 'fx' or 'fy', got {x_focal!r}")
    if invalid_bins not in ("drop", "reference"):
        raise ValueError(f"invalid_bins must be 'drop' or 'reference', got {invalid_bins!r}")


def _keep(
    xp,
    centers,
    mean_z,
    valid,
    P2,
    plane,
    mode,
    y_range,
    x_limit,
    x_focal,
    camera_height,
    height_range,
    invalid_bins,
):
    """Shared math; ``P2`` (B, 3, 4), plane (B, 4), centres (N, 2), mean_z / valid (K, N) ->
    (B, N)."""
    u = centers[None, None, :, 0]  # (1, 1, N)
    v = centers[None, None, :, 1]
    z = xp.where(valid, mean_z, INVALID_MEAN)[None]  # (1, K, N)

    def entry(i, j):
        return P2[:, i, j][:, None, None]  # (B, 1, 1)

    fx, cx, tx = entry(0, 0), entry(0, 2), entry(0, 3)
    fy, cy, ty, tz = entry(1, 1), entry(1, 2), entry(1, 3), entry(2, 3)
    a, b, c, d = (plane[:, i][:, None, None] for i in range(4))
    if mode == "reference":
        x = (u - cx) * z / (fy if x_focal == "fy" else fx)
        y = (v - cy) * z / fy
        # depth below a camera camera_height above the road; y itself for the level plane
        below = -(a * x + b * y + c * z) + (camera_height - d)
        keep = (below > y_range[0]) & (below < y_range[1])
    else:
        w = z + tz  # homogeneous depth of a point at camera-frame depth z
        x = (u * w - cx * z - tx) / fx
        y = (v * w - cy * z - ty) / fy
        height = a * x + b * y + c * z + d
        keep = (height > height_range[0]) & (height < height_range[1])
    if x_limit is not None:
        keep = keep & (xp.abs(x) < x_limit)
    if invalid_bins == "drop":
        keep = keep & valid[None]
    return keep.any(axis=1)


def _planes(xp, plane, P2, camera_height, dtype):
    """(B, 4) planes: ``plane`` ((B, 4) or (4,)) or the level plane of ``camera_height``."""
    if plane is None:
        plane = level_plane(camera_height)
    plane = xp.asarray(plane, dtype)
    return xp.broadcast_to(plane[None] if plane.ndim == 1 else plane, (P2.shape[0], 4))


def ground_filter_mask(
    anchor_centers,
    prior_mean_z,
    prior_valid,
    P2,
    plane=None,
    *,
    mode: str = "reference",
    y_range: tuple[float, float] = (-0.5, 1.8),
    x_limit: float | None = 40.0,
    x_focal: str = "fy",
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    height_range: tuple[float, float] = (-0.15, 2.15),
    invalid_bins: str = "drop",
):
    """Per-image anchor keep-mask (jnp, jit-able; settings are static Python values).

    Args:
      anchor_centers: (N, 2) anchor centres ``(u, v)`` in network-input pixels.
      prior_mean_z: (K, N) per-class prior mean depth of each anchor's bin (metres).
      prior_valid: (K, N) bool, bins with usable priors.
      P2: (B, 3, 4) projection of each network-input image (or (3, 4) for one).
      plane: (B, 4) (or (4,)) ground plane of each image, unit upward normal; None: the
        level plane ``(0, -1, 0, camera_height)``.
      mode, y_range, x_limit, x_focal, camera_height, height_range, invalid_bins:
        see the module docstring.

    Returns:
      (B, N) bool (or (N,) for a single (3, 4) ``P2``): True = anchor kept.
    """
    _check(mode, x_focal, invalid_bins)
    P2 = jnp.asarray(P2, jnp.float32)
    single = P2.ndim == 2
    P2 = P2[None] if single else P2
    keep = _keep(
        jnp,
        jnp.asarray(anchor_centers, jnp.float32),
        jnp.asarray(prior_mean_z, jnp.float32),
        jnp.asarray(prior_valid, bool),
        P2,
        _planes(jnp, plane, P2, camera_height, jnp.float32),
        mode,
        y_range,
        x_limit,
        x_focal,
        camera_height,
        height_range,
        invalid_bins,
    )
    return keep[0] if single else keep


def ground_mask_from_constants(constants: DetectionConstants, P2, plane=None, **options):
    """:func:`ground_filter_mask` for the anchors and prior depths of ``constants``.

    ``P2`` (B, 3, 4), ``plane`` (B, 4) or None -> (B, N) bool; ``options`` are the keyword
    settings of :func:`ground_filter_mask`.
    """
    return ground_filter_mask(
        constants.anchor_centers,
        constants.prior_mean[..., 0],
        constants.prior_valid,
        P2,
        plane,
        **options,
    )


def ground_filter_mask_np(
    anchor_centers: np.ndarray,
    prior_mean_z: np.ndarray,
    prior_valid: np.ndarray,
    P2: np.ndarray,
    plane: np.ndarray | None = None,
    *,
    mode: str = "reference",
    y_range: tuple[float, float] = (-0.5, 1.8),
    x_limit: float | None = 40.0,
    x_focal: str = "fy",
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    height_range: tuple[float, float] = (-0.15, 2.15),
    invalid_bins: str = "drop",
) -> np.ndarray:
    """Float64 numpy twin of :func:`ground_filter_mask` (analysis, tests, host-side decoding)."""
    _check(mode, x_focal, invalid_bins)
    P2 = np.asarray(P2, dtype=np.float64)
    single = P2.ndim == 2
    P2 = P2[None] if single else P2
    keep = _keep(
        np,
        np.asarray(anchor_centers, dtype=np.float64),
        np.asarray(prior_mean_z, dtype=np.float64),
        np.asarray(prior_valid, dtype=bool),
        P2,
        _planes(np, plane, P2, camera_height, np.float64),
        mode,
        y_range,
        x_limit,
        x_focal,
        camera_height,
        height_range,
        invalid_bins,
    )
    return keep[0] if single else keep
