"""Road users of a driving clip: KITTI boxes that move along the road at their own speeds.

Everything is in the road frame ``(t, y, s)`` of :mod:`scene` (t lateral, s along the
road, metres); clip time runs from 0 s at frame 0. Where a road user starts comes from
:meth:`scene.SceneBuilder.propose`, as for a single frame; how it moves from its kind:

* cars in a lane drive in the lane's direction at the lane's speed (6-14 m/s; every car
  of a lane has the same speed, so none runs into another); parked cars and cars at a
  random heading stand still;
* cyclists on the road ride at the lanes' outer edge at 3-6 m/s in the lane direction;
* pedestrians (and cyclists on the sidewalk) walk along it at 0.8-1.6 m/s (2-4 m/s for
  cyclists), walk across the zebra crossing (slowly enough to stay on the road for the
  whole clip) or stand.

Motion is straight and at constant velocity. Road users fill the road around the ego
vehicle's path with the density a single frame has (``counts`` per 66 m of depth), and a
road user is kept only if it is within the viewing range (4-95 m ahead of the ego) at
some time of the clip; it is placed where its footprint stays clear of the roadside's
obstacles, the ego vehicle and the road users already placed throughout the clip (checked
every 0.25 s; up to 10 places are tried, as a single frame tries 30).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes
from gac_jax.data.synthetic.roadside import Footprint
from gac_jax.data.synthetic.scene import DEPTH_RANGE, FAR_RANGE

LANE_SPEED = (6.0, 14.0)  # m/s
CYCLE_SPEED = (3.0, 6.0)
WALK_SPEED = {"Pedestrian": (0.8, 1.6), "Cyclist": (2.0, 4.0)}
MAX_SPEED = {
    "Car": LANE_SPEED[1],
    "Cyclist": CYCLE_SPEED[1],
    "Pedestrian": WALK_SPEED["Pedestrian"][1],
}
CHECK_STEP = 0.25  # seconds between the clearance checks
TRIES = 10  # places tried for a road user whose first place is not clear
EGO_HALF = (3.0, 1.0)  # half length and width of the ego vehicle's footprint (m)
EGO_OFFSET = -1.0  # its centre relative to the camera along the road (m)


@dataclasses.dataclass
class Mover:
    """A road user of a clip.

    Attributes:
      track_id: its id in the clip's labels (the order of placement).
      type: ``Car``, ``Pedestrian`` or ``Cyclist``.
      dimensions: (3,) KITTI ``h, w, l`` (m).
      parts: its convex parts in its box frame (bottom-face centre at the origin).
      t0, s0: road position of the box centre at time 0 (m).
      vt, vs: road velocity (m/s).
      psi: heading in the road frame (0 = along +s, pi/2 = along +t).
      support: road-frame ``y`` of the surface it stands on.
    """

    track_id: int
    type: str
    dimensions: np.ndarray
    parts: list[shapes.Solid]
    t0: float
    s0: float
    vt: float
    vs: float
    psi: float
    support: float

    def position(self, time: float) -> tuple[float, float]:
        """Road position ``(t, s)`` at ``time`` seconds."""
        return self.t0 + self.vt * time, self.s0 + self.vs * time


@dataclasses.dataclass(frozen=True)
class _Track:
    """A footprint moving at constant velocity (for the clearance checks)."""

    t0: float
    s0: float
    vt: float
    vs: float
    half_l: float
    half_w: float
    psi: float
    margin: float

    def at(self, time: float) -> Footprint:
        return Footprint(
            self.t0 + self.vt * time, self.s0 + self.vs * time, self.half_l, self.half_w, self.psi
        )

    def may_meet(self, other: _Track, duration: float) -> bool:
        """False when the bounding circles stay apart for the whole clip (closed form)."""
        reach = np.hypot(self.half_l, self.half_w) + np.hypot(other.half_l, other.half_w)
        reach += self.margin + other.margin
        d = np.array([other.t0 - self.t0, other.s0 - self.s0])
        v = np.array([other.vt - self.vt, other.vs - self.vs])
        vv = float(v @ v)
        tmin = 0.0 if vv == 0.0 else float(np.clip(-(d @ v) / vv, 0.0, duration))
        return float(np.hypot(*(d + v * tmin))) <= reach


def _clear(track: _Track, others: list[_Track], times: np.ndarray, duration: float) -> bool:
    for other in others:
        if not track.may_meet(other, duration):
            continue
        margin = max(track.margin, other.margin)
        if any(track.at(tm).overlaps(other.at(tm), margin) for tm in times):
            return False
    return True


def _motion(b, cls: str, t: float, psi: float, kind: str, lane_speed: dict, duration: float):
    """``(vt, vs, psi)`` of a road user of ``kind`` proposed at lateral position ``t``."""
    rng = b.rng
    if kind == "lane":
        centre, lane_psi = min(b.lanes, key=lambda lane: abs(lane[0] - t))
        direction = 1.0 if lane_psi == 0.0 else -1.0
        psi = lane_psi + np.deg2rad(rng.normal(0.0, 0.5))
        return 0.0, direction * lane_speed[centre], psi
    if kind == "cycle_lane":
        direction = 1.0 if np.cos(psi) > 0 else -1.0
        psi = (0.0 if direction > 0 else np.pi) + np.deg2rad(rng.normal(0.0, 1.0))
        return 0.0, direction * rng.uniform(*CYCLE_SPEED), psi
    if kind == "sidewalk":
        direction = 1.0 if np.cos(psi) > 0 else -1.0
        psi = (0.0 if direction > 0 else np.pi) + np.deg2rad(rng.normal(0.0, 3.0))
        return 0.0, direction * rng.uniform(*WALK_SPEED[cls]), psi
    if kind == "crossing":  # towards the far kerb, slowly enough to stay on the road
        side = 1 if np.sin(psi) > 0 else -1
        room = max(0.0, side * (b.edges[side] - side * 0.5 - t))
        speed = min(rng.uniform(*WALK_SPEED["Pedestrian"]), room / max(duration, 1e-6))
        return side * speed, 0.0, psi
    return 0.0, 0.0, psi  # parked, stray, standing


def place_movers(b, duration: float, ego_speed: float) -> list[Mover]:
    """Samples the road users of a clip of ``duration`` seconds (ego at ``ego_speed`` m/s).

    Args:
      b: a :class:`scene.SceneBuilder` after ``road()`` and ``roadside()`` (its ``rng``,
        ``counts``, lanes, edges, sidewalks, crossing and static ``obstacles`` are used).
    """
    rng = b.rng
    times = np.linspace(0.0, duration, int(np.ceil(duration / CHECK_STEP)) + 1)
    lane_speed = {centre: rng.uniform(*LANE_SPEED) for centre, _ in b.lanes}
    ego = _Track(b.lateral, EGO_OFFSET, 0.0, ego_speed, *EGO_HALF, 0.0, 0.0)
    statics = [_Track(o.t, o.s, 0.0, 0.0, o.half_l, o.half_w, o.psi, 0.0) for o in b.obstacles]
    placed: list[_Track] = []
    movers: list[Mover] = []
    view_lo, view_hi = DEPTH_RANGE[0], FAR_RANGE[1]
    per_metre = 1.0 / (DEPTH_RANGE[1] - DEPTH_RANGE[0])
    for cls in ("Car", "Cyclist", "Pedestrian"):
        if cls not in b.counts:
            continue
        lo, hi = b.counts[cls]
        density = int(rng.integers(lo, hi + 1)) * per_metre
        # the start positions (relative to the ego) from which a road user of this class can
        # be within [view_lo, view_hi] at some time of the clip
        x_lo = view_lo - duration * max(0.0, MAX_SPEED[cls] - ego_speed)
        x_hi = view_hi + duration * (ego_speed + MAX_SPEED[cls])
        for _ in range(int(rng.poisson(density * (x_hi - x_lo)))):
            for _ in range(TRIES):  # a spot that is not clear is tried again elsewhere
                x0 = rng.uniform(x_lo, x_hi)
                dims = b.sample_dimensions(cls)
                t, s, psi, support, kind = b.propose(cls)
                if kind != "crossing":
                    s = x0  # (crossing pedestrians stay at the zebra crossing)
                vt, vs, psi = _motion(b, cls, t, psi, kind, lane_speed, duration)
                ahead = (s, s + (vs - ego_speed) * duration)  # relative position, start and end
                if max(ahead) < view_lo or min(ahead) > view_hi:
                    break  # never in view: not a road user of this clip
                margin = 0.3 if cls == "Car" else 0.15
                track = _Track(t, s, vt, vs, dims[2] / 2, dims[1] / 2, psi, margin)
                if _clear(track, [ego, *statics, *placed], times, duration):
                    placed.append(track)
                    parts = b.object_parts(cls, dims)
                    movers.append(Mover(len(movers), cls, dims, parts, t, s, vt, vs, psi, support))
                    break
    return movers
