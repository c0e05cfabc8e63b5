"""One generated frame in memory: scene, both camera views, labels and LiDAR depth.

Frame ``index`` of a dataset with ``seed`` draws all its randomness from
``numpy.random.SeedSequence([seed, index])``, so a frame does not depend on the
number of frames, the split or the worker that renders it. Domain randomization (of the
background and of the cars) and photo textures draw from streams of their own, so a frame
they leave alone is the same with or without them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.kitti import Calibration, KittiObjects
from gac_jax.data.synthetic import (
    calibration,
    domain_randomization,
    labels,
    lidar,
    photo_textures,
    render,
    rigs,
)
from gac_jax.data.synthetic.scene import Scene, sample_scene


@dataclasses.dataclass
class Frame:
    """A rendered frame.

    Attributes:
      rig: index into the rig set's cameras (:func:`rigs.cameras`).
      image_size: (H, W) of this frame's images.
      calib: the frame's KITTI calibration (P0..P3 for this image size).
      plane: (4,) the road ``a x + b y + c z + d = 0`` in the reference camera frame
        (normal up, ``d`` = camera height; KITTI ``planes/`` convention).
      scene: the sampled scene (camera pose, road, solids, road users).
      views: camera (2 or 3) -> :class:`~gac_jax.data.synthetic.render.ViewRender`.
      objects: labels of the left view; label_source: (M,) scene object per label line.
      sparse: camera -> (H, W) bool mask of LiDAR returns in the dense depth.
    """

    rig: int
    image_size: tuple[int, int]
    calib: Calibration
    plane: np.ndarray
    scene: Scene
    views: dict[int, render.ViewRender]
    objects: KittiObjects
    label_source: np.ndarray
    sparse: dict[int, np.ndarray]


def _streams(seed: int, index: int) -> list[np.random.Generator]:
    # (children are keyed by their position: a new stream leaves the earlier ones as they were)
    children = np.random.SeedSequence([int(seed), int(index)]).spawn(9)
    return [np.random.default_rng(c) for c in children]


def frame_rig(seed: int, index: int, rig_set: str = "kitti") -> int:
    """Which camera rig (recording day or vehicle) frame ``index`` uses; cheap, no rendering."""
    return rigs.choose_rig(rig_set, _streams(seed, index)[0])


def make_frame(
    seed: int,
    index: int,
    image_size: tuple[int, int] = calibration.KITTI_SIZE,
    counts: dict[str, tuple[int, int]] | None = None,
    pitch: float | None = None,
    camera_height: float | None = None,
    rig_set: str = "kitti",
    randomize: float = 0.0,
    photo: float = 0.0,
    randomize_cars: float = 0.0,
    large_vehicles: float = 0.0,
    gardens: float = 0.0,
) -> Frame:
    """Samples and renders frame ``index`` of the dataset ``seed``.

    Args:
      image_size: (H, W) of KITTI's rigs; the intrinsics are scaled from 375x1242 (another
        rig set's native sizes by the same factors, :func:`rigs.image_size`).
      counts: class -> (min, max) road users (default ``scene.DEFAULT_COUNTS``).
      pitch, camera_height: fix the camera pose (radians, metres) instead of sampling it.
      rig_set: ``"kitti"`` (the default dataset) or ``"multi"`` (:mod:`rigs`).
      randomize: share of frames whose background gets random colours and patterns
        (:mod:`domain_randomization`; 0 = none).
      photo: share of frames whose foliage, rough solids and verges take their detail from
        photographs (:mod:`photo_textures`; 0 = none).
      randomize_cars: share of frames whose cars get random paint, glass and tyres
        (:func:`domain_randomization.randomize_cars`; 0 = none).
      large_vehicles: share of frames with vans and trucks among the road users, labelled
        ``Van`` / ``Truck`` (:mod:`vehicles`; 0 = none).
      gardens: probability that an urban roadside has front gardens, its buildings set back
        3-14 m behind lawns, hedges and trees (:mod:`gardens`; 0 = none).
    """
    (
        rig_rng, scene_rng, camera_rng, lidar_rng, random_rng, photo_rng, car_rng, vehicle_rng,
        garden_rng,
    ) = _streams(seed, index)  # fmt: skip
    rig_index = rigs.choose_rig(rig_set, rig_rng)
    rig = rigs.cameras(rig_set)[rig_index]
    pose = rigs.sample_pose(rig_set, rig_index, rig_rng)
    if pose is not None:
        pitch = pose[0] if pitch is None else pitch
        camera_height = pose[1] if camera_height is None else camera_height
    image_size = rigs.image_size(rig, image_size)
    calib = calibration.object_calibration(rig, image_size)
    scene = sample_scene(
        scene_rng,
        calib.P2,
        image_size,
        counts,
        pitch,
        camera_height,
        large_vehicles,
        vehicle_rng,
        gardens,
        garden_rng,
    )
    if randomize > 0.0:
        scene.background = domain_randomization.randomize_background(
            scene.background, random_rng, randomize
        )
    if photo > 0.0:
        scene.background, scene.road = photo_textures.photo_background(
            scene.background, scene.road, photo_rng, photo
        )
    if randomize_cars > 0.0:
        scene.objects = domain_randomization.randomize_cars(scene.objects, car_rng, randomize_cars)
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
    plane = rigs.ground_plane(scene.ground_normal, scene.camera_height)
    return Frame(rig_index, image_size, calib, plane, scene, views, objects, source, sparse)
