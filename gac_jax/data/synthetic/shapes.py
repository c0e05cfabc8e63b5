"""Convex solids and the part models of Cars, Pedestrians and Cyclists.

Every visible thing except the ground plane and the sky is a union of convex
polyhedra. A :class:`Solid` stores its faces as half-spaces ``n . X <= d``
(outward unit normals), which is all the ray caster in ``render.py`` needs, plus
its vertices (for the screen rectangle) and a colour/material per face.

Object models are built in the KITTI object frame: origin at the bottom-face
centre, x forward (length ``l``), y down (height ``h``), z to the object's right
(width ``w``). Every part lies inside ``[-l/2, l/2] x [-h, 0] x [-w/2, w/2]``,
i.e. inside the labelled 3D box.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# Face materials (how ``materials.py`` shades a face).
FLAT, GLASS, FACADE, PAVING, FOLIAGE, HEADLIGHTS, TAILLIGHTS, ROUGH, CARSIDE, RANDOM = range(10)
PHOTO = 10  # foliage and rough faces with a photograph's detail (photo_textures)

# Face order of box-like hexahedra: vertices are indexed like the corners of
# ``[x0, x1] x [y0, y1] x [z0, z1]`` with bit 0 = x, bit 1 = y, bit 2 = z.
HEX_FACES = (
    (1, 3, 7, 5),  # +x (front)
    (0, 4, 6, 2),  # -x (back)
    (0, 1, 5, 4),  # -y (top, y points down)
    (2, 6, 7, 3),  # +y (bottom)
    (0, 2, 3, 1),  # -z (left)
    (4, 5, 7, 6),  # +z (right)
)
FRONT, BACK, TOP, BOTTOM, LEFT, RIGHT = range(6)


@dataclasses.dataclass(frozen=True)
class Solid:
    """A convex polyhedron ``{X : normals @ X <= offsets}``.

    Attributes:
      normals: (K, 3) outward unit face normals.
      offsets: (K,) plane offsets.
      vertices: (V, 3) corner points (their hull is the solid).
      colors: (K, 3) float32 albedo per face in [0, 1].
      materials: (K,) int material code per face (``FLAT``, ``GLASS``, ...).
      frame: (3, 4) ``[R | t]`` mapping the solid's texture frame to the current
        frame (``X = R x + t``); shaders read texture coordinates ``x``.
      params: material parameters (e.g. a facade's window layout).
      gloss: a glossy finish: faces add this share of the sky's colour, the zenith's as they
        face up and the horizon's as they face sideways (0: matte).
    """

    normals: np.ndarray
    offsets: np.ndarray
    vertices: np.ndarray
    colors: np.ndarray
    materials: np.ndarray
    frame: np.ndarray
    params: tuple = ()
    gloss: float = 0.0  # share of the sky a face mirrors (car paint), by how much it faces up

    def transformed(self, R: np.ndarray, t: np.ndarray) -> Solid:
        """The solid moved by ``X' = R X + t`` (R a rotation)."""
        normals = self.normals @ R.T
        return dataclasses.replace(
            self,
            normals=normals,
            offsets=self.offsets + normals @ t,
            vertices=self.vertices @ R.T + t,
            frame=np.concatenate([R @ self.frame[:, :3], (R @ self.frame[:, 3] + t)[:, None]], 1),
        )

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(N,) bool: which of the (N, 3) points lie inside (within ``tol`` metres)."""
        return np.all(points @ self.normals.T <= self.offsets + tol, axis=-1)


def convex_solid(vertices, faces, colors, materials=FLAT, params: tuple = ()) -> Solid:
    """Builds a :class:`Solid` from vertices (V, 3) and planar faces (vertex-index lists).

    Normals are oriented away from the vertex centroid. ``colors`` is one RGB
    triple or one per face; ``materials`` one code or one per face.
    """
    v = np.asarray(vertices, dtype=np.float64)
    centre = v.mean(axis=0)
    first = np.array([f[:4] if len(f) >= 4 else (*f, f[0]) for f in faces])  # (K, 4)
    p0, p1, p2, p3 = (v[first[:, i]] for i in range(4))
    n = _cross(p1 - p0, p2 - p0)
    bad = np.einsum("ij,ij->i", n, n) < 1e-24  # degenerate first triangle: use the next one
    n[bad] = _cross(p2 - p0, p3 - p0)[bad]
    n /= np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
    n *= np.where(np.einsum("ij,ij->i", n, p0 - centre) < 0, -1.0, 1.0)[:, None]
    normals, offsets = n, np.einsum("ij,ij->i", n, p0)
    k = len(faces)
    colors = np.broadcast_to(np.asarray(colors, np.float32).reshape(-1, 3), (k, 3)).copy()
    materials = np.broadcast_to(np.asarray(materials, np.int64), (k,)).copy()
    frame = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    return Solid(normals, offsets, v, colors, materials, frame, params)


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (K, 3) arrays (np.cross is slow for small arrays)."""
    return np.stack(
        [
            a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
            a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
        ],
        axis=1,
    )


def hexahedron(vertices, colors, materials=FLAT, params: tuple = ()) -> Solid:
    """A six-faced convex solid from 8 vertices in box-corner order (faces :data:`HEX_FACES`).

    Opposite edges of each face must be parallel (boxes, sheared boxes,
    frusta with parallel top and bottom), so that every face is planar.
    """
    return convex_solid(vertices, HEX_FACES, colors, materials, params)


def box_vertices(x0, x1, y0, y1, z0, z1) -> np.ndarray:
    """(8, 3) corners of an axis-aligned box in :data:`HEX_FACES` order."""
    return np.array(
        [[(x0, x1)[i & 1], (y0, y1)[(i >> 1) & 1], (z0, z1)[(i >> 2) & 1]] for i in range(8)],
        dtype=np.float64,
    )


_BOX_NORMALS = np.array([[1.0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])


def box(x0, x1, y0, y1, z0, z1, colors, materials=FLAT, params: tuple = ()) -> Solid:
    """Axis-aligned box ``[x0, x1] x [y0, y1] x [z0, z1]`` (faces in :data:`HEX_FACES` order)."""
    offsets = np.array([x1, -x0, -y0, y1, -z0, z1], dtype=np.float64)
    colors = np.broadcast_to(np.asarray(colors, np.float32).reshape(-1, 3), (6, 3)).copy()
    materials = np.broadcast_to(np.asarray(materials, np.int64), (6,)).copy()
    frame = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)
    vertices = box_vertices(x0, x1, y0, y1, z0, z1)
    return Solid(_BOX_NORMALS.copy(), offsets, vertices, colors, materials, frame, params)


def sheared_box(bottom_xz, top_xz, y0, y1, half_x, half_z, colors) -> Solid:
    """A box whose top face (at ``y0``) is shifted horizontally against its bottom (at ``y1``).

    ``bottom_xz``/``top_xz`` are the (x, z) face centres; ``half_x``, ``half_z``
    the half sizes. Used for limbs and tubes.
    """
    v = box_vertices(-half_x, half_x, y0, y1, -half_z, half_z)
    top = v[:, 1] == y0
    v[top, 0] += top_xz[0]
    v[top, 2] += top_xz[1]
    v[~top, 0] += bottom_xz[0]
    v[~top, 2] += bottom_xz[1]
    return hexahedron(v, colors)


def prism_z(profile_xy, z0, z1, colors, cap_colors=None) -> Solid:
    """Extrudes a convex polygon (n, 2) in the x-y plane along z from ``z0`` to ``z1``.

    Faces: the n sides (edge i from vertex i to i+1), then the caps at z0 and z1.
    """
    p = np.asarray(profile_xy, dtype=np.float64)
    n = len(p)
    v = np.concatenate(
        [np.column_stack([p, np.full(n, z0)]), np.column_stack([p, np.full(n, z1)])], axis=0
    )
    faces = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    faces += [tuple(range(n)), tuple(range(n, 2 * n))]
    side = np.broadcast_to(np.asarray(colors, np.float32).reshape(-1, 3), (n, 3))
    cap = side[:1] if cap_colors is None else np.asarray(cap_colors, np.float32).reshape(1, 3)
    return convex_solid(v, faces, np.concatenate([side, cap, cap], axis=0))


def prism_y(profile_xz, y0, y1, colors) -> Solid:
    """Extrudes a convex polygon (n, 2) in the x-z plane vertically from ``y0`` (top) to ``y1``."""
    p = np.asarray(profile_xz, dtype=np.float64)
    n = len(p)
    top = np.column_stack([p[:, 0], np.full(n, y0), p[:, 1]])
    bottom = np.column_stack([p[:, 0], np.full(n, y1), p[:, 1]])
    faces = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    faces += [tuple(range(n)), tuple(range(n, 2 * n))]
    return convex_solid(np.concatenate([top, bottom]), faces, colors)


def lathe(radii, ys, n: int, centre_xz=(0.0, 0.0), colors=(0.5, 0.5, 0.5), materials=FLAT) -> Solid:
    """A convex solid of revolution about a vertical axis: rings of ``n`` vertices.

    ``ys`` (top to bottom) and ``radii`` give the rings; the profile must be
    convex. Adjacent rings are aligned, so every side face is planar.
    """
    m = len(ys)
    ring = polygon(n, 1.0, (0.0, 0.0), np.pi / n)
    v = np.concatenate(
        [
            np.column_stack(
                [centre_xz[0] + r * ring[:, 0], np.full(n, y), centre_xz[1] + r * ring[:, 1]]
            )
            for r, y in zip(radii, ys, strict=True)
        ]
    )
    faces = [
        (k * n + i, k * n + (i + 1) % n, (k + 1) * n + (i + 1) % n, (k + 1) * n + i)
        for k in range(m - 1)
        for i in range(n)
    ]
    faces += [tuple(range(n)), tuple(range((m - 1) * n, m * n))]
    return convex_solid(v, faces, colors, materials)


def polygon(n: int, radius: float, centre=(0.0, 0.0), phase: float = 0.0) -> np.ndarray:
    """(n, 2) regular polygon with vertices on a circle of ``radius``."""
    a = phase + 2.0 * np.pi * np.arange(n) / n
    return np.column_stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a)])


def _shade(color, factor) -> np.ndarray:
    return np.clip(np.asarray(color, np.float32) * factor, 0.0, 1.0)


# --------------------------------------------------------------------------- object models


def _rounded(a, b, x: float, bulge: float) -> tuple[float, float]:
    """A point above the chord from ``a`` to ``b`` (x-y profile points, y down) at ``x``:
    lifted by ``bulge`` it rounds the corner between them and keeps the outline convex."""
    t = (x - a[0]) / (b[0] - a[0])
    return (x, a[1] + t * (b[1] - a[1]) - bulge)


# Car body types and how often they occur (KITTI's "Car" class: saloons, hatchbacks,
# estates and small SUVs; vans and lorries are other classes).
CAR_BODIES = ("sedan", "hatchback", "wagon", "suv")
CAR_BODY_WEIGHTS = (0.4, 0.32, 0.16, 0.12)


def car_parts(
    h: float, w: float, l: float, paint, rng: np.random.Generator, kind: str | None = None
) -> list[Solid]:
    """A car: rounded body with wheel arches, glass cabin with a painted roof, mirrors, wheels.

    The body type (:data:`CAR_BODIES`; drawn from ``rng`` when ``kind`` is None) sets the
    cabin's length and the rear's shape. ``paint`` is the body RGB in [0, 1]. All parts lie
    inside the (h, w, l) box.
    """
    drawn = CAR_BODIES[rng.choice(len(CAR_BODIES), p=CAR_BODY_WEIGHTS)]
    kind = drawn if kind is None else kind
    r = min(0.21 * h, 0.09 * l) * rng.uniform(0.95, 1.05)  # wheel radius
    tyre_w = 0.13 * w
    sill = -0.45 * r  # bottom of the body panels
    belt = -rng.uniform(0.55, 0.60) * h if kind != "suv" else -rng.uniform(0.60, 0.66) * h
    nose = -rng.uniform(0.38, 0.46) * h  # top of the front face
    hatch = kind in ("hatchback", "wagon", "suv")
    tail = belt + (rng.uniform(0.0, 0.03) if hatch else rng.uniform(0.02, 0.08)) * h
    body_w = 0.47 * w
    # cabin: windscreen base/top (front) and rear window base/top (back), along x
    c_front = rng.uniform(0.12, 0.2) * l
    t_front = c_front - rng.uniform(0.15, 0.21) * l
    if kind == "sedan":
        c_back = -rng.uniform(0.28, 0.34) * l
        t_back = c_back + rng.uniform(0.1, 0.14) * l
    elif kind == "hatchback":
        c_back = -rng.uniform(0.42, 0.46) * l
        t_back = c_back + rng.uniform(0.06, 0.1) * l
    else:  # wagon, suv: a near-vertical tailgate
        c_back = -rng.uniform(0.45, 0.47) * l
        t_back = c_back + rng.uniform(0.02, 0.04) * l
    front_face_top = nose
    rear_face_top = tail + 0.02 * h
    hood_end = (c_front + 0.01 * l, belt)
    deck_end = (max(c_back - 0.01 * l, -l / 2 + 0.06 * l), belt)
    profile = [  # a convex side outline, rounded at the corners
        (-l / 2 + 0.03 * l, sill),
        (l / 2 - 0.03 * l, sill),
        (l / 2, sill - 0.35 * (sill - nose)),
        (l / 2, front_face_top),
        _rounded((l / 2, front_face_top), hood_end, l / 2 - 0.04 * l, 0.015 * h),
        hood_end,
        deck_end,
        _rounded(deck_end, (-l / 2, rear_face_top), -l / 2 + 0.03 * l, 0.01 * h),
        (-l / 2, rear_face_top),
        (-l / 2, sill - 0.3 * (sill - tail)),
    ]
    x_wheels = (l / 2 - 0.19 * l, -l / 2 + 0.2 * l)
    doors = (c_front - 0.02 * l, 0.5 * (c_front + c_back))
    gloss = rng.uniform(0.05, 0.3)
    body = dataclasses.replace(
        prism_z(profile, -body_w, body_w, paint),
        params=(front_face_top, rear_face_top, body_w, *x_wheels, r, sill, belt, *doors),
        gloss=gloss,
    )
    body.materials[2] = HEADLIGHTS  # the front face (x = +l/2)
    body.materials[8] = TAILLIGHTS  # the rear face (x = -l/2)
    body.materials[-2:] = CARSIDE  # the two sides (z = -+body_w): wheel arches, doors

    # Cabin: a frustum with parallel top and bottom rectangles (planar faces).
    wb, wt = 0.45 * w, rng.uniform(0.36, 0.40) * w
    ys = (-h, belt + 0.01)  # cabin top and bottom (slightly sunk into the body)
    verts = []
    for i in range(8):
        top = ((i >> 1) & 1) == 0
        x = (t_back, t_front)[i & 1] if top else (c_back, c_front)[i & 1]
        half = wt if top else wb
        verts.append((x, ys[0] if top else ys[1], half if (i >> 2) & 1 else -half))
    glass = np.array([0.05, 0.06, 0.08]) + rng.uniform(0, 0.05)
    colors = np.array([glass] * 6, np.float32)
    colors[TOP] = paint
    materials = np.full(6, GLASS)
    materials[TOP] = FLAT
    reflect = rng.uniform(0.1, 0.45)  # share of the sky seen in the windows
    cabin = convex_solid(np.array(verts), HEX_FACES, colors, materials, (reflect, -h, belt))
    cabin = dataclasses.replace(cabin, gloss=gloss)  # (the painted roof; glass shades itself)

    mirrors = []
    for z0, z1 in ((-w / 2 + 0.005, -body_w + 0.01), (body_w - 0.01, w / 2 - 0.005)):
        x0 = c_front - 0.06 * l
        mirrors.append(box(x0, x0 + 0.05 * l, belt - 0.14, belt - 0.03, z0, z1, paint))

    return [body, cabin, *mirrors, *wheels(x_wheels, r, w, tyre_w, rng)]


def wheels(x_axles, r: float, w: float, tyre_w: float, rng: np.random.Generator) -> list[Solid]:
    """Tyres of radius ``r`` with hub caps (12-sided prisms) at the axles' x, on both sides of
    a ``w`` wide body (object frame); one draw from ``rng`` (the hubs' shade)."""
    tyre = np.array([0.05, 0.05, 0.055])
    rim = np.array([0.35, 0.35, 0.36]) * rng.uniform(0.6, 1.2)
    out = []
    for x in x_axles:
        for z0, z1 in ((-w / 2, -w / 2 + tyre_w), (w / 2 - tyre_w, w / 2)):
            outline = polygon(12, r, (x, -r), np.pi / 12)
            outline[:, 1] = np.minimum(outline[:, 1], 0.0)  # (no part below the ground)
            wheel = prism_z(outline, z0, z1, tyre, cap_colors=tyre)
            wheel.colors[-2:] = rim  # hub caps
            wheel.materials[-2:] = ROUGH
            out.append(wheel)
    return out


def pedestrian_parts(h: float, w: float, l: float, rng: np.random.Generator) -> list[Solid]:
    """A walking person: two sheared legs, torso, swinging arms, head (inside the box)."""
    shirt = rng.uniform(0.1, 0.9, 3) * rng.uniform(0.4, 1.0)
    trousers = rng.choice([[0.15, 0.2, 0.35], [0.08, 0.08, 0.09], [0.45, 0.4, 0.3]])
    trousers = np.asarray(trousers) * rng.uniform(0.8, 1.2)
    skin = np.array([0.85, 0.65, 0.5]) * rng.uniform(0.5, 1.05)
    hair = np.array([0.12, 0.09, 0.06]) * rng.uniform(0.5, 2.0)
    hip, shoulder, neck = -0.5 * h, -0.81 * h, -0.86 * h
    stride = (l / 2 - 0.07) * rng.uniform(0.4, 0.9)  # feet apart along x (walking)
    half_leg = min(0.07, w / 8)
    parts = []
    for sign, zc in ((1.0, -0.25 * w), (-1.0, 0.25 * w)):
        zc = np.clip(zc, -w / 2 + half_leg, w / 2 - half_leg) * 0.55
        parts.append(
            sheared_box((sign * stride, zc), (0.0, zc), hip, 0.0, half_leg, half_leg, trousers)
        )
        arm_z = np.clip(zc * 3.0, -w / 2 + 0.05, w / 2 - 0.05)
        swing = -sign * stride * 0.7
        parts.append(
            sheared_box((swing, arm_z), (0.0, arm_z), shoulder, hip + 0.05, 0.045, 0.045, shirt)
        )
    torso_w = min(0.19, w / 2 - 0.1)
    parts.append(box(-0.11, 0.11, shoulder, hip + 0.02, -torso_w, torso_w, shirt))
    head = prism_y(polygon(8, 0.1, (0.0, 0.0), np.pi / 8), -h, neck + 0.02, skin)
    head.colors[-2] = hair  # top cap
    parts.append(head)
    return parts


def cyclist_parts(h: float, w: float, l: float, rng: np.random.Generator) -> list[Solid]:
    """A bicycle (two thin wheels, frame tubes) ridden by a leaning person (inside the box)."""
    r = min(0.34, l / 4.2, h / 5.0)
    tyre = np.array([0.05, 0.05, 0.05])
    frame_c = rng.uniform(0.1, 0.9, 3)
    shirt = rng.uniform(0.1, 0.9, 3)
    trousers = np.array([0.1, 0.1, 0.12]) * rng.uniform(0.8, 2.0)
    skin = np.array([0.85, 0.65, 0.5]) * rng.uniform(0.5, 1.05)
    helmet = rng.uniform(0.1, 0.9, 3)
    xr, xf = -l / 2 + r, l / 2 - r
    parts = []
    for x in (xr, xf):
        wheel = prism_z(polygon(10, r, (x, -r), np.pi / 10), -0.025, 0.025, tyre)
        parts.append(wheel)
    seat = (xr + 0.35 * (xf - xr), -2.6 * r)
    bar = (xf - 0.12 * l, -2.9 * r)
    crank = (0.5 * (xr + xf) - 0.05, -r)
    tubes = [((xr, -r), seat), (crank, seat), (crank, bar), ((xf, -r), bar)]
    for (x0, y0), (x1, y1) in tubes:  # tubes as sheared boxes in the x-y plane
        lo, hi = (x0, y0), (x1, y1)
        if y1 > y0:
            lo, hi = hi, lo
        parts.append(sheared_box((lo[0], 0.0), (hi[0], 0.0), hi[1], lo[1], 0.025, 0.025, frame_c))
    hip = (seat[0], seat[1] - 0.05)
    shoulder_x = seat[0] + rng.uniform(0.2, 0.32)
    shoulder_y = -0.8 * h
    half_body = min(0.17, w / 2 - 0.06)
    torso = sheared_box((hip[0], 0.0), (shoulder_x, 0.0), shoulder_y, hip[1], 0.1, half_body, shirt)
    parts.append(torso)
    for zc in (-0.1, 0.1):  # legs from the hip down to the pedals
        zc = float(np.clip(zc, -w / 2 + 0.06, w / 2 - 0.06))
        foot_x = crank[0] + (0.12 if zc > 0 else -0.12)
        parts.append(
            sheared_box((foot_x, zc), (hip[0], zc), hip[1], -0.35 * r, 0.06, 0.06, trousers)
        )
        arm_z = float(np.clip(zc * 1.8, -w / 2 + 0.04, w / 2 - 0.04))
        parts.append(
            sheared_box(
                (bar[0], arm_z), (shoulder_x, arm_z), shoulder_y + 0.04, bar[1], 0.04, 0.04, shirt
            )
        )
    neck = shoulder_y - 0.04
    head_x = min(shoulder_x + 0.04, l / 2 - 0.12)
    head = prism_y(polygon(8, 0.1, (head_x, 0.0), np.pi / 8), -h, neck, skin)
    head.colors[-2] = helmet
    parts.append(head)
    return parts
