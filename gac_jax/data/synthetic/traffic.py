"""Road users of a driving clip: KITTI boxes moving along the road, and the clip's scenarios.

Everything is in the road frame ``(t, y, s)`` of :mod:`scene` (t lateral, s along the
road, metres, bent by the clip's :class:`road_path.RoadPath`); clip time runs from 0 s at
frame 0. Each road user follows a :class:`road_path.Motion`. Where a road user starts
comes from :meth:`scene.SceneBuilder.propose`, as for a single frame; how it moves from its
kind: cars in a lane drive in the lane's direction at the lane's speed (6-14 m/s), cyclists
at the lanes' outer edge (3-6 m/s), pedestrians (and cyclists on the sidewalk) walk along
it (0.8-1.6 m/s; 2-4 m/s) or across the zebra crossing up to the far kerb; parked cars,
cars at a random heading and standing pedestrians stand still.

A sequence's *scenarios* (:data:`SCENARIOS`, drawn per sequence from a mix) add:

* ``curve``: the road curves (radius 100-350 m, one or two bends); ``ego_speed``: the ego
  vehicle accelerates, brakes, sometimes stops (:mod:`drive`);
* ``lane_change``: cars change lanes (a smooth 3-5 s manoeuvre); ``brake``: cars brake
  (sometimes to a stop) or accelerate at 1.5-3.5 m/s^2;
* ``oncoming``: a two-way road with cars coming the other way;
* ``intersection``: a cross street the ego sees or drives through, cars crossing it;
* ``occlusion``: a road user passing behind another (same bearing from the camera
  mid-clip, different speeds: hidden for some frames, then visible again);
* ``crossing``: a zebra crossing ahead with pedestrians crossing; ``parked``: a parking
  lane with a row of parked cars.

Road users fill the road around the ego vehicle's path with the density a single frame has
(``counts`` per 66 m of depth); a road user is kept only if it is within the viewing range
(4-95 m ahead of the ego) at some time of the clip, where its footprint stays clear of the
roadside's obstacles, the ego vehicle and the road users already placed throughout the clip
(checked every 0.25 s; up to 10 places are tried).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes
from gac_jax.data.synthetic.road_path import Motion, SpeedProfile
from gac_jax.data.synthetic.roadside import Footprint
from gac_jax.data.synthetic.scene import DEPTH_RANGE, FAR_RANGE

LANE_SPEED = (6.0, 14.0)  # m/s
CYCLE_SPEED = (3.0, 6.0)
WALK_SPEED = {"Pedestrian": (0.8, 1.6), "Cyclist": (2.0, 4.0)}
MAX_SPEED = {"Car": 17.0, "Cyclist": CYCLE_SPEED[1], "Pedestrian": WALK_SPEED["Pedestrian"][1]}
CHECK_STEP = 0.25  # seconds between the clearance checks
TRIES = 10  # places tried for a road user whose first place is not clear
EGO_HALF = (3.0, 1.0)  # half length and width of the ego vehicle's footprint (m)
EGO_OFFSET = -1.0  # its centre relative to the camera along the road (m)
SCENARIOS = (
    "curve",
    "ego_speed",
    "lane_change",
    "brake",
    "oncoming",
    "intersection",
    "occlusion",
    "crossing",
    "parked",
)
# share of the sequences that have each scenario (drawn independently per sequence)
DEFAULT_MIX = {
    "curve": 0.5,
    "ego_speed": 0.6,
    "lane_change": 0.5,
    "brake": 0.5,
    "oncoming": 0.6,
    "intersection": 0.35,
    "occlusion": 0.6,
    "crossing": 0.4,
    "parked": 0.5,
}


@dataclasses.dataclass
class Mover:
    """A road user of a clip.

    Attributes:
      track_id: its id in the clip's labels (the order of placement).
      type: ``Car``, ``Pedestrian`` or ``Cyclist``.
      dimensions: (3,) KITTI ``h, w, l`` (m).
      parts: its convex parts in its box frame (bottom-face centre at the origin).
      motion: its road-frame motion ``(t, s, psi)`` over time.
      support: road-frame ``y`` of the surface it stands on.
      role: what it does (``lane``, ``lane_change``, ``brake``, ``oncoming``,
        ``cross_traffic``, ``occluder``, ``occluded``, ``crossing``, ``parked``,
        ``cycle_lane``, ``sidewalk``, ``stray``, ``standing``).
    """

    track_id: int
    type: str
    dimensions: np.ndarray
    parts: list[shapes.Solid]
    motion: Motion
    support: float
    role: str

    def position(self, time: float) -> tuple[float, float]:
        """Road position ``(t, s)`` at ``time`` seconds."""
        t, s, _ = self.motion.at(time)
        return float(t), float(s)


@dataclasses.dataclass
class _Track:
    """A footprint's road positions at the check times (for the clearance checks)."""

    t: np.ndarray
    s: np.ndarray
    psi: np.ndarray
    half_l: float
    half_w: float
    margin: float

    def at(self, i: int) -> Footprint:
        return Footprint(self.t[i], self.s[i], self.half_l, self.half_w, self.psi[i])


def _clear(track: _Track, others: list[_Track]) -> bool:
    for other in others:
        reach = np.hypot(track.half_l, track.half_w) + np.hypot(other.half_l, other.half_w)
        reach += track.margin + other.margin
        near = np.hypot(track.t - other.t, track.s - other.s) <= reach
        margin = max(track.margin, other.margin)
        if any(track.at(i).overlaps(other.at(i), margin) for i in np.flatnonzero(near)):
            return False
    return True


def _constant(speed: float) -> SpeedProfile:
    return SpeedProfile((0.0,), (float(speed),))


def _speed_change(rng, v0: float, duration: float) -> SpeedProfile:
    """Brakes (sometimes to a stop) or accelerates once, at 1.5-3.5 m/s^2."""
    start = rng.uniform(0.0, max(duration * 0.6, 0.1))
    if rng.random() < 0.6:
        v1 = 0.0 if rng.random() < 0.3 else v0 * rng.uniform(0.2, 0.6)
    else:
        v1 = min(v0 + rng.uniform(2.0, 5.0), MAX_SPEED["Car"])
    ramp = max(abs(v1 - v0) / rng.uniform(1.5, 3.5), 0.1)
    return SpeedProfile((0.0, start, start + ramp), (v0, v0, v1))


class _Placer:
    """Places road users one by one, each clear of everything placed before."""

    def __init__(self, b, duration: float, ego_motion: Motion):
        self.b = b
        self.times = np.linspace(0.0, duration, int(np.ceil(duration / CHECK_STEP)) + 1)
        self.duration = duration
        t, s, psi = ego_motion.at(self.times)
        self.ego_s = s - EGO_OFFSET
        self.tracks = [_Track(t, s, psi, *EGO_HALF, 0.0)]
        for o in b.obstacles:
            full = np.full(len(self.times), 1.0)
            self.tracks.append(_Track(o.t * full, o.s * full, o.psi * full, o.half_l, o.half_w, 0))
        self.movers: list[Mover] = []

    def ego_ahead(self, time: float) -> float:
        """Road ``s`` of the camera at ``time``."""
        return float(np.interp(time, self.times, self.ego_s))

    def add(self, cls, dims, motion: Motion, support: float, role: str) -> str:
        """``placed``, ``unseen`` (never 4-95 m ahead of the camera) or ``blocked``."""
        t, s, psi = motion.at(self.times)
        ahead = s - self.ego_s
        if not ((ahead >= DEPTH_RANGE[0]) & (ahead <= FAR_RANGE[1])).any():
            return "unseen"
        track = _Track(t, s, psi, dims[2] / 2, dims[1] / 2, 0.3 if cls == "Car" else 0.15)
        if not _clear(track, self.tracks):
            return "blocked"
        self.tracks.append(track)
        parts = self.b.object_parts(cls, dims)
        self.movers.append(Mover(len(self.movers), cls, dims, parts, motion, support, role))
        return "placed"

    def force(self, cls: str, propose, count: int) -> None:
        """Places ``count`` road users from ``propose() -> (motion, support, role)``."""
        for _ in range(count):
            for _ in range(TRIES):
                dims = self.b.sample_dimensions(cls)
                if self.add(cls, dims, *propose()) == "placed":
                    break


def _lane_motion(b, rng, scenarios, t, s, psi, lane_speed, duration) -> tuple[Motion, str]:
    centre, lane_psi = min(b.lanes, key=lambda lane: abs(lane[0] - t))
    direction = 1.0 if lane_psi == 0.0 else -1.0
    psi = lane_psi + np.deg2rad(rng.normal(0.0, 0.5))
    profile, role = _constant(lane_speed[centre]), "lane" if direction > 0 else "oncoming"
    change = None
    if "brake" in scenarios and rng.random() < 0.35:
        profile, role = _speed_change(rng, lane_speed[centre], duration), "brake"
    elif "lane_change" in scenarios and rng.random() < 0.35:
        others = [c for c, p in b.lanes if p == lane_psi and abs(abs(c - centre) - b.lane_w) < 0.1]
        if others and duration > 3.0:
            span = rng.uniform(3.0, 5.0)
            start = rng.uniform(0.0, max(duration - span, 0.0))
            change = (others[rng.integers(len(others))] - centre, start, span)
            role = "lane_change"
    return Motion(t, s, psi, direction, profile, lane_change=change), role


def _motion(b, rng, scenarios, cls, t, s, psi, kind, lane_speed, duration):
    """``(motion, role)`` of a road user of ``kind`` proposed at ``(t, s)``."""
    if kind == "lane":
        return _lane_motion(b, rng, scenarios, t, s, psi, lane_speed, duration)
    if kind in ("cycle_lane", "sidewalk"):
        direction = 1.0 if np.cos(psi) > 0 else -1.0
        spread = 1.0 if kind == "cycle_lane" else 3.0
        psi = (0.0 if direction > 0 else np.pi) + np.deg2rad(rng.normal(0.0, spread))
        speed = rng.uniform(*(CYCLE_SPEED if kind == "cycle_lane" else WALK_SPEED[cls]))
        return Motion(t, s, psi, direction, _constant(speed)), kind
    if kind == "crossing":  # towards the far kerb, then waiting there
        side = 1 if np.sin(psi) > 0 else -1
        lo, hi = b.edges[-1] + 0.4, b.edges[1] - 0.4
        speed = rng.uniform(*WALK_SPEED["Pedestrian"])
        return Motion(t, s, psi, vt=side * speed, t_range=(lo, hi)), kind
    return Motion(t, s, psi), kind  # parked, stray, standing


def _forced(p: _Placer, rng, scenarios: frozenset, lane_speed: dict) -> None:
    """The road users that make each of the sequence's scenarios happen in view."""
    b, duration = p.b, p.duration

    def ahead_at(time, lo, hi):
        return p.ego_ahead(time) + rng.uniform(lo, hi)

    def lane_car(direction, role):
        lanes = [(c, q) for c, q in b.lanes if (q == 0.0) == (direction > 0)]
        centre, lane_psi = lanes[rng.integers(len(lanes))]
        when = rng.uniform(0.2, 0.8) * duration
        motion, _ = _lane_motion(b, rng, scenarios, centre, 0.0, lane_psi, lane_speed, duration)
        if role == "brake":
            profile = _speed_change(rng, lane_speed[centre], duration)
            motion = dataclasses.replace(motion, profile=profile, lane_change=None)
        elif role == "lane_change":
            others = [c for c, q in lanes if abs(abs(c - centre) - b.lane_w) < 0.1]
            if others and duration > 3.0:
                span = rng.uniform(3.0, 5.0)
                start = rng.uniform(0.0, max(duration - span, 0.0))
                change = (others[rng.integers(len(others))] - centre, start, span)
                motion = dataclasses.replace(motion, lane_change=change)
        s_then = ahead_at(when, 15.0, 50.0)
        s0 = s_then - direction * float(motion.profile.distance(when))
        return dataclasses.replace(motion, s0=s0), b.h, role

    if "occlusion" in scenarios:
        for _ in range(int(rng.integers(1, 3))):
            _occlusion_pair(p, rng, lane_speed)
    if "oncoming" in scenarios and any(q != 0.0 for _, q in b.lanes):
        p.force("Car", lambda: lane_car(-1.0, "oncoming"), int(rng.integers(1, 3)))
    if "brake" in scenarios:
        p.force("Car", lambda: lane_car(1.0, "brake"), 1)
    if "lane_change" in scenarios:
        p.force("Car", lambda: lane_car(1.0, "lane_change"), 1)
    if "intersection" in scenarios and b.cross is not None:
        c0, c1 = b.cross

        def cross_car():
            side = 1.0 if rng.random() < 0.5 else -1.0  # moving towards +t or -t
            s = (c0 + c1) / 2 - side * (c1 - c0) / 4  # keep right
            speed, when = rng.uniform(5.0, 11.0), rng.uniform(0.0, duration)
            motion = Motion(-side * speed * when, s, side * np.pi / 2, vt=side * speed)
            return motion, b.h, "cross_traffic"

        p.force("Car", cross_car, int(rng.integers(1, 4)))
    if "crossing" in scenarios and b.crosswalk is not None:
        s0, s1 = b.crosswalk
        lo, hi = b.edges[-1] + 0.4, b.edges[1] - 0.4

        def pedestrian():
            side = 1.0 if rng.random() < 0.5 else -1.0
            speed, delay = rng.uniform(*WALK_SPEED["Pedestrian"]), rng.uniform(0, duration / 2)
            start = lo if side > 0 else hi
            psi = side * np.pi / 2 + np.deg2rad(rng.normal(0.0, 5.0))
            motion = Motion(
                start - side * speed * delay,
                rng.uniform(s0 + 0.4, s1 - 0.4),
                psi,
                vt=side * speed,
                t_range=(lo, hi),
            )
            return motion, b.h, "crossing"

        p.force("Pedestrian", pedestrian, int(rng.integers(1, 4)))
    if "parked" in scenarios and 1 in b.parking:

        def parked():
            s = rng.uniform(p.ego_ahead(0.0) + 5.0, p.ego_ahead(duration) + 60.0)
            psi = np.deg2rad(rng.normal(0.0, 2.0)) + (np.pi if rng.random() < 0.2 else 0.0)
            return Motion(b.parking[1] + rng.normal(0.0, 0.12), s, psi), b.h, "parked"

        p.force("Car", parked, int(rng.integers(3, 7)))


def _occlusion_pair(p: _Placer, rng, lane_speed: dict) -> None:
    """A car (the occluder) and, farther out on the same side, a car or pedestrian that has
    the same bearing from the camera mid-clip and another speed: it passes behind."""
    b, duration = p.b, p.duration
    te = b.lateral
    when = rng.uniform(0.3, 0.7) * duration
    lanes = [(c, q) for c, q in b.lanes if abs(c - te) > 1.5]
    for _ in range(TRIES):
        if not lanes:
            return
        tb, qb = lanes[rng.integers(len(lanes))]
        side = np.sign(tb - te)
        beyond = [("Car", c, q) for c, q in b.lanes if side * (c - tb) > 2.0]
        if side in b.parking:
            beyond.append(("Car", b.parking[side], None))
        if b.sidewalk.get(side, 0.0) > 0:
            beyond.append(("Pedestrian", b.edges[side] + side * 1.0, None))
        if not beyond:
            return
        cls, ta, qa = beyond[rng.integers(len(beyond))]
        vb = lane_speed[tb]
        db = 1.0 if qb == 0.0 else -1.0
        rel_b = rng.uniform(10.0, 25.0)
        rel_a = rel_b * (ta - te) / (tb - te) + rng.uniform(-0.5, 0.5)
        if cls == "Pedestrian":
            da, va, psi_a = (1.0 if rng.random() < 0.5 else -1.0), rng.uniform(0.8, 1.6), 0.0
        elif qa is None:  # parked
            da, va, psi_a = 0.0, 0.0, 0.0
        else:
            da = 1.0 if qa == 0.0 else -1.0
            va = float(np.clip(vb + rng.choice([-1, 1]) * rng.uniform(3.0, 6.0), 2.0, 16.0))
            psi_a = 0.0 if da > 0 else np.pi
        ego_s = p.ego_ahead(when)
        occluder = Motion(tb, ego_s + rel_b - db * vb * when, qb, db, _constant(vb))
        psi_a = psi_a if da >= 0 else np.pi
        hidden = Motion(ta, ego_s + rel_a - da * va * when, psi_a, da, _constant(va))
        dims_b, dims_a = b.sample_dimensions("Car"), b.sample_dimensions(cls)
        if p.add("Car", dims_b, occluder, b.h, "occluder") != "placed":
            continue
        support = b.h if cls == "Car" else b.h - b.kerb[side]
        if p.add(cls, dims_a, hidden, support, "occluded") == "placed":
            return
        p.movers.pop()  # the pair or nothing
        p.tracks.pop()


def place_movers(b, duration: float, ego_motion: Motion, scenarios=frozenset()) -> list[Mover]:
    """Samples the road users of a clip of ``duration`` seconds.

    Args:
      b: a :class:`scene.SceneBuilder` after ``road()`` and ``roadside()`` (its ``rng``,
        ``counts``, lanes, edges, sidewalks, crossing, cross street and static
        ``obstacles`` are used).
      ego_motion: the ego vehicle's road-frame motion (its camera's).
      scenarios: the sequence's scenarios (:data:`SCENARIOS`).
    """
    rng = b.rng
    lane_speed = {centre: rng.uniform(*LANE_SPEED) for centre, _ in b.lanes}
    p = _Placer(b, duration, ego_motion)
    _forced(p, rng, scenarios, lane_speed)
    per_metre = 1.0 / (DEPTH_RANGE[1] - DEPTH_RANGE[0])
    travelled = p.ego_ahead(duration) - p.ego_ahead(0.0)
    for cls in ("Car", "Cyclist", "Pedestrian"):
        if cls not in b.counts:
            continue
        lo, hi = b.counts[cls]
        density = int(rng.integers(lo, hi + 1)) * per_metre
        # start positions (relative to the ego) from which a road user of this class can
        # be in view at some time of the clip
        x_lo = DEPTH_RANGE[0] - duration * MAX_SPEED[cls]
        x_hi = FAR_RANGE[1] + travelled + duration * MAX_SPEED[cls]
        for _ in range(int(rng.poisson(density * (x_hi - x_lo)))):
            for _ in range(TRIES):  # a spot that is not clear is tried again elsewhere
                x0 = rng.uniform(x_lo, x_hi)
                dims = b.sample_dimensions(cls)
                t, s, psi, support, kind = b.propose(cls)
                if kind != "crossing":
                    s = p.ego_ahead(0.0) + x0  # (crossing pedestrians stay at the crossing)
                motion, role = _motion(
                    b, rng, scenarios, cls, t, s, psi, kind, lane_speed, duration
                )
                outcome = p.add(cls, dims, motion, support, role)
                if outcome != "blocked":
                    break  # placed, or never in view: not a road user of this clip
    return p.movers
