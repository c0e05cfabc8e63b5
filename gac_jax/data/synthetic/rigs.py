"""Camera rig sets of the generated dataset: KITTI's one mount, or several vehicles.

``"kitti"`` is what the default dataset has always been: the three real KITTI recording
days (:data:`calibration.RIGS`), a camera 1.65 +- 0.05 m above the road, pitch within
+-1 degree. ``"multi"`` mounts cameras on eight vehicles (:data:`MULTI_RIGS`): heights
1.2-2.4 m, nominal pitch -5..+6 degrees (positive = tilted down; +-1 degree of per-frame
jitter on top, so -6..+7 in all), focal lengths 600-860 px, principal points and image
sizes of their own. Two of them are held out: their frames are never in ``train`` and form
the ``val_heldout`` split. With one camera height and no pitch a network can learn the
row -> depth map from the pixels alone; with several it needs the ground plane, which
``"multi"`` frames carry in ``training/planes/NNNNNN.txt`` and, for the KITTI-depth layout
of the same frames, ``depth/planes/<drive>/NNNNNNNNNN.txt`` (the same file).

The ground plane of a frame is ``a x + b y + c z + d = 0`` in the rectified reference
camera frame (x right, y down, z forward, metres), normal pointing up (``b < 0``) and
``d`` the camera height: the KITTI ``planes/`` convention.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import calibration

RIG_SETS = ("kitti", "multi")
POSE_JITTER_HEIGHT = 0.05  # m, uniform, per frame
POSE_JITTER_PITCH = 0.5  # degrees, normal (clipped to twice this), per frame


@dataclasses.dataclass(frozen=True)
class MountedRig:
    """A camera rig on a vehicle: intrinsics and native image size, mount height and pitch.

    Attributes:
      name: short name (folder names, reports).
      camera: the :class:`~calibration.CameraRig` (``K`` at ``camera.size``).
      height: nominal camera height above the road (m).
      pitch: nominal pitch (degrees, positive = tilted down).
      heldout: frames of this rig form ``val_heldout`` only.
    """

    name: str
    camera: calibration.CameraRig
    height: float
    pitch: float
    heldout: bool = False


def _rig(number: int, size, f, cx, cy) -> calibration.CameraRig:
    K = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    base = calibration.RIGS[0]  # KITTI's LiDAR mount; camera 2 ~6 cm right of camera 0
    return calibration.CameraRig(
        date=f"2030_01_{number:02d}",
        K=K,
        p2_col3=K @ np.array([0.06, 0.0, 0.003]),
        velo_rotation=base.velo_rotation,
        velo_translation=base.velo_translation,
        size=size,
    )


MULTI_RIGS: tuple[MountedRig, ...] = (
    MountedRig("kitti", _rig(1, (375, 1242), 721.5377, 609.5593, 172.854), 1.65, 0.0),
    MountedRig("hatchback", _rig(2, (360, 1280), 640.0, 650.0, 185.0), 1.25, 4.0),
    MountedRig("suv", _rig(3, (400, 1216), 780.0, 600.0, 190.0), 1.95, -3.0),
    MountedRig("van", _rig(4, (384, 1280), 700.0, 630.0, 200.0), 2.20, 6.0),
    MountedRig("sports", _rig(5, (352, 1232), 600.0, 620.0, 160.0), 1.20, -5.0),
    MountedRig("truck", _rig(6, (416, 1248), 860.0, 615.0, 215.0), 2.40, 2.0),
    MountedRig("crossover", _rig(7, (376, 1240), 680.0, 612.0, 178.0), 1.80, -2.0, True),
    MountedRig("minibus", _rig(8, (392, 1264), 740.0, 640.0, 205.0), 1.45, 3.0, True),
)


def cameras(rig_set: str) -> tuple[calibration.CameraRig, ...]:
    """The camera rigs of a set, in index order (a frame's ``rig`` indexes this)."""
    check_rig_set(rig_set)
    if rig_set == "kitti":
        return calibration.RIGS
    return tuple(r.camera for r in MULTI_RIGS)


def check_rig_set(rig_set: str) -> None:
    if rig_set not in RIG_SETS:
        raise ValueError(f"rig set must be one of {', '.join(RIG_SETS)}, got {rig_set!r}")


def image_size(camera: calibration.CameraRig, scale_to: tuple[int, int]) -> tuple[int, int]:
    """(H, W) of a rig's frames when the dataset's KITTI-sized frames are ``scale_to``.

    KITTI's own rigs give ``scale_to``; another rig's native size is scaled by the same
    factors (``scale_to / 375x1242``), so ``--height/--width`` keep meaning "KITTI at
    this resolution" for every rig set.
    """
    if camera.size == calibration.KITTI_SIZE:
        return tuple(scale_to)
    kh, kw = calibration.KITTI_SIZE
    return (
        int(round(camera.size[0] * scale_to[0] / kh)),
        int(round(camera.size[1] * scale_to[1] / kw)),
    )


def choose_rig(rig_set: str, rng: np.random.Generator) -> int:
    """Index of the rig (in :func:`cameras` order) of one frame."""
    if rig_set == "kitti":
        return int(rng.choice(len(calibration.RIGS), p=calibration.RIG_WEIGHTS))
    return int(rng.integers(len(MULTI_RIGS)))


def sample_pose(rig_set: str, rig: int, rng: np.random.Generator) -> tuple[float, float] | None:
    """``(pitch radians, camera height m)`` of one frame of a ``"multi"`` rig: the mount's
    nominal pose plus per-frame jitter. None for ``"kitti"``: the scene samples its own
    (kept as it was, so the default dataset does not change)."""
    if rig_set == "kitti":
        return None
    mount = MULTI_RIGS[rig]
    jitter = np.clip(
        rng.normal(0.0, POSE_JITTER_PITCH), -2 * POSE_JITTER_PITCH, 2 * POSE_JITTER_PITCH
    )
    height = mount.height + rng.uniform(-POSE_JITTER_HEIGHT, POSE_JITTER_HEIGHT)
    return float(np.deg2rad(mount.pitch + jitter)), float(height)


def heldout(rig_set: str, rig: int) -> bool:
    return rig_set == "multi" and MULTI_RIGS[rig].heldout


def ground_plane(ground_normal: np.ndarray, camera_height: float) -> np.ndarray:
    """(4,) ``(a, b, c, d)`` of the road ``ground_normal . X = camera_height`` (normal pointing
    down, as the scene has it) in the KITTI ``planes/`` convention (normal up, ``d`` = height)."""
    n = np.asarray(ground_normal, np.float64)
    return np.concatenate([-n / np.linalg.norm(n), [camera_height]]) + 0.0  # (no -0.0)
