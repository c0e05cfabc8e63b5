"""Vans and trucks: the models of KITTI's ``Van`` and ``Truck`` classes.

Real roads carry delivery vans, minibuses, lorries and tankers beside the cars, and a detector
that has only seen cars calls every large box on wheels a Car. In the generated frames
(``large_vehicles``: a share of the frames gets one to three of them) they are labelled
``Van`` / ``Truck`` with KITTI's size statistics: a detector trained for ``Car`` learns them as
background, as it does on KITTI, and KITTI's evaluation excuses a Car detection on a Van but
counts one on a Truck as false.

Object frame as in :mod:`shapes`: origin at the bottom-face centre, x forward (length ``l``),
y down (height ``h``), z to the right (width ``w``); every part lies inside the box.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes
from gac_jax.geometry import rotation_y_matrix

# Sizes (mean, std) of (h, w, l) in metres: the means of KITTI's training labels, spreads about
# theirs (a truck's length narrowed to keep it between 5 and 15 m after the 2.5-sigma clip).
SIZES = {
    "Van": ((2.21, 0.32), (1.90, 0.13), (5.08, 0.55)),
    "Truck": ((3.25, 0.45), (2.59, 0.20), (10.11, 2.0)),
}
VAN_SHARE = 0.65  # of the large vehicles; the rest are trucks
COUNT = (1, 3)  # large vehicles in a frame that has them (uniform, inclusive)
CARGO_COLOURS = np.array(
    [[0.88, 0.88, 0.87], [0.7, 0.71, 0.72], [0.75, 0.1, 0.08], [0.1, 0.25, 0.55], [0.85, 0.7, 0.1]]
)
CARGO_WEIGHTS = np.array([0.45, 0.25, 0.1, 0.1, 0.1])


def _cabin(x_base_front, x_top_front, x_back, y_top, y_base, half_w, glass, paint, side_glass):
    """A hexahedron above the belt line: glass front, painted roof and back, glass or painted
    sides; vertices in the order of :data:`shapes.HEX_FACES`."""
    verts = []
    for i in range(8):
        top = ((i >> 1) & 1) == 0
        x = (x_back, x_top_front if top else x_base_front)[i & 1]
        verts.append((x, y_top if top else y_base, half_w if (i >> 2) & 1 else -half_w))
    colors = np.array([paint] * 6, np.float32)
    materials = np.full(6, shapes.FLAT)
    faces = [shapes.FRONT] + ([shapes.LEFT, shapes.RIGHT] if side_glass else [])
    for f in faces:
        colors[f], materials[f] = glass, shapes.GLASS
    return shapes.convex_solid(np.array(verts), shapes.HEX_FACES, colors, materials)


def van_parts(h: float, w: float, l: float, paint, rng: np.random.Generator) -> list:
    """A van: short bonnet, steep windscreen, a tall box to the rear (windows along the sides
    for a minibus, painted panels for a delivery van), lamps, mirrors, four wheels."""
    r = min(0.16 * h, 0.075 * l) * rng.uniform(0.95, 1.05)
    sill = -0.45 * r
    nose = -rng.uniform(0.36, 0.42) * h  # top of the front face
    belt = -rng.uniform(0.46, 0.52) * h
    x_screen = l / 2 - rng.uniform(0.12, 0.18) * l  # windscreen base
    x_screen_top = x_screen - rng.uniform(0.1, 0.14) * l
    body_w = 0.48 * w
    profile = [
        (-l / 2 + 0.02 * l, sill),
        (l / 2 - 0.03 * l, sill),
        (l / 2, sill - 0.35 * (sill - nose)),
        (l / 2, nose),
        (x_screen, belt),
        (-l / 2, belt),
        (-l / 2, sill - 0.3 * (sill - belt)),
    ]
    x_wheels = (l / 2 - 0.17 * l, -l / 2 + 0.2 * l)
    doors = (x_screen - 0.02 * l, x_screen - 0.22 * l)
    gloss = rng.uniform(0.05, 0.25)
    body = dataclasses.replace(
        shapes.prism_z(profile, -body_w, body_w, paint),
        params=(nose, belt, body_w, *x_wheels, r, sill, belt, *doors),
        gloss=gloss,
    )
    body.materials[2] = shapes.HEADLIGHTS  # the front face (x = +l/2)
    body.materials[5] = shapes.TAILLIGHTS  # the rear face (x = -l/2)
    body.materials[-2:] = shapes.CARSIDE
    glass = np.array([0.05, 0.06, 0.08]) + rng.uniform(0, 0.05)
    top = -h
    cab_back = x_screen - rng.uniform(0.2, 0.26) * l
    minibus = rng.random() < 0.35
    cab = _cabin(x_screen, x_screen_top, cab_back, top, belt + 0.01, 0.47 * w, glass, paint, True)
    box = _cabin(cab_back + 0.01, cab_back + 0.01, -l / 2, top, belt + 0.01, 0.47 * w, glass,
                 paint, minibus)  # fmt: skip
    reflect = rng.uniform(0.1, 0.4)
    cab = dataclasses.replace(cab, params=(reflect, top, belt), gloss=gloss)
    box = dataclasses.replace(box, params=(reflect, top, belt), gloss=gloss)
    mirrors = []
    for z0, z1 in ((-w / 2 + 0.005, -body_w + 0.01), (body_w - 0.01, w / 2 - 0.005)):
        x0 = x_screen - 0.04 * l
        mirrors.append(shapes.box(x0, x0 + 0.04 * l, belt - 0.2, belt - 0.02, z0, z1, paint))
    return [body, cab, box, *mirrors, *shapes.wheels(x_wheels, r, w, 0.12 * w, rng)]


def truck_parts(h: float, w: float, l: float, paint, rng: np.random.Generator) -> list:
    """A lorry: a tall cab (windscreen, lamps) ahead of a cargo box or tank on a dark chassis,
    wheels on two or three axles."""
    r = min(0.16 * h, 0.55) * rng.uniform(0.9, 1.05)
    cab_l = min(rng.uniform(1.9, 2.5), 0.4 * l)
    cab_h = min(h, rng.uniform(2.7, 3.2))
    floor = -min(2.2 * r + 0.1, 0.45 * h)  # underside of the cargo box
    x_cab = l / 2 - cab_l  # back of the cab
    belt = -0.55 * cab_h
    bumper = -0.9 * r
    body = shapes.box(x_cab, l / 2, belt, bumper, -0.49 * w, 0.49 * w, paint)
    lamps = bumper - 0.2  # the headlights' band lies just above the bumper
    body = dataclasses.replace(body, params=(lamps, lamps, 0.49 * w), gloss=rng.uniform(0.05, 0.2))
    body.materials[shapes.FRONT] = shapes.HEADLIGHTS
    glass = np.array([0.05, 0.06, 0.08]) + rng.uniform(0, 0.05)
    cab = _cabin(l / 2, l / 2 - 0.12 * cab_l, x_cab, -cab_h, belt + 0.01, 0.48 * w, glass,
                 paint, False)  # fmt: skip
    cab = dataclasses.replace(cab, params=(rng.uniform(0.1, 0.4), -cab_h, belt))
    cargo_colour = CARGO_COLOURS[rng.choice(len(CARGO_COLOURS), p=CARGO_WEIGHTS)]
    cargo_colour = np.clip(cargo_colour * rng.uniform(0.85, 1.1), 0.0, 1.0)
    x_front = x_cab - rng.uniform(0.15, 0.4)
    if rng.random() < 0.25:  # a tank: a horizontal cylinder (12-sided prism along x)
        radius = min(0.5 * (floor + h), 0.47 * w)
        outline = shapes.polygon(12, radius, (0.0, floor - radius), np.pi / 12)
        # (prism_z extrudes the (lateral, y) outline along z; a quarter turn about y lays it
        # along x, and the outline is symmetric about the lateral centre)
        tank = shapes.prism_z(outline, -l / 2 + 0.1, x_front, cargo_colour)
        cargo = tank.transformed(rotation_y_matrix(np.pi / 2), np.zeros(3))
    else:
        cargo = shapes.box(-l / 2, x_front, -h, floor, -w / 2, w / 2, cargo_colour)
        cargo.materials[shapes.BACK] = shapes.TAILLIGHTS
        cargo = dataclasses.replace(cargo, params=(floor - 0.16, floor - 0.16, w / 2))
    chassis = shapes.box(-l / 2 + 0.05, x_cab, floor, -0.6 * r, -0.3 * w, 0.3 * w, (0.04,) * 3)
    axles = [l / 2 - 0.55 * cab_l, -l / 2 + 0.18 * l]
    if l > 8.0:
        axles.append(axles[-1] + 2.0 * r + 0.15)
    return [body, cab, cargo, chassis, *shapes.wheels(axles, r, w, 0.12 * w, rng)]


def parts(cls: str, dims, paint, rng: np.random.Generator) -> list:
    """The part models of a ``Van`` or ``Truck`` of size ``dims`` (h, w, l) in its box frame."""
    h, w, l = dims
    if cls == "Van":
        return van_parts(h, w, l, paint, rng)
    if cls == "Truck":
        return truck_parts(h, w, l, paint, rng)
    raise ValueError(f"not a large vehicle class: {cls!r}")
