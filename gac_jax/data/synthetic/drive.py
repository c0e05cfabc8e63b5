"""A driving clip: one world (road, roadside, light, road users) seen from a moving car at 10 Hz.

The world is sampled once per sequence with the single-frame scene code
(:class:`scene.SceneBuilder`: road, roadside, light; :mod:`traffic`: road users, how they
move and the sequence's scenarios), in the road frame ``(t, y, s)``, and bent along the
road's centre line (:class:`road_path.RoadPath`: straight, or with bends). The ego vehicle
drives along its lane (``s`` from 0 at frame 0) at a speed that is constant or, with the
``ego_speed`` scenario, changes (accelerating, braking, stopping); its camera keeps its
height and yaw on the car (turning with the road) and pitches with a small oscillation
(suspension). Frame ``k`` (time ``k / 10`` s) is a :class:`scene.Scene` in that frame's
camera frame, rendered and labelled like a single frame (:func:`render.render_view`,
:func:`labels.frame_labels`): only the left camera (``P2``).

Poses follow the KITTI odometry convention: ``pose_k`` (3, 4) maps the rectified reference
camera frame of frame ``k`` (x right, y down, z forward; the frame of labels and planes) to
that of frame 0, ``X_0 = pose_k[:, :3] @ X_k + pose_k[:, 3]``. The ground is one flat plane
of that world; each frame's plane is that plane in the frame's camera frame.

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
from gac_jax.data.synthetic.road_path import Motion, RoadPath, SpeedProfile
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
EGO_SPEED = (5.0, 12.0)  # m/s (the starting speed)
PITCH_AMPLITUDE = (0.1, 0.4)  # degrees, of the oscillation
PITCH_FREQUENCY = (0.6, 1.5)  # Hz
NEAR_FAR = (-8.0, 120.0)  # depth range (m) of the road users put into a frame's scene
BEND_RADIUS = (100.0, 350.0)  # m
BEND_LENGTH = (40.0, 150.0)  # m of road
EGO_ACCELERATION = (1.0, 3.0)  # m/s^2, either way
DEFAULT_MIX = tuple(traffic.DEFAULT_MIX.items())


@dataclasses.dataclass(frozen=True)
class EgoMotion:
    """The ego vehicle's camera over a clip and the sequence's plan (cheap: no world).

    Attributes:
      rig: index into :func:`rigs.cameras` of the rig set.
      speed: m/s along the road at frame 0; profile: the speed over time.
      camera_height: metres above the road.
      pitch0, pitch_amplitude: mean pitch and oscillation amplitude (radians, + = down).
      pitch_frequency, pitch_phase: of the oscillation (Hz, radians).
      heading: the camera's yaw relative to the road direction (radians about y).
      path: the road's centre line; scenarios: the sequence's (:data:`traffic.SCENARIOS`).
    """

    rig: int
    speed: float
    camera_height: float
    pitch0: float
    pitch_amplitude: float
    pitch_frequency: float
    pitch_phase: float
    heading: float
    profile: SpeedProfile = SpeedProfile()
    path: RoadPath = RoadPath()
    scenarios: frozenset = frozenset()

    def pitch(self, k: int) -> float:
        """Pitch of frame ``k`` (radians)."""
        phase = 2 * np.pi * self.pitch_frequency * k / FRAME_RATE + self.pitch_phase
        return float(self.pitch0 + self.pitch_amplitude * np.sin(phase))

    def travelled(self, k: int) -> float:
        """Metres along the road from frame 0 to frame ``k``."""
        return float(self.profile.distance(k / FRAME_RATE))

    def road_rotation(self, k: int) -> np.ndarray:
        """(3, 3) world road-frame directions -> camera frame of frame ``k``."""
        theta = float(self.path.heading(self.travelled(k)))
        return rotation_x(self.pitch(k)) @ rotation_y_matrix(self.heading - theta)

    def plane(self, k: int) -> np.ndarray:
        """(4,) ground plane of frame ``k`` (KITTI ``planes/`` convention: normal up, d = h)."""
        return rigs.ground_plane(self.road_rotation(k)[:, 1], self.camera_height)

    def motion(self, lateral: float) -> Motion:
        """The camera's road-frame motion (in the lane at ``lateral``)."""
        return Motion(lateral, 0.0, 0.0, 1.0, self.profile)


def _streams(seed: int, sequence: int) -> list[np.random.Generator]:
    children = np.random.SeedSequence([CLIP_TAG, int(seed), int(sequence)]).spawn(3)
    return [np.random.default_rng(c) for c in children]


def _bends(rng) -> RoadPath:
    """One or two bends (the first may already be under way at frame 0)."""
    starts, curvatures = [0.0], [0.0]
    s = rng.uniform(-10.0, 40.0)
    for _ in range(1 + int(rng.random() < 0.5)):
        kappa = rng.choice([-1.0, 1.0]) / rng.uniform(*BEND_RADIUS)
        if s <= 0.0:
            curvatures[0] = kappa
        else:
            starts.append(s)
            curvatures.append(kappa)
        s = max(s, 0.0) + rng.uniform(*BEND_LENGTH)
        starts.append(s)
        curvatures.append(0.0)
        s += rng.uniform(10.0, 60.0)
    return RoadPath(tuple(float(v) for v in starts), tuple(float(v) for v in curvatures))


def _speed_changes(rng, v0: float) -> SpeedProfile:
    """Holds, then accelerates or brakes (sometimes to a stop) to a new speed, and again."""
    times, speeds = [0.0], [v0]
    time, v = rng.uniform(0.0, 1.5), v0
    while time < 120.0 and len(times) < 40:
        times.append(time)
        speeds.append(v)
        target = 0.0 if rng.random() < 0.15 else rng.uniform(3.0, 14.0)
        time += max(abs(target - v) / rng.uniform(*EGO_ACCELERATION), 0.1)
        v = target
        times.append(time)
        speeds.append(v)
        time += rng.uniform(1.0, 4.0)
    return SpeedProfile(tuple(times), tuple(speeds))


def ego_motion(
    seed: int, sequence: int, rig_set: str = "kitti", mix: tuple = DEFAULT_MIX
) -> EgoMotion:
    """The camera motion and plan of sequence ``sequence`` (one rig for the whole sequence).

    Args:
      mix: ``(scenario, share of sequences)`` pairs (:data:`traffic.SCENARIOS`).
    """
    rng, _, plan = _streams(seed, sequence)
    rig = rigs.choose_rig(rig_set, rng)
    pose = rigs.sample_pose(rig_set, rig, rng)
    if pose is None:  # KITTI's rigs: level within +-0.6 deg, 1.65 +- 0.05 m
        pitch0 = float(np.deg2rad(np.clip(rng.normal(0.0, 0.3), -0.6, 0.6)))
        height = float(1.65 + rng.uniform(-0.05, 0.05))
    else:
        pitch0, height = pose
    speed = float(rng.uniform(*EGO_SPEED))
    shares = dict(mix)
    draws = {name: plan.random() for name in traffic.SCENARIOS}
    scenarios = frozenset(n for n in traffic.SCENARIOS if draws[n] < shares.get(n, 0.0))
    path = _bends(plan) if "curve" in scenarios else RoadPath()
    profile = (
        _speed_changes(plan, speed) if "ego_speed" in scenarios else SpeedProfile((0.0,), (speed,))
    )
    return EgoMotion(
        rig=rig,
        speed=speed,
        camera_height=height,
        pitch0=pitch0,
        pitch_amplitude=float(np.deg2rad(rng.uniform(*PITCH_AMPLITUDE))),
        pitch_frequency=float(rng.uniform(*PITCH_FREQUENCY)),
        pitch_phase=float(rng.uniform(0.0, 2 * np.pi)),
        heading=float(np.deg2rad(np.clip(rng.normal(0.0, 0.7), -1.5, 1.5))),
        profile=profile,
        path=path,
        scenarios=scenarios,
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
    world_solids: list  # the background, world road frame
    movers: list[traffic.Mover]
    sun_world: np.ndarray  # (3,) towards the sun, world road frame
    light: dict  # ambient, shadow, sky_top, sky_horizon, exposure

    def camera(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """``(R, P)``: frame ``k``'s camera sees world road-frame point X at ``R (X - P)``."""
        x, z = self.ego.path.point(self.lateral, self.ego.travelled(k))
        return self.ego.road_rotation(k), np.array([x, 0.0, z])

    def pose(self, k: int) -> np.ndarray:
        """(3, 4) camera-to-world pose of frame ``k`` (world = frame 0's camera frame)."""
        R0, P0 = self.camera(0)
        Rk, Pk = self.camera(k)
        return np.concatenate([R0 @ Rk.T, (R0 @ (Pk - P0))[:, None]], axis=1) + 0.0

    def mover_world(self, mover: traffic.Mover, time: float) -> tuple[np.ndarray, float]:
        """World road-frame bottom centre (3,) and heading (radians about y) at ``time``."""
        t, s, psi = mover.motion.at(time)
        x, z = self.ego.path.point(t, s)
        return np.array([x, mover.support, z]), float(self.ego.path.heading(s) + psi)

    def velocity(self, mover: traffic.Mover, time: float) -> np.ndarray:
        """(3,) velocity (m/s) of ``mover`` at ``time`` in frame 0's camera frame."""
        t, s, _ = mover.motion.at(time)
        vx, vz = self.ego.path.velocity(t, s, *mover.motion.rates(time))
        return self.camera(0)[0] @ np.array([vx, 0.0, vz])

    def scene(self, k: int) -> tuple[Scene, np.ndarray]:
        """Frame ``k``'s scene and the track id of each of its objects (M,)."""
        ego = self.ego
        R, P = self.camera(k)
        T = -R @ P
        yaw = ego.heading - float(ego.path.heading(ego.travelled(k)))  # world -> camera
        time = k / FRAME_RATE
        objects, ids = [], []
        for m in self.movers:
            where, heading = self.mover_world(m, time)
            loc = np.round(R @ (where - P), 2)
            if not NEAR_FAR[0] <= loc[2] <= NEAR_FAR[1]:
                continue
            ry = float(np.round(wrap_angle(yaw + heading - np.pi / 2), 2))
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
            background=[solid.transformed(R, T) for solid in self.world_solids],
            objects=objects,
            sun=R @ self.sun_world,
            **self.light,
            path=None if ego.path.straight else ego.path,
        )
        return scene, np.array(ids, np.int64)


def make_drive(
    seed: int,
    sequence: int,
    num_frames: int,
    image_size: tuple[int, int] = calibration.KITTI_SIZE,
    counts: dict[str, tuple[int, int]] | None = None,
    rig_set: str = "kitti",
    mix: tuple = DEFAULT_MIX,
) -> Drive:
    """Samples the world of sequence ``sequence`` for a clip of ``num_frames`` frames."""
    ego = ego_motion(seed, sequence, rig_set, mix)
    calib, size = clip_calibration(ego, image_size, rig_set)
    rng = _streams(seed, sequence)[1]
    counts = DEFAULT_COUNTS if counts is None else counts
    b = SceneBuilder(rng, calib.P2, size, counts, ego.pitch0, ego.camera_height)
    duration = (num_frames - 1) / FRAME_RATE
    end = ego.travelled(num_frames - 1)
    b.road_end = ROAD_END + end
    scenarios = ego.scenarios
    b.two_way = "oncoming" in scenarios
    b.min_right_lanes = 2 if "lane_change" in scenarios else 1
    b.force_parking = "parked" in scenarios
    b.piece_length = None if ego.path.straight else 4.0
    if "intersection" in scenarios:  # ahead of where the ego is some time in the clip
        middle = ego.travelled(int(rng.uniform(0.2, 1.0) * (num_frames - 1))) + rng.uniform(20, 45)
        width = rng.uniform(8.0, 12.0)
        b.cross = (middle - width / 2, middle + width / 2)
    road = b.road()
    if "crossing" in scenarios:
        s0 = ego.travelled((num_frames - 1) // 2) + rng.uniform(12.0, 30.0)
        b.crosswalk = road.crosswalk = (s0, s0 + rng.uniform(3.0, 5.0))
    b.roadside()
    movers = traffic.place_movers(b, duration, ego.motion(float(b.lateral)), scenarios)
    light = b.light()
    sun = light.pop("sun")  # (camera frame at frame 0's pitch, heading)
    R0 = rotation_x(ego.pitch0) @ rotation_y_matrix(ego.heading)
    path = ego.path
    return Drive(
        ego=ego,
        calib=calib,
        image_size=size,
        lateral=float(b.lateral),
        road=road,
        world_solids=b.road_solids if path.straight else [path.bend(s) for s in b.road_solids],
        movers=movers,
        sun_world=R0.T @ sun,
        light=light,
    )


@functools.lru_cache(maxsize=2)
def cached_drive(seed, sequence, num_frames, image_size, counts_items, rig_set, mix) -> Drive:
    """:func:`make_drive` kept for the next frames of the same sequence (in a worker)."""
    return make_drive(seed, sequence, num_frames, image_size, dict(counts_items), rig_set, mix)


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
        drive.pose(k),
    )
