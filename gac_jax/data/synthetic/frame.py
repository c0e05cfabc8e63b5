"""One generated frame in memory: scene, both camera views, labels and LiDAR depth.

Frame ``index`` of a dataset with ``seed`` draws all its randomness from
``numpy.random.SeedSequence([seed, index])``, so a frame does not depend on the
number of frames, the split or the worker that renders it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.kitti import Calibration, KittiObjects
from gac_jax.data.synthetic import calibration, labels, lidar, render
from gac_jax.data.synthetic.scene import Scene, sample_scene


@dataclasses.dataclass
class Frame:
    """A rendered frame.

    Attributes:
      rig: index into :data:`calibration.RIGS`.
      calib: the frame's KITTI calibration (P0..P3 for this image size).
      scene: the sampled scene (camera pose, road, solids, road users).
      views: camera (2 or 3) -> :class:`~gac_jax.data.synthetic.render.ViewRender`.
      objects: labels of the left view; label_source: (M,) scene object per label line.
      sparse: camera -> (H, W) bool mask of LiDAR returns in the dense depth.
    """

    rig: int
    calib: Calibration
    scene: Scene
    views: dict[int, render.ViewRender]
    objects: KittiObjects
    label_source: np.ndarray
    sparse: dict[int, np.ndarray]


def _streams(seed: int, index: int) -> list[np.random.Generator]:
    children = np.random.SeedSequence([int(seed), int(index)]).spawn(4)
    return [np.random.default_rng(c) for c in children]


def frame_rig(seed: int, index: int) -> int:
    """Which camera rig (recording day) frame ``index`` uses; cheap, no rendering."""
    rng = _streams(seed, index)[0]
    return int(rng.choice(len(calibration.RIGS), p=calibration.RIG_WEIGHTS))


def make_frame(
    seed: int,
    index: int,
    image_size: tuple[int, int] = calibration.KITTI_SIZE,
    counts: dict[str, tuple[int, int]] | None = None,
    pitch: float | None = None,
    camera_height: float | None = None,
) -> Frame:
    """Samples and renders frame ``index`` of the dataset ``seed``.

    Args:
      image_size: (H, W); the rig intrinsics are scaled from 375x1242.
      counts: class -> (min, max) road users (default ``scene.DEFAULT_COUNTS``).
      pitch, camera_height: fix the camera pose instead of sampling it.
    """
    _, scene_rng, camera_rng, lidar_rng = _streams(seed, index)
    rig_index = frame_rig(seed, index)
    rig = calibration.RIGS[rig_index]
    calib = calibration.object_calibration(rig, image_size)
    scene = sample_scene(scene_rng, calib.P2, image_size, counts, pitch, camera_height)
    views = {
        2: render.render_view(scene, calib.P2, image_size, camera_rng),
        3: render.render_view(scene, calib.P3, image_size, camera_rng),
    }
    objects, source = labels.frame_labels(scene, views[2], calib.P2, image_size)
    sparse = {
        cam: lidar.lidar_mask(
            views[cam].depth, P, rig.velo_rotation, rig.velo_translation, lidar_rng
        )
        for cam, P in ((2, calib.P2), (3, calib.P3))
    }
    return Frame(rig_index, calib, scene, views, objects, source, sparse)
