"""Sparse LiDAR-like depth: which pixels of a dense depth map a 64-beam scanner would hit.

The scanner model is a Velodyne HDL-64E as mounted on the KITTI car: 64
beams at fixed elevations (32 from +2.0 to -8.33 deg, 32 from -8.83 to -24.33
deg), one return every 0.09 deg of azimuth (its finest mode), range up to 80 m. A
pixel receives a return when a beam's elevation, seen from the scanner (which
sits at the ``Tr_velo_to_cam`` mounting, not at the camera), falls between it
and its upper neighbour, and an azimuth sample between its column and the left
one. The returned depth is
the dense depth of that pixel, so the sparse map is an exact subset of the
dense one. At 375x1242 about 12 % of the pixels below the horizon are valid.
"""

from __future__ import annotations

import numpy as np

from gac_jax.geometry import camera_center

BEAM_ELEVATIONS = np.deg2rad(
    np.concatenate([np.linspace(2.0, -8.33, 32), np.linspace(-8.83, -24.33, 32)])
)
AZIMUTH_STEP = np.deg2rad(0.09)
MAX_RANGE = 80.0
DROPOUT = 0.08  # fraction of returns lost (dark or specular surfaces)


def lidar_mask(
    depth: np.ndarray,
    P: np.ndarray,
    velo_rotation: np.ndarray,
    velo_translation: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """(H, W) bool: the pixels of the dense ``depth`` (metres, 0 = none) that get a LiDAR return.

    Args:
      P: (3, 4) projection of the depth map's camera.
      velo_rotation, velo_translation: the LiDAR -> camera-0 transform
        (``X_cam = velo_rotation @ X_velo + velo_translation``).
    """
    H, W = depth.shape
    P = np.asarray(P, np.float64)
    # rows that can hold a beam: ray elevation (from the camera) below the top beam + margin
    cy, fy = P[1, 2], P[1, 1]
    v_top = int(max(0, np.floor(cy - fy * np.tan(BEAM_ELEVATIONS[0] + np.deg2rad(3.0)))))
    d = depth[v_top:].astype(np.float32)
    Minv = np.linalg.inv(P[:, :3]).astype(np.float32)
    C = camera_center(P).astype(np.float32)
    u = np.arange(W, dtype=np.float32)[None, :]
    v = np.arange(v_top, H, dtype=np.float32)[:, None]
    # camera-frame point minus the scanner origin, rotated into the scanner frame
    rel = [
        C[i] - np.float32(velo_translation[i]) + d * (Minv[i, 0] * u + Minv[i, 1] * v + Minv[i, 2])
        for i in range(3)
    ]
    R = np.asarray(velo_rotation, np.float32)
    xv, yv, zv = (rel[0] * R[0, k] + rel[1] * R[1, k] + rel[2] * R[2, k] for k in range(3))
    tan_elevation = zv / np.hypot(xv, yv)
    beam = np.interp(-tan_elevation, -np.tan(BEAM_ELEVATIONS), np.arange(64, dtype=np.float64))
    beam = np.floor(beam + 0.5).astype(np.int16)
    top, bottom = np.tan(BEAM_ELEVATIONS[0] + 0.003), np.tan(BEAM_ELEVATIONS[-1] - 0.004)
    valid = (d > 0) & (d < MAX_RANGE) & (tan_elevation <= top) & (tan_elevation >= bottom)
    # azimuth samples per image column (the scanner's parallax only shifts their phase)
    azimuth = np.arctan2(P[0, 2] - np.arange(W), P[0, 0]).astype(np.float32)
    phase = rng.uniform(0.0, 1.0, 64).astype(np.float32)
    sample = np.floor(azimuth[None, :] / np.float32(AZIMUTH_STEP) + phase[beam]).astype(np.int32)

    hit = np.zeros_like(valid)
    hit[1:] = (beam[1:] != beam[:-1]) & valid[1:] & valid[:-1]
    hit[:, 1:] &= sample[:, 1:] != sample[:, :-1]
    hit[:, 0] = False
    rr, cc = np.nonzero(hit)
    keep = rng.random(len(rr)) >= DROPOUT
    mask = np.zeros((H, W), bool)
    mask[rr[keep] + v_top, cc[keep]] = True
    return mask
