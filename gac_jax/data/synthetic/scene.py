"""Random driving scenes: a straight road with lanes, kerbs, buildings, clutter and road users.

Frames used here:

* camera frame: KITTI's rectified reference frame (x right, y down, z forward).
* level frame: the camera frame with the camera's pitch removed (y along gravity).
* road frame ``(t, y, s)``: t lateral (right positive, 0 = road centre line), y
  down, s along the road: ``X_cam = road_rotation @ [t, y, s] + road_translation``.
  The ground is ``y = camera_height`` (the camera sits at ``t = lateral``,
  ``y = 0``, ``s = 0``), i.e. the plane ``ground_normal . X_cam = camera_height``.

Road users are yaw-only KITTI boxes in the camera frame (their bottom-face
centre lies on the road or sidewalk surface); their geometry lies inside the box.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import gardens, roadside, shapes, vehicles
from gac_jax.data.synthetic.road_path import RoadPath
from gac_jax.data.synthetic.roadside import Footprint
from gac_jax.geometry import box2d_from_corners, box3d_corners, rotation_y_matrix, wrap_angle

# KITTI size statistics (mean, std) of (h, w, l) in metres of the classes a frame's counts
# name (vans and trucks: vehicles.SIZES).
CLASS_SIZES = {
    "Car": ((1.53, 0.14), (1.63, 0.10), (3.88, 0.43)),
    "Pedestrian": ((1.76, 0.11), (0.66, 0.14), (0.84, 0.23)),
    "Cyclist": ((1.74, 0.09), (0.60, 0.12), (1.76, 0.18)),
}
DEFAULT_COUNTS = {"Car": (3, 8), "Pedestrian": (0, 4), "Cyclist": (0, 2)}
DEPTH_RANGE = (4.0, 70.0)  # depth of the labelled objects' bottom centres
FAR_RANGE = (72.0, 95.0)  # a few farther cars (labelled DontCare)
PARKED_ROW_SHARE = 0.75  # share of parking lanes with a row of parked cars
PARKED_ROW_END = 75.0  # rows run from beside the camera to this far along the road (m)
PARKED_DEPTH_RANGE = (3.0, 70.0)  # (nearer ones are left out of training: data.min_depth)

PAINTS = np.array(
    [
        [0.85, 0.85, 0.86],
        [0.06, 0.06, 0.07],
        [0.60, 0.62, 0.65],
        [0.33, 0.34, 0.36],
        [0.08, 0.12, 0.30],
        [0.55, 0.06, 0.05],
        [0.15, 0.30, 0.60],
        [0.10, 0.25, 0.15],
        [0.70, 0.62, 0.45],
        [0.80, 0.65, 0.10],
    ]
)
PAINT_WEIGHTS = np.array([0.2, 0.18, 0.18, 0.14, 0.07, 0.08, 0.06, 0.03, 0.04, 0.02])


@dataclasses.dataclass
class Road:
    """The ground plane's painting, in road coordinates (metres).

    Attributes:
      left, right: lateral positions ``t`` of the road edges (left < right).
      lane_centres: lateral positions of the driving lanes' centres.
      markings: (M, 5) painted lines: ``t``, half width, dash period (0 = solid),
        dash length, phase.
      crosswalk: ``(s0, s1)`` extent of a zebra crossing, or None.
      cross: ``(s0, s1)`` extent of a cross street (asphalt to both sides), or None.
      verge_photo: :func:`~gac_jax.data.synthetic.photo_textures.photo_params` of the
        verges' grass, or None (procedural noise).
    """

    left: float
    right: float
    lane_centres: tuple[float, ...]
    markings: np.ndarray
    crosswalk: tuple[float, float] | None
    asphalt: np.ndarray
    verge_left: np.ndarray
    verge_right: np.ndarray
    paint_color: np.ndarray
    paint_strength: float
    cross: tuple[float, float] | None = None
    verge_photo: tuple | None = None  # grass from a photograph on the verges (photo_textures)


@dataclasses.dataclass
class SceneObject:
    """A labelled road user: a KITTI box and the convex parts inside it (camera frame)."""

    type: str
    dimensions: np.ndarray  # (3,) h, w, l
    location: np.ndarray  # (3,) bottom-face centre
    rotation_y: float
    parts: list[shapes.Solid]
    support_y: float  # road-frame y of the surface it stands on (for its shadow)

    def corners(self) -> np.ndarray:
        """(8, 3) corners of the labelled box."""
        return box3d_corners(self.location[None], self.dimensions[None], [self.rotation_y])[0]


@dataclasses.dataclass
class Scene:
    """Everything needed to render one frame from any camera of the rig."""

    camera_height: float
    pitch: float  # radians, positive = camera tilted down
    heading: float  # road direction relative to the camera (radians about y)
    lateral: float  # camera position across the road (t)
    road_rotation: np.ndarray  # (3, 3)
    road_translation: np.ndarray  # (3,)
    road: Road
    background: list[shapes.Solid]
    objects: list[SceneObject]
    sun: np.ndarray  # (3,) unit vector towards the sun, camera frame
    ambient: float
    shadow: float  # darkening of shadowed ground (0 = none)
    sky_top: np.ndarray
    sky_horizon: np.ndarray
    exposure: np.ndarray  # (3,) per-channel gain of the camera
    path: RoadPath | None = None  # a curved road's centre line (None: straight)

    @property
    def ground_normal(self) -> np.ndarray:
        """(3,) unit normal (pointing down) of the ground plane ``n . X = camera_height``."""
        return self.road_rotation[:, 1].copy()

    def to_road(self, points: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) -> road coordinates ``(t, y, s)`` (same dtype).

        With a curved road (``path``) these are world road-frame coordinates ``(x, y, z)``
        (:mod:`road_path`), the same ground plane.
        """
        pts = np.asarray(points)
        R = self.road_rotation.astype(pts.dtype)
        d = [pts[..., i] - pts.dtype.type(self.road_translation[i]) for i in range(3)]
        return np.stack([d[0] * R[0, k] + d[1] * R[1, k] + d[2] * R[2, k] for k in range(3)], -1)


def place_object(cls, dims, local_parts, loc, ry, support) -> SceneObject:
    """A road user whose box-frame parts are turned by ``ry`` and moved to ``loc`` (camera)."""
    R = rotation_y_matrix(ry)
    return SceneObject(cls, dims, loc, ry, [p.transformed(R, loc) for p in local_parts], support)


def rotation_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _normal(rng, mean, std, clip=2.5):
    return mean + std * float(np.clip(rng.standard_normal(), -clip, clip))


class SceneBuilder:
    """Samples one scene; methods add road, roadside and road users in turn."""

    def __init__(self, rng, P2, image_size, counts, pitch, camera_height):
        self.rng = rng
        self.P2 = np.asarray(P2, np.float64)
        self.image_size = image_size
        self.counts = counts
        self.h = 1.65 + rng.uniform(-0.05, 0.05) if camera_height is None else camera_height
        self.pitch = (
            np.deg2rad(np.clip(rng.normal(0.0, 0.5), -1.0, 1.0)) if pitch is None else pitch
        )
        self.heading = np.deg2rad(np.clip(rng.normal(0.0, 3.0), -8.0, 8.0))
        self.level_R = rotation_x(self.pitch)
        self.road_rotation = self.level_R @ rotation_y_matrix(self.heading)
        self.background: list[shapes.Solid] = []
        self.road_solids: list[shapes.Solid] = []  # the background in road coordinates
        self.road_end = roadside.ROAD_END  # how far the roadside is built (s, metres)
        self.objects: list[SceneObject] = []
        self.obstacles: list[Footprint] = []
        # a clip's choices (no effect on the random draws of a single frame)
        self.two_way = False  # no one-way road
        self.min_right_lanes = 1  # lanes in the ego's direction
        self.force_parking = False  # a parking lane on the right
        self.cross: tuple[float, float] | None = None  # a cross street (s0, s1)
        self.piece_length: float | None = None  # long kerbs in pieces (a curved road)
        self.garden_depths: dict[int, float] = {}  # side -> front gardens' depth (gardens.plan)

    # ----------------------------------------------------------------- road
    def road(self):
        rng = self.rng
        lane_w = rng.uniform(3.0, 3.6)
        one_way = rng.random() < 0.2 and not self.two_way
        n_left = 0 if one_way else int(rng.integers(1, 3))
        n_right = int(rng.integers(1, 4)) if one_way else int(rng.integers(1, 3))
        n_right = max(n_right, self.min_right_lanes)
        self.sides = {s: ("urban" if rng.random() < 0.7 else "open") for s in (-1, 1)}
        park = {s: self.sides[s] == "urban" and rng.random() < 0.65 for s in (-1, 1)}
        park[1] = park[1] or self.force_parking
        lanes_left, lanes_right = -n_left * lane_w, n_right * lane_w
        self.lanes = [((i + 0.5) * lane_w, 0.0) for i in range(n_right)]
        self.lanes += [(-(i + 0.5) * lane_w, np.pi) for i in range(n_left)]
        self.lane_w = lane_w
        self.parking = {}
        edges = {}
        for side, lanes_edge in ((-1, lanes_left), (1, lanes_right)):
            if park[side]:
                edges[side] = lanes_edge + side * 2.3
                self.parking[side] = lanes_edge + side * 1.15
            else:
                edges[side] = lanes_edge + side * rng.uniform(0.3, 0.8)
        self.edges = edges
        ego = int(rng.integers(0, n_right))
        self.lateral = (ego + 0.5) * lane_w + rng.uniform(-0.3, 0.3)
        self.road_translation = -self.road_rotation @ np.array([self.lateral, 0.0, 0.0])

        marks = []
        half = rng.uniform(0.05, 0.08)
        if not one_way:
            solid = rng.random() < 0.35
            period = rng.uniform(8.0, 12.0)
            marks.append((0.0, half, 0.0 if solid else period, period / 3, rng.uniform(0, period)))
        period = rng.uniform(8.0, 12.0)
        for i in range(1, n_right):
            marks.append((i * lane_w, half, period, period / 3, rng.uniform(0, period)))
        for i in range(1, n_left):
            marks.append((-i * lane_w, half, period, period / 3, rng.uniform(0, period)))
        for lanes_edge in (lanes_left, lanes_right):
            if rng.random() < 0.8:
                marks.append((lanes_edge, half * 1.5, 0.0, 0.0, 0.0))
        crosswalk = None
        if rng.random() < 0.25:
            s0 = rng.uniform(10.0, 40.0)
            crosswalk = (s0, s0 + rng.uniform(3.0, 5.0))
        grey = rng.uniform(0.28, 0.45)
        verges = {}
        for side in (-1, 1):
            if self.sides[side] == "urban":
                verges[side] = np.array([0.42, 0.40, 0.37]) * rng.uniform(0.8, 1.1)
            elif rng.random() < 0.6:
                verges[side] = np.array([0.22, 0.32, 0.12]) * rng.uniform(0.8, 1.3)
            else:
                verges[side] = np.array([0.45, 0.41, 0.30]) * rng.uniform(0.8, 1.2)
        self.crosswalk = crosswalk
        return Road(
            left=edges[-1],
            right=edges[1],
            lane_centres=tuple(c for c, _ in self.lanes),
            markings=np.array(marks, dtype=np.float64).reshape(-1, 5),
            crosswalk=crosswalk,
            asphalt=(grey * np.array([1.0, 1.0, 1.02]) * rng.uniform(0.95, 1.05, 3)).astype(
                np.float32
            ),
            verge_left=verges[-1].astype(np.float32),
            verge_right=verges[1].astype(np.float32),
            paint_color=np.array([0.9, 0.9, 0.87], np.float32),
            paint_strength=float(rng.uniform(0.6, 0.95)),
            cross=self.cross,
        )

    def add_road_solid(self, solid: shapes.Solid):
        self.road_solids.append(solid)
        self.background.append(solid.transformed(self.road_rotation, self.road_translation))

    def roadside(self):
        roadside.build(self)

    # ----------------------------------------------------------- road users
    def road_users(self):
        rng = self.rng
        ego = Footprint(self.lateral, -1.0, 3.0, 1.0, 0.0)
        self.obstacles.append(ego)
        if "Car" in self.counts and self.counts["Car"][1] > 0:
            for side in sorted(self.parking):
                if rng.random() < PARKED_ROW_SHARE:
                    self._parked_row(side)
        for cls in ("Car", "Cyclist", "Pedestrian"):
            if cls not in self.counts:
                continue
            lo, hi = self.counts[cls]
            for _ in range(int(rng.integers(lo, hi + 1))):
                self._place(cls, DEPTH_RANGE)
        if "Car" in self.counts and self.counts["Car"][1] > 0:
            for _ in range(int(rng.integers(0, 3))):
                self._place("Car", FAR_RANGE)

    def large_vehicles(self, rng: np.random.Generator, share: float) -> None:
        """In a ``share`` of the calls, 1-3 vans and trucks (:mod:`vehicles`) parked or in the
        lanes like cars, wherever there is room; drawn from ``rng`` alone, so the rest of the
        scene is the same with or without them."""
        if share <= 0.0 or rng.random() >= share:
            return
        scene_rng, self.rng = self.rng, rng
        try:
            for _ in range(int(rng.integers(vehicles.COUNT[0], vehicles.COUNT[1] + 1))):
                self._place("Van" if rng.random() < vehicles.VAN_SHARE else "Truck", DEPTH_RANGE)
        finally:
            self.rng = scene_rng

    def _parked_row(self, side: int) -> None:
        """A row of cars parked nose to tail along the parking lane on ``side``, from beside
        the camera (cut by the image border) to far ahead, with a few empty spaces."""
        rng = self.rng
        psi0 = 0.0 if rng.random() < 0.8 else np.pi  # most park in the lane's direction
        if side < 0 and any(p == np.pi for _, p in self.lanes):
            psi0 = np.pi - psi0
        s = rng.uniform(-4.0, 4.0)
        while s < PARKED_ROW_END:
            dims = self.sample_dimensions("Car")
            if rng.random() < 0.15:  # an empty space
                s += rng.uniform(3.0, 10.0)
                continue
            t = self.parking[side] + rng.normal(0.0, 0.12)
            psi = psi0 + np.deg2rad(rng.normal(0.0, 2.0))
            centre = s + dims[2] / 2
            self._try_at("Car", dims, t, centre, psi, self.h, PARKED_DEPTH_RANGE)
            s += dims[2] + rng.uniform(0.4, 2.5)

    def _try_at(self, cls, dims, t, s, psi, support, depth_range) -> bool:
        """Adds a road user at road position ``(t, s)`` and heading ``psi`` if it is free,
        within ``depth_range`` and at least partly in the image."""
        foot = Footprint(t, s, dims[2] / 2, dims[1] / 2, psi)
        margin = 0.15 if cls in ("Pedestrian", "Cyclist") else 0.3
        if any(foot.overlaps(o, margin) for o in self.obstacles):
            return False
        loc = np.round(self.road_rotation @ np.array([t - self.lateral, support, s]), 2)
        if not depth_range[0] <= loc[2] <= depth_range[1]:
            return False
        ry = float(np.round(wrap_angle(self.heading + psi - np.pi / 2), 2))
        box = box2d_from_corners(box3d_corners(loc[None], dims[None], [ry]), self.P2)[0]
        height, width = self.image_size
        if not (box[2] > 0 and box[0] < width - 1 and box[3] > 0 and box[1] < height - 1):
            return False  # entirely outside the image
        self.obstacles.append(foot)
        self.objects.append(self._make(cls, dims, loc, ry, support))
        return True

    def propose(self, cls):
        """A position ``(t, s)``, heading ``psi`` (road frame), support height and kind for ``cls``.

        ``kind`` says where it is: ``parked``, ``lane`` (a car in its lane), ``stray`` (a car
        at a random heading), ``cycle_lane``, ``crossing`` (on the zebra crossing),
        ``sidewalk`` (walking along the road) or ``standing`` (at a random heading).
        """
        rng, h = self.rng, self.h
        s = rng.uniform(2.0, 100.0)
        if cls == "Car":
            if self.parking and rng.random() < 0.4:
                side = list(self.parking)[rng.integers(len(self.parking))]
                t = self.parking[side] + rng.normal(0.0, 0.12)
                psi = rng.choice([0.0, np.pi]) + np.deg2rad(rng.normal(0.0, 2.0))
                kind = "parked"
            else:
                centre, psi = self.lanes[rng.integers(len(self.lanes))]
                t = centre + np.clip(rng.normal(0.0, 0.25), -0.5, 0.5)
                psi += np.deg2rad(rng.normal(0.0, 3.0))
                kind = "lane"
                if rng.random() < 0.08:
                    psi, kind = rng.uniform(-np.pi, np.pi), "stray"
            return t, s, psi, h, kind
        if cls == "Cyclist":
            if rng.random() < 0.8:
                side = 1 if rng.random() < 0.7 or not any(p == np.pi for _, p in self.lanes) else -1
                lanes = [c for c, p in self.lanes if (p == 0.0) == (side == 1)]
                outer = max(lanes, key=abs) + side * (self.lane_w / 2 - 0.7)
                psi = (0.0 if side == 1 else np.pi) + np.deg2rad(rng.normal(0.0, 4.0))
                return outer + rng.normal(0.0, 0.15), s, psi, h, "cycle_lane"
            cls = "Pedestrian"  # on the sidewalk, like a pedestrian
        # pedestrians (and cyclists on the sidewalk)
        if self.crosswalk is not None and rng.random() < 0.3:
            s0, s1 = self.crosswalk
            t = rng.uniform(self.edges[-1] + 0.5, self.edges[1] - 0.5)
            psi = rng.choice([-np.pi / 2, np.pi / 2]) + np.deg2rad(rng.normal(0.0, 10.0))
            return t, rng.uniform(s0 + 0.4, s1 - 0.4), psi, h, "crossing"
        side = -1 if rng.random() < 0.5 else 1
        edge = self.edges[side]
        if self.sidewalk[side] > 0:
            t = edge + side * rng.uniform(0.5, self.sidewalk[side] - 0.4)
            support = h - self.kerb[side]
        else:
            t = edge + side * rng.uniform(0.5, 2.0)
            support = h
        psi = rng.choice([0.0, np.pi]) + np.deg2rad(rng.normal(0.0, 15.0))
        kind = "sidewalk"
        if rng.random() < 0.25:
            psi, kind = rng.uniform(-np.pi, np.pi), "standing"
        return t, s, psi, support, kind

    def sample_dimensions(self, cls) -> np.ndarray:
        """(3,) ``h, w, l`` of a road user of class ``cls`` (KITTI's statistics, cm steps)."""
        sizes = vehicles.SIZES[cls] if cls in vehicles.SIZES else CLASS_SIZES[cls]
        return np.round(np.array([_normal(self.rng, m, sd) for m, sd in sizes]), 2)

    def _place(self, cls, depth_range, tries: int = 30):
        for _ in range(tries):
            dims = self.sample_dimensions(cls)
            t, s, psi, support, _ = self.propose("Car" if cls in vehicles.SIZES else cls)
            if self._try_at(cls, dims, t, s, psi, support, depth_range):
                return

    def _make(self, cls, dims, loc, ry, support):
        return place_object(cls, dims, self.object_parts(cls, dims), loc, ry, support)

    def object_parts(self, cls, dims) -> list[shapes.Solid]:
        """The part models of a road user of size ``dims`` (h, w, l) in its box frame."""
        rng = self.rng
        h, w, l = dims
        if cls == "Car" or cls in vehicles.SIZES:
            paint = PAINTS[rng.choice(len(PAINTS), p=PAINT_WEIGHTS)] * rng.uniform(0.9, 1.1)
            paint = np.clip(paint, 0, 1)
            if cls == "Car":
                return shapes.car_parts(h, w, l, paint, rng)
            return vehicles.parts(cls, dims, paint, rng)
        if cls == "Pedestrian":
            return shapes.pedestrian_parts(h, w, l, rng)
        return shapes.cyclist_parts(h, w, l, rng)

    # --------------------------------------------------------------- light
    def light(self) -> dict:
        rng = self.rng
        if rng.random() < 0.7:  # sunny
            el, az = np.deg2rad(rng.uniform(25.0, 60.0)), rng.uniform(-np.pi, np.pi)
            ambient, shadow = rng.uniform(0.35, 0.5), rng.uniform(0.35, 0.55)
            top = np.array([0.30, 0.50, 0.85]) * rng.uniform(0.85, 1.1)
            horizon = np.array([0.80, 0.87, 0.95]) * rng.uniform(0.95, 1.05)
        else:  # overcast
            el, az = np.deg2rad(80.0), 0.0
            ambient, shadow = rng.uniform(0.7, 0.85), rng.uniform(0.15, 0.3)
            top = np.array([0.70, 0.72, 0.76]) * rng.uniform(0.85, 1.05)
            horizon = np.array([0.86, 0.87, 0.89]) * rng.uniform(0.95, 1.05)
        sun = self.level_R @ np.array(
            [np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)]
        )
        exposure = rng.uniform(0.85, 1.15) * rng.uniform(0.95, 1.05, 3)
        return dict(
            sun=sun,
            ambient=float(ambient),
            shadow=float(shadow),
            sky_top=np.clip(top, 0, 1).astype(np.float32),
            sky_horizon=np.clip(horizon, 0, 1).astype(np.float32),
            exposure=exposure.astype(np.float32),
        )


def sample_scene(
    rng: np.random.Generator,
    P2: np.ndarray,
    image_size: tuple[int, int],
    counts: dict[str, tuple[int, int]] | None = None,
    pitch: float | None = None,
    camera_height: float | None = None,
    large_vehicles: float = 0.0,
    vehicle_rng: np.random.Generator | None = None,
    gardens_share: float = 0.0,
    garden_rng: np.random.Generator | None = None,
) -> Scene:
    """Samples a random driving scene seen by the camera ``P2`` (images of size (H, W)).

    Args:
      counts: class -> (min, max) number of road users placed (uniform); the
        default is :data:`DEFAULT_COUNTS`. A car that finds no free spot is skipped.
      pitch, camera_height: fix the camera pose (radians, metres) instead of
        sampling it (pitch ~ N(0, 0.5 deg) clipped to +-1 deg, height 1.65 +- 0.05 m).
      large_vehicles: probability that vans and trucks join the road users, drawn from
        ``vehicle_rng`` (:meth:`SceneBuilder.large_vehicles`; 0 = never).
      gardens_share: probability that an urban roadside has front gardens, drawn from
        ``garden_rng`` (:mod:`gardens`; 0 = never).
    """
    b = SceneBuilder(
        rng, P2, image_size, DEFAULT_COUNTS if counts is None else counts, pitch, camera_height
    )
    road = b.road()
    if gardens_share > 0.0:
        b.garden_depths = gardens.plan(garden_rng, gardens_share, b.sides)
    b.roadside()
    if any(b.garden_depths.values()):
        gardens.build(b, garden_rng)
    b.road_users()
    if large_vehicles > 0.0:
        b.large_vehicles(vehicle_rng, large_vehicles)
    return Scene(
        camera_height=float(b.h),
        pitch=float(b.pitch),
        heading=float(b.heading),
        lateral=float(b.lateral),
        road_rotation=b.road_rotation,
        road_translation=b.road_translation,
        road=road,
        background=b.background,
        objects=b.objects,
        **b.light(),
    )
