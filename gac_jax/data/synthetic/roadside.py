"""The roadside of a scene: kerbs and sidewalks, buildings with windows, trees, poles, skyline.

Everything is built in the road frame ``(t, y, s)`` (see ``scene.py``) as
convex solids and handed to the scene builder, which moves it to the camera
frame. Trees, poles and barriers also leave footprints that road users avoid.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes

ROAD_END = 170.0  # buildings and sidewalks end here (a clip extends it); a skyline closes the view
PLASTER = np.array(
    [
        [0.80, 0.76, 0.66],
        [0.85, 0.84, 0.80],
        [0.62, 0.62, 0.60],
        [0.78, 0.62, 0.40],
        [0.58, 0.30, 0.22],
        [0.86, 0.80, 0.55],
        [0.55, 0.50, 0.45],
    ]
)


@dataclasses.dataclass
class Footprint:
    """An oriented rectangle on the road plane: centre (t, s), half sizes, heading psi."""

    t: float
    s: float
    half_l: float
    half_w: float
    psi: float

    def axes(self):
        fwd = np.array([np.sin(self.psi), np.cos(self.psi)])
        side = np.array([np.cos(self.psi), -np.sin(self.psi)])
        return fwd, side

    def overlaps(self, other: Footprint, margin: float) -> bool:
        """Separating-axis test of the two rectangles grown by ``margin``."""
        d = np.array([other.t - self.t, other.s - self.s])
        reach = np.hypot(self.half_l, self.half_w) + np.hypot(other.half_l, other.half_w)
        if abs(d[0]) > reach + 2 * margin or abs(d[1]) > reach + 2 * margin:
            return False
        a_f, a_s = self.axes()
        b_f, b_s = other.axes()
        for axis in (a_f, a_s, b_f, b_s):
            ra = (self.half_l + margin) * abs(axis @ a_f) + (self.half_w + margin) * abs(axis @ a_s)
            rb = (other.half_l + margin) * abs(axis @ b_f) + (other.half_w + margin) * abs(
                axis @ b_s
            )
            if abs(axis @ d) > ra + rb:
                return False
        return True


def build(b) -> None:
    """Adds kerbs, sidewalks, buildings, trees, poles and the skyline to the scene builder ``b``."""
    rng, h = b.rng, b.h
    b.kerb = {}
    b.sidewalk = {}
    for side in (-1, 1):
        edge = b.edges[side]
        if b.sides[side] == "urban":
            width = rng.uniform(2.0, 4.5)
            kerb = rng.uniform(0.10, 0.16)
            b.kerb[side], b.sidewalk[side] = kerb, width
            t0, t1 = sorted((edge, edge + side * (width + 3.0)))
            paving = np.array([0.62, 0.60, 0.56]) * rng.uniform(0.8, 1.1)
            colors = np.array([paving * 1.1] * 6)
            mats = np.full(6, shapes.FLAT)
            colors[shapes.TOP], mats[shapes.TOP] = paving, shapes.PAVING
            for s0, s1 in spans(b, -20.0, b.road_end):
                b.add_road_solid(shapes.box(t0, t1, h - kerb, h + 0.3, s0, s1, colors, mats))
            # (front gardens, :mod:`gardens`, set the buildings back by their depth)
            _buildings(b, side, edge + side * (width + b.garden_depths.get(side, 0.0)))
            if rng.random() < 0.5:
                trees(b, side, edge + side * 0.9, h - kerb, spacing=(8.0, 16.0))
            _poles(b, side, edge + side * 0.5, h - kerb)
            _clutter(b, side, edge + side * (width - 0.5), h - kerb)
        else:
            b.kerb[side], b.sidewalk[side] = 0.0, 0.0
            if rng.random() < 0.5:  # concrete barrier
                t0, t1 = sorted((edge + side * 0.4, edge + side * 0.65))
                grey = np.array([0.7, 0.7, 0.68]) * rng.uniform(0.8, 1.1)
                top = h - rng.uniform(0.6, 0.9)
                for s0, s1 in spans(b, -10.0, b.road_end):
                    b.add_road_solid(shapes.box(t0, t1, top, h + 0.2, s0, s1, grey))
                    b.obstacles.append(
                        Footprint(0.5 * (t0 + t1), (s0 + s1) / 2, (s1 - s0) / 2, 0.2, 0.0)
                    )
            trees(b, side, edge + side * rng.uniform(2.0, 5.0), h, spacing=(5.0, 12.0))
            _poles(b, side, edge + side * 1.2, h)
            _hedges(b, side, edge + side * rng.uniform(1.5, 3.0), h)
    _skyline(
        b,
    )


def spans(b, s0: float, s1: float) -> list[tuple[float, float]]:
    """``[s0, s1]`` less a cross street (``b.cross``) and, on a curved road, in pieces of
    ``b.piece_length`` metres overlapping by 1.5 m (each piece is bent rigidly)."""
    out = [(s0, s1)]
    if b.cross is not None:
        c0, c1 = b.cross
        out = [(a, c) for a, c in ((s0, min(s1, c0)), (max(s0, c1), s1)) if c > a]
    if b.piece_length is None:
        return out
    pieces = []
    for a, c in out:
        n = max(1, int(np.ceil((c - a) / b.piece_length)))
        edges = np.linspace(a, c, n + 1)
        pieces += [
            (max(a, e0 - 0.75), min(c, e1 + 0.75))
            for e0, e1 in zip(edges[:-1], edges[1:], strict=True)
        ]
    return pieces


def in_cross(b, s0: float, s1: float) -> bool:
    return b.cross is not None and s1 > b.cross[0] - 1.0 and s0 < b.cross[1] + 1.0


def _buildings(b, side, front_t):
    rng, h = b.rng, b.h
    s = -25.0
    while s < b.road_end:
        width = rng.uniform(8.0, 28.0)
        setback = 0.0 if rng.random() < 0.6 else rng.uniform(0.5, 3.0)
        height = rng.uniform(5.0, 22.0)
        t_front = front_t + side * setback
        t0, t1 = sorted((t_front, t_front + side * rng.uniform(8.0, 15.0)))
        plaster = PLASTER[rng.integers(len(PLASTER))] * rng.uniform(0.8, 1.1)
        glass = np.array([0.12, 0.15, 0.2]) * rng.uniform(0.6, 1.4)
        params = (
            h,
            rng.uniform(2.8, 3.6),
            rng.uniform(1.8, 3.5),
            rng.uniform(0.35, 0.6),
            rng.uniform(0.4, 0.6),
            *glass,
            int(rng.integers(1 << 20)),
            float(rng.random() < 0.4),  # shop windows on the ground floor
            float(rng.uniform(0.04, 0.3)),  # texture contrast (smooth plaster .. rough render)
            float(rng.random() < 0.3),  # brick courses
        )
        mats = np.full(6, shapes.FACADE)
        mats[shapes.TOP] = shapes.FLAT
        solid = shapes.box(t0, t1, h - height, h + 0.5, s, s + width, plaster, mats, params)
        if not in_cross(b, s, s + width):
            b.add_road_solid(solid)
        s += width + (0.0 if rng.random() < 0.6 else rng.uniform(2.0, 10.0))


def trees(b, side, t, ground_y, spacing, rng: np.random.Generator | None = None):
    """A row of trees at lateral ``t`` standing on ``ground_y``, ``spacing`` (m) apart, drawn
    from ``rng`` (default: the scene's)."""
    rng = b.rng if rng is None else rng
    s = rng.uniform(-5.0, 10.0)
    while s < b.road_end - 20:
        tt = t + side * rng.uniform(0.0, 0.4)
        trunk_h, crown_h, radius = (
            rng.uniform(1.8, 3.0),
            rng.uniform(2.5, 5.5),
            rng.uniform(1.0, 2.2),
        )
        bark = np.array([0.3, 0.22, 0.15]) * rng.uniform(0.6, 1.2)
        leaf = np.array([0.18, 0.32, 0.12]) * rng.uniform(0.6, 1.4, 3)
        top = ground_y - trunk_h - crown_h
        if not in_cross(b, s - radius, s + radius):
            b.add_road_solid(
                shapes.box(
                    tt - 0.15, tt + 0.15, top + 0.5 * crown_h, ground_y, s - 0.15, s + 0.15, bark
                )
            )
            for k in range(int(rng.integers(1, 4))):  # a crown of 1-3 overlapping blobs
                scale = 1.0 if k == 0 else rng.uniform(0.5, 0.8)
                dt, ds = (0.0, 0.0) if k == 0 else rng.uniform(-0.7, 0.7, 2) * radius
                dy = 0.0 if k == 0 else rng.uniform(0.0, 0.4) * crown_h
                ys = [top + dy, top + dy + 0.45 * crown_h * scale, top + dy + crown_h * scale]
                radii = [0.5 * radius * scale, radius * scale, 0.45 * radius * scale]
                blob = leaf * rng.uniform(0.8, 1.2)
                b.add_road_solid(
                    shapes.lathe(radii, ys, 8, (tt + dt, s + ds), blob, shapes.FOLIAGE)
                )
            b.obstacles.append(Footprint(tt, s, 0.3, 0.3, 0.0))
        s += rng.uniform(*spacing)


def _poles(b, side, t, ground_y):
    rng = b.rng
    s = rng.uniform(0.0, 30.0)
    while s < b.road_end - 20:
        grey = np.array([0.5, 0.5, 0.52]) * rng.uniform(0.6, 1.2)
        keep = not in_cross(b, s - 0.5, s + 0.5)  # (the random draws stay the same)
        add = b.add_road_solid if keep else lambda solid: None
        if rng.random() < 0.3:  # traffic sign
            top = ground_y - rng.uniform(2.2, 2.8)
            add(shapes.box(t - 0.04, t + 0.04, top, ground_y, s - 0.04, s + 0.04, grey))
            plate = [(0.1, 0.25, 0.65), (0.8, 0.1, 0.1), (0.9, 0.9, 0.9), (0.9, 0.75, 0.1)]
            color = np.array(plate[rng.integers(4)])
            add(shapes.box(t - 0.35, t + 0.35, top - 0.6, top + 0.05, s - 0.08, s - 0.04, color))
        else:
            top = ground_y - rng.uniform(5.0, 8.0)
            add(shapes.box(t - 0.08, t + 0.08, top, ground_y, s - 0.08, s + 0.08, grey))
        if keep:
            b.obstacles.append(Footprint(t, s, 0.3, 0.4, 0.0))
        s += rng.uniform(20.0, 45.0)


CLUTTER_END = 150.0  # street furniture along the sidewalks up to here (m)
BIN_COLORS = np.array(
    [[0.1, 0.3, 0.12], [0.35, 0.35, 0.36], [0.08, 0.08, 0.09], [0.1, 0.2, 0.45], [0.5, 0.35, 0.1]]
)


def _clutter(b, side, t, ground_y):
    """Street furniture at the back of a sidewalk: bins, bushes, bollards, fences and
    boxes of random colour and texture (distractors that are not road users)."""
    rng = b.rng
    s = rng.uniform(-5.0, 6.0)
    while s < CLUTTER_END:
        kind = rng.choice(4, p=[0.3, 0.3, 0.2, 0.2])
        tt = t + side * rng.uniform(-0.2, 0.3)
        if in_cross(b, s - 2.0, s + 2.0):
            kind = -1
        if kind == 0:  # wheelie bins in a row
            for k in range(int(rng.integers(1, 4))):
                color = BIN_COLORS[rng.integers(len(BIN_COLORS))] * rng.uniform(0.8, 1.2)
                hb = rng.uniform(0.9, 1.2)
                c = s + 0.7 * k
                b.add_road_solid(
                    shapes.box(
                        tt - 0.3,
                        tt + 0.3,
                        ground_y - hb,
                        ground_y,
                        c - 0.3,
                        c + 0.3,
                        color,
                        shapes.ROUGH,
                    )
                )
        elif kind == 1:  # a bush
            r = rng.uniform(0.5, 1.4)
            leaf = np.array([0.16, 0.28, 0.1]) * rng.uniform(0.6, 1.4, 3)
            hb = rng.uniform(0.7, 1.8)
            b.add_road_solid(
                shapes.lathe(
                    [0.6 * r, r, 0.7 * r],
                    [ground_y - hb, ground_y - 0.5 * hb, ground_y],
                    8,
                    (tt + side * 0.3, s),
                    leaf,
                    shapes.FOLIAGE,
                )
            )
        elif kind == 2:  # a fence or railing along the sidewalk
            length = rng.uniform(3.0, 15.0)
            color = rng.uniform(0.1, 0.7, 3) * rng.uniform(0.5, 1.0)
            hf = rng.uniform(0.8, 1.8)
            b.add_road_solid(
                shapes.box(
                    tt - 0.03,
                    tt + 0.03,
                    ground_y - hf,
                    ground_y,
                    s,
                    s + length,
                    color,
                    shapes.ROUGH,
                )
            )
            s += length
        elif kind == 3:  # a box of random colour (structured domain randomisation)
            size = rng.uniform(0.4, 1.6, 3) * (rng.uniform(1.0, 2.8) if rng.random() < 0.3 else 1)
            color = rng.uniform(0.05, 0.95, 3)
            b.add_road_solid(
                shapes.box(
                    tt - size[0] / 2,
                    tt + size[0] / 2,
                    ground_y - size[1],
                    ground_y,
                    s - size[2] / 2,
                    s + size[2] / 2,
                    color,
                    shapes.ROUGH,
                )
            )
        s += rng.uniform(2.0, 12.0) * (1.0 if s < 40.0 else 0.6)  # denser far away


def _hedges(b, side, t, ground_y):
    """Hedges and bushes on an open roadside's verge."""
    rng = b.rng
    s = rng.uniform(-5.0, 20.0)
    while s < CLUTTER_END:
        length = rng.uniform(3.0, 25.0)
        hh, depth = rng.uniform(0.8, 2.5), rng.uniform(0.6, 1.5)
        leaf = np.array([0.15, 0.27, 0.1]) * rng.uniform(0.6, 1.4, 3)
        t0, t1 = sorted((t, t + side * depth))
        if not in_cross(b, s, s + length):
            b.add_road_solid(
                shapes.box(t0, t1, ground_y - hh, ground_y, s, s + length, leaf, shapes.FOLIAGE)
            )
        s += length + rng.uniform(2.0, 30.0)


def _skyline(b):
    rng, h = b.rng, b.h
    t = -320.0
    trees = rng.random() < 0.5
    while t < 320.0:
        width = rng.uniform(15.0, 60.0)
        s0 = b.road_end + rng.uniform(0.0, 25.0)
        height = rng.uniform(6.0, 18.0) if trees else rng.uniform(8.0, 35.0)
        if trees:
            color = np.array([0.14, 0.22, 0.10]) * rng.uniform(0.7, 1.4)
            mats, params = shapes.FOLIAGE, ()
        else:
            color = PLASTER[rng.integers(len(PLASTER))] * rng.uniform(0.6, 0.9)
            mats = np.full(6, shapes.FACADE)
            params = (h, 3.2, 2.5, 0.5, 0.5, 0.12, 0.14, 0.18, int(rng.integers(1 << 20)))
        b.add_road_solid(
            shapes.box(t, t + width, h - height, h + 0.5, s0, s0 + 20.0, color, mats, params)
        )
        t += width
