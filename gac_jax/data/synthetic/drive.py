"""A driving clip: one world (road, roadside, light, road users) seen from a moving car at 10 Hz.

The world is sampled once per sequence with the single-frame scene code
(:class:`scene.SceneBuilder`: road, roadside, light; :mod:`traffic`: road users and how they
move), in the road frame ``(t, y, s)``. The ego vehicle drives along its lane (``s``
growing at ``speed`` m/s from 0 at frame 0); its camera keeps its height and yaw on the car
and pitches with a small oscillation (suspension). Frame ``k`` (time ``k / 10`` s) is a
:class:`scene.Scene` in that frame's camera frame, rendered and labelled like a single frame
(:func:`render.render_view`, :func:`labels.frame_labels`): only the left camera (``P2``).

Poses follow the KITTI odometry convention: ``pose_k`` (3, 4) maps the rectified reference
camera frame of frame ``k`` (x right, y down, z forward; the frame of labels and planes) to
that of frame 0, ``X_0 = pose_k[:, :3] @ X_k + pose_k[:, 3]``.

Sequence ``seq`` of a clip set with ``seed`` draws all its randomness from
``numpy.random.SeedSequence([CLIP_TAG, seed, seq])`` (and the sensor noise of frame ``k`` from
``[CLIP_TAG, seed, seq, k + 1]``), so it does not depend on the number of sequences or
frames rendered, nor on the worker that renders it.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from gac_jax.data.kitti import Calibration, KittiObjects
from gac_jax.data.synthetic import calibration, labels, render, rigs, traffic
from gac_jax.data.synthetic.roadside import ROAD_END
from gac_jax.data.synthetic.scene import (
    DEFAULT_COUNTS,
    Road,
    Scene,
    SceneBuilder,
    place_object,
    rotation_x,
)
from gac_jax.geometry import rotation_y_matrix, wrap_angle

FRAME_RATE = 10.0  # Hz, KITTI's
CLIP_TAG = 0x636C6970  # "clip": keeps clip streams apart from the frames' (seed, index) streams
EGO_SPEED = (5.0, 12.0)  # m/s
PITCH_AMPLITUDE = (0.1, 0.4)  # degrees, of the oscillation
PITCH_FREQUENCY = (0.6, 1.5)  # Hz
NEAR_FAR = (-8.0, 120.0)  # depth range (m) of the road users put into a frame's scene


@dataclasses.dataclass(frozen=True)
class EgoMotion:
    """The ego vehicle's camera over a clip (cheap: no world is sampled).

    Attributes:
      rig: index into :func:`rigs.cameras` of the rig set.
      speed: m/s along the road.
      camera_height: metres above the road.
      pitch0, pitch_amplitude: mean pitch and oscillation amplitude (radians, + = down).
      pitch_frequency, pitch_phase: of the oscillation (Hz, radians).
      heading: the camera's yaw relative to the road direction (radians about y).
    """

    rig: int
    speed: float
    camera_height: float
    pitch0: float
    pitch_amplitude: float
    pitch_frequency: float
    pitch_phase: float
    heading: float

    def pitch(self, k: int) -> float:
        """Pitch of frame ``k`` (radians)."""
        phase = 2 * np.pi * self.pitch_frequency * k / FRAME_RATE + self.pitch_phase
        return float(self.pitch0 + self.pitch_amplitude * np.sin(phase))

    def road_rotation(self, k: int) -> np.ndarray:
        """(3, 3) road-frame directions -> camera frame of frame ``k``."""
        return rotation_x(self.pitch(k)) @ rotation_y_matrix(self.heading)

    def travelled(self, k: int) -> float:
        """Metres along the road from frame 0 to frame ``k``."""
        return self.speed * k / FRAME_RATE

    def pose(self, k: int) -> np.ndarray:
        """(3, 4) camera-to-world pose of frame ``k`` (world = frame 0's camera frame)."""
        # X_road = Rk^T X_k + (lateral, 0, travelled) and X_0 = R0 (X_road - (lateral, 0, 0)):
        # the rotation R0 Rk^T is a pitch difference (the yaw cancels), the translation the
        # distance travelled along the road direction seen from frame 0
        rotation = rotation_x(self.pitch(0) - self.pitch(k))
        translation = self.road_rotation(0)[:, 2] * self.travelled(k)
        return np.concatenate([rotation, translation[:, None]], axis=1) + 0.0  # (no -0.0)

    def plane(self, k: int) -> np.ndarray:
        """(4,) ground plane of frame ``k`` (KITTI ``planes/`` convention: normal up, d = h)."""
        return rigs.ground_plane(self.road_rotation(k)[:, 1], self.camera_height)


def _streams(seed: int, sequence: int) -> list[np.random.Generator]:
    children = np.random.SeedSequence([CLIP_TAG, int(seed), int(sequence)]).spawn(2)
    return [np.random.default_rng(c) for c in children]


def ego_motion(seed: int, sequence: int, rig_set: str = "kitti") -> EgoMotion:
    """The camera motion of sequence ``sequence`` (one rig for the whole sequence)."""
    rng = _streams(seed, sequence)[0]
    rig = rigs.choose_rig(rig_set, rng)
    pose = rigs.sample_pose(rig_set, rig, rng)
    if pose is None:  # KITTI's rigs: level within +-0.6 deg, 1.65 +- 0.05 m
        pitch0 = float(np.deg2rad(np.clip(rng.normal(0.0, 0.3), -0.6, 0.6)))
        height = float(1.65 + rng.uniform(-0.05, 0.05))
    else:
        pitch0, height = pose
    return EgoMotion(
        rig=rig,
        speed=float(rng.uniform(*EGO_SPEED)),
        camera_height=height,
        pitch0=pitch0,
        pitch_amplitude=float(np.deg2rad(rng.uniform(*PITCH_AMPLITUDE))),
        pitch_frequency=float(rng.uniform(*PITCH_FREQUENCY)),
        pitch_phase=float(rng.uniform(0.0, 2 * np.pi)),
        heading=float(np.deg2rad(np.clip(rng.normal(0.0, 0.7), -1.5, 1.5))),
    )


def clip_calibration(
    ego: EgoMotion, image_size: tuple[int, int], rig_set: str
) -> tuple[Calibration, tuple[int, int]]:
    """The sequence's calibration and its image size (the rig's, scaled like the frames')."""
    rig = rigs.cameras(rig_set)[ego.rig]
    size = rigs.image_size(rig, image_size)
    return calibration.object_calibration(rig, size), size


@dataclasses.dataclass
class Drive:
    """The world of one sequence and the camera moving through it."""

    ego: EgoMotion
    calib: Calibration
    image_size: tuple[int, int]
    lateral: float  # the camera's road position t
    road: Road
    road_solids: list  # the background, road frame
    movers: list[traffic.Mover]
    sun_level: np.ndarray  # (3,) towards the sun, camera frame without pitch
    light: dict  # ambient, shadow, sky_top, sky_horizon, exposure

    def scene(self, k: int) -> tuple[Scene, np.ndarray]:
        """Frame ``k``'s scene and the track id of each of its objects (M,)."""
        ego = self.ego
        R = ego.road_rotation(k)
        T = -R @ np.array([self.lateral, 0.0, ego.travelled(k)])
        time = k / FRAME_RATE
        objects, ids = [], []
        for m in self.movers:
            t, s = m.position(time)
            loc = np.round(R @ np.array([t - self.lateral, m.support, s - ego.travelled(k)]), 2)
            if not NEAR_FAR[0] <= loc[2] <= NEAR_FAR[1]:
                continue
            ry = float(np.round(wrap_angle(ego.heading + m.psi - np.pi / 2), 2))
            objects.append(place_object(m.type, m.dimensions, m.parts, loc, ry, m.support))
            ids.append(m.track_id)
        scene = Scene(
            camera_height=ego.camera_height,
            pitch=ego.pitch(k),
            heading=ego.heading,
            lateral=self.lateral,
            road_rotation=R,
            road_translation=T,
            road=self.road,
            background=[solid.transformed(R, T) for solid in self.road_solids],
            objects=objects,
            sun=rotation_x(ego.pitch(k)) @ self.sun_level,
            **self.light,
        )
        return scene, np.array(ids, np.int64)


def make_drive(
    seed: int,
    sequence: int,
    num_frames: int,
    image_size: tuple[int, int] = calibration.KITTI_SIZE,
    counts: dict[str, tuple[int, int]] | None = None,
    rig_set: str = "kitti",
) -> Drive:
    """Samples the world of sequence ``sequence`` for a clip of ``num_frames`` frames."""
    ego = ego_motion(seed, sequence, rig_set)
    calib, size = clip_calibration(ego, image_size, rig_set)
    rng = _streams(seed, sequence)[1]
    counts = DEFAULT_COUNTS if counts is None else counts
    b = SceneBuilder(rng, calib.P2, size, counts, ego.pitch0, ego.camera_height)
    duration = (num_frames - 1) / FRAME_RATE
    b.road_end = ROAD_END + ego.travelled(num_frames - 1)
    road = b.road()
    b.roadside()
    movers = traffic.place_movers(b, duration, ego.speed)
    light = b.light()
    sun = light.pop("sun")
    return Drive(
        ego=ego,
        calib=calib,
        image_size=size,
        lateral=float(b.lateral),
        road=road,
        road_solids=b.road_solids,
        movers=movers,
        sun_level=rotation_x(ego.pitch0).T @ sun,
        light=light,
    )


@functools.lru_cache(maxsize=2)
def cached_drive(seed, sequence, num_frames, image_size, counts_items, rig_set) -> Drive:
    """:func:`make_drive` kept for the next frames of the same sequence (in a worker)."""
    return make_drive(seed, sequence, num_frames, image_size, dict(counts_items), rig_set)


@dataclasses.dataclass
class ClipFrame:
    """A rendered frame of a clip: the left view, its labels with track ids, plane and pose.

    Attributes:
      view: :class:`render.ViewRender` of ``P2`` (image, depth, object ids).
      objects: KITTI labels (labelled objects first, DontCare last).
      track_ids: (M,) track id per label line (-1 for DontCare).
      label_source: (M,) index into ``scene.objects`` (and ``view.object_ids``) per line.
      plane: (4,) ground plane; pose: (3, 4) camera-to-world.
    """

    scene: Scene
    view: render.ViewRender
    objects: KittiObjects
    track_ids: np.ndarray
    label_source: np.ndarray
    plane: np.ndarray
    pose: np.ndarray


def render_clip_frame(drive: Drive, seed: int, sequence: int, k: int) -> ClipFrame:
    """Renders and labels frame ``k`` of the sequence ``drive`` (of clip set ``seed``)."""
    scene, ids = drive.scene(k)
    noise_rng = np.random.default_rng(
        np.random.SeedSequence([CLIP_TAG, int(seed), int(sequence), int(k) + 1])
    )
    view = render.render_view(scene, drive.calib.P2, drive.image_size, noise_rng)
    objects, source = labels.frame_labels(scene, view, drive.calib.P2, drive.image_size)
    track_ids = np.where(objects.type == "DontCare", -1, ids[source])
    return ClipFrame(
        scene,
        view,
        objects,
        track_ids.astype(np.int64),
        source,
        drive.ego.plane(k),
        drive.ego.pose(k),
    )
