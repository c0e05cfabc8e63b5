"""Camera rigs of the generated dataset: real KITTI intrinsics, a 0.54 m stereo pair, a LiDAR mount.

Each rig is one KITTI recording day. Its projections follow KITTI's rectified
model: every camera is ``P_i = K [I | t_i]`` in the rectified reference frame of
camera 0 (x right, y down, z forward, metres), with ``R0_rect = I``:

* ``P0`` grey left (``t = 0``), ``P1`` grey right (0.54 m to the right),
* ``P2`` colour left: the real KITTI ``P2`` of that day (``t ~ (0.06, 0, 0.003)`` m),
* ``P3`` colour right: ``P2`` moved 0.54 m to the right, so ``P3 - P2 = -0.54 fx`` in
  column 3 only (the paper's virtual baseline; the real colour pair is 0.532 m).

At an image size other than KITTI's 375x1242 the intrinsics are scaled by
``(W / 1242, H / 375)`` (a resized KITTI frame). The LiDAR mount is KITTI's:
the scanner sits about 8 cm above and 27 cm behind camera 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.kitti import Calibration

KITTI_SIZE = (375, 1242)  # (H, W) the rig intrinsics refer to
BASELINE = 0.54  # metres between P2 and P3 (and between P0 and P1)


@dataclasses.dataclass(frozen=True)
class CameraRig:
    """One recording day: intrinsics ``K`` (3, 3) at ``size`` and the P2 column 3.

    Attributes:
      date: KITTI raw date string, e.g. ``"2011_09_26"``.
      K: (3, 3) intrinsics at ``size`` (KITTI's 375x1242 for the real days).
      p2_col3: (3,) ``P2[:, 3]`` of the real calibration (pixels, pixels, metres).
      velo_rotation: (3, 3) rotation LiDAR -> camera 0.
      velo_translation: (3,) LiDAR origin in camera 0.
      size: (H, W) of the rig's native images.
    """

    date: str
    K: np.ndarray
    p2_col3: np.ndarray
    velo_rotation: np.ndarray
    velo_translation: np.ndarray
    size: tuple[int, int] = KITTI_SIZE  # (H, W) that K and p2_col3 refer to


def _K(f: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


# Values from the calibration files of the real KITTI days (object-benchmark calib / raw calib).
RIGS: tuple[CameraRig, ...] = (
    CameraRig(
        "2011_09_26",
        _K(721.5377, 609.5593, 172.854),
        np.array([44.85728, 0.2163791, 0.002745884]),
        np.array(
            [
                [7.533745e-03, -9.999714e-01, -6.166020e-04],
                [1.480249e-02, 7.280733e-04, -9.998902e-01],
                [9.998621e-01, 7.523790e-03, 1.480755e-02],
            ]
        ),
        np.array([-4.069766e-03, -7.631618e-02, -2.717806e-01]),
    ),
    CameraRig(
        "2011_09_29",
        _K(718.3351, 600.3891, 181.5122),
        np.array([44.50382, -0.5951107, 0.002616315]),
        np.array(
            [
                [7.755449e-03, -9.999694e-01, -1.014303e-03],
                [2.294056e-03, 1.032122e-03, -9.999968e-01],
                [9.999673e-01, 7.753097e-03, 2.301990e-03],
            ]
        ),
        np.array([-7.275538e-03, -6.324057e-02, -2.670414e-01]),
    ),
    CameraRig(
        "2011_09_30",
        _K(707.0493, 604.0814, 180.5066),
        np.array([45.75831, -0.3454157, 0.004981016]),
        np.array(
            [
                [6.927964e-03, -9.999722e-01, -2.757829e-03],
                [-1.162982e-03, 2.749836e-03, -9.999955e-01],
                [9.999753e-01, 6.931141e-03, -1.143899e-03],
            ]
        ),
        np.array([-2.457729e-02, -6.127237e-02, -3.321029e-01]),
    ),
)
RIG_WEIGHTS = np.array([0.6, 0.2, 0.2])  # most KITTI object frames come from the 721.5 px days


def scale_matrix(image_size: tuple[int, int], native: tuple[int, int] = KITTI_SIZE) -> np.ndarray:
    """(3, 3) pixel scaling from the ``native`` grid (KITTI's 375x1242) to ``image_size``."""
    height, width = image_size
    return np.diag([width / native[1], height / native[0], 1.0])


def projections(rig: CameraRig, image_size: tuple[int, int]) -> dict[int, np.ndarray]:
    """``{0: P0, 1: P1, 2: P2, 3: P3}`` (3, 4) float64 for images of size ``(H, W)``."""
    K = rig.K
    t2 = np.linalg.solve(K, rig.p2_col3)  # camera-2 translation in metres
    shift = np.array([-BASELINE, 0.0, 0.0])
    translations = {0: np.zeros(3), 1: shift, 2: t2, 3: t2 + shift}
    S = scale_matrix(image_size, rig.size)
    out = {}
    for cam, t in translations.items():
        P = np.concatenate([K, (K @ t)[:, None]], axis=1)
        if cam == 2:
            P[:, 3] = rig.p2_col3  # exactly the published numbers
        elif cam == 3:
            P[:, 3] = rig.p2_col3 - np.array([BASELINE * K[0, 0], 0.0, 0.0])
        out[cam] = S @ P
    return out


def velo_to_cam(rig: CameraRig) -> np.ndarray:
    """(3, 4) ``Tr_velo_to_cam``: LiDAR (x forward, y left, z up) -> camera 0."""
    return np.concatenate([rig.velo_rotation, rig.velo_translation[:, None]], axis=1)


def object_calibration(rig: CameraRig, image_size: tuple[int, int]) -> Calibration:
    """The per-frame ``calib/NNNNNN.txt`` content (``R0_rect = I``)."""
    P = projections(rig, image_size)
    return Calibration(
        P0=P[0], P1=P[1], P2=P[2], P3=P[3], R0_rect=np.eye(3), Tr_velo_to_cam=velo_to_cam(rig)
    )


def _fmt(values) -> str:
    return " ".join(f"{v:.6e}" for v in np.ravel(values))


def cam_to_cam_text(rig: CameraRig, image_size: tuple[int, int]) -> str:
    """KITTI raw ``calib_cam_to_cam.txt`` for ``rig`` (distortion-free, rectified cameras)."""
    height, width = image_size
    P = projections(rig, image_size)
    lines = ["calib_time: 01-Jan-2012 00:00:00", "corner_dist: 9.950000e-02"]
    for cam in range(4):
        K = P[cam][:, :3]
        t = np.linalg.solve(K, P[cam][:, 3])
        lines += [
            f"S_0{cam}: {_fmt([width, height])}",
            f"K_0{cam}: {_fmt(K)}",
            f"D_0{cam}: {_fmt(np.zeros(5))}",
            f"R_0{cam}: {_fmt(np.eye(3))}",
            f"T_0{cam}: {_fmt(t)}",
            f"S_rect_0{cam}: {_fmt([width, height])}",
            f"R_rect_0{cam}: {_fmt(np.eye(3))}",
            f"P_rect_0{cam}: {_fmt(P[cam])}",
        ]
    return "\n".join(lines) + "\n"


def velo_to_cam_text(rig: CameraRig) -> str:
    """KITTI raw ``calib_velo_to_cam.txt`` for ``rig``."""
    return (
        "calib_time: 01-Jan-2012 00:00:00\n"
        f"R: {_fmt(rig.velo_rotation)}\nT: {_fmt(rig.velo_translation)}\n"
        "delta_f: 0.000000e+00 0.000000e+00\ndelta_c: 0.000000e+00 0.000000e+00\n"
    )
