"""Structured domain randomization: random colours and patterns on the background and cars.

In a share of the generated frames (``randomize``), part of the background solids
(buildings, trees, hedges, poles, street furniture, the far skyline; not sidewalks, which
receive shadows) are repainted with a random colour and one of four random patterns (noise,
stripes, checks, spots) at a random scale from 5 cm to 3 m. Geometry, lighting, shadows,
depth, the cars and the labels are those of the same frame without it. A detector trained
on such frames cannot tell a car from its surroundings by the renderer's own look of a
tree or a wall, only by shape and context, which is what transfers to a real camera
(Tobin et al. 2017, "Domain randomization"; Prakash et al. 2019, "Structured domain
randomization").

The cars can be randomized too (``randomize_cars``, Tremblay et al. 2018, "Training deep
networks with synthetic data: bridging the reality gap by domain randomization"): in a share
of the frames, part of the cars get a body of a random colour and pattern (no lights, plate,
arches or door seams), windows of a random tint and reflection, and tyres and hubs of random
shades. A real car's paint, reflections and trim then differ from the generated ones' as
much as the generated ones differ among themselves, and what stays is the car's shape: its
silhouette, cabin and wheels, where the box's edges are.

The randomness comes from streams of their own (``frame.make_frame``), so a frame that draws
no randomization is the same bytes as without the option.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes

PATTERNS = ("noise", "stripes", "checks", "spots")
SOLID_SHARE = 0.6  # of the background solids repainted in a randomized frame
SCALE_RANGE = (0.05, 3.0)  # metres per pattern period (log-uniform)
CAR_SHARE = 0.7  # of the cars repainted in a frame whose cars are randomized
CAR_SCALE_RANGE = (0.05, 1.5)  # metres per pattern period on a car body (log-uniform)


def random_colour(rng: np.random.Generator) -> np.ndarray:
    """(3,) float32 RGB in [0, 1]: uniform hue, saturation 0-1, value 0.1-0.9."""
    h, s, v = rng.random(), rng.random(), rng.uniform(0.1, 0.9)
    k = (np.array([5.0, 3.0, 1.0]) + 6.0 * h) % 6.0
    rgb = v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return rgb.astype(np.float32)


def _face_colours(base: np.ndarray, k: int, rng: np.random.Generator, gains: tuple):
    """(k, 3) float32: ``base`` times a gain drawn per face from ``gains``, clipped to [0, 1]."""
    gain = rng.uniform(gains[0], gains[1], (k, 1))
    return np.clip(base * gain, 0.0, 1.0).astype(np.float32)


def _pattern_params(rng: np.random.Generator, scale_range) -> tuple:
    """Parameters of ``materials._random_pattern``: pattern, period, contrast, second colour,
    direction, salt."""
    second = random_colour(rng)  # (drawn first: the order of the draws is the frames' bytes)
    lo, hi = np.log(scale_range[0]), np.log(scale_range[1])
    return (
        float(rng.integers(len(PATTERNS))),  # pattern
        float(np.exp(rng.uniform(lo, hi))),  # scale (m)
        float(rng.uniform(0.3, 1.0)),  # contrast
        *(float(c) for c in second),  # second colour
        float(rng.uniform(0.0, np.pi)),  # direction in the texture frame's x-z plane
        float(rng.integers(1 << 20)),  # hash salt
    )


def randomize_background(
    background: list[shapes.Solid], rng: np.random.Generator, share: float
) -> list[shapes.Solid]:
    """The background solids, part of them repainted, in a ``share`` of the calls.

    Args:
      background: the scene's background solids (road frame).
      rng: the frame's randomization stream.
      share: probability in [0, 1] that this frame is randomized at all.

    Returns:
      A new list (the input is not modified); the same list when the frame draws none.
    """
    if share <= 0.0 or rng.random() >= share:
        return background
    out = []
    for solid in background:
        if np.any(solid.materials == shapes.PAVING) or rng.random() >= SOLID_SHARE:
            out.append(solid)
            continue
        k = len(solid.offsets)
        base = random_colour(rng)
        colors = _face_colours(base, k, rng, (0.85, 1.15))
        params = _pattern_params(rng, SCALE_RANGE)
        out.append(
            dataclasses.replace(
                solid,
                colors=colors,
                materials=np.full(k, shapes.RANDOM, np.int64),
                params=params,
                gloss=0.0,
            )
        )
    return out


def randomize_cars(objects: list, rng: np.random.Generator, share: float) -> list:
    """The scene's road users, part of the cars repainted, in a ``share`` of the calls.

    A repainted car (:data:`CAR_SHARE` of the cars of a randomized frame) keeps its shape
    and box: its body (every face: no lights, plate, arches or seams) takes a random colour
    and pattern in its own frame, its mirrors and roof the body's colour, its windows a
    random tint and share of the sky, its tyres and hubs random shades, and its gloss is
    drawn anew. Other road users are unchanged.

    Args:
      objects: the scene's :class:`~gac_jax.data.synthetic.scene.SceneObject` list, whose
        cars have the parts of :func:`shapes.car_parts` (body, cabin, 2 mirrors, 4 wheels).
      rng: the frame's car-randomization stream.
      share: probability in [0, 1] that this frame's cars are randomized at all.

    Returns:
      A new list (the input is not modified); the same list when the frame draws none.
    """
    if share <= 0.0 or rng.random() >= share:
        return objects
    out = []
    for obj in objects:
        if obj.type != "Car" or rng.random() >= CAR_SHARE:
            out.append(obj)
            continue
        body, cabin, *rest = obj.parts
        mirrors, wheels = rest[:2], rest[2:]
        base = random_colour(rng)
        k = len(body.offsets)
        gloss = float(rng.uniform(0.0, 0.35))
        body = dataclasses.replace(
            body,
            colors=_face_colours(base, k, rng, (0.9, 1.1)),
            materials=np.full(k, shapes.RANDOM, np.int64),
            params=_pattern_params(rng, CAR_SCALE_RANGE),
            gloss=gloss,
        )
        glass = random_colour(rng) * np.float32(rng.uniform(0.1, 0.6))
        colors = np.where(
            (cabin.materials == shapes.GLASS)[:, None], glass[None, :], base[None, :]
        ).astype(np.float32)
        reflect = float(rng.uniform(0.0, 0.7))
        cabin = dataclasses.replace(
            cabin, colors=colors, params=(reflect, *cabin.params[1:]), gloss=gloss
        )
        mirrors = [
            dataclasses.replace(m, colors=np.tile(base, (len(m.offsets), 1))) for m in mirrors
        ]
        tyre = random_colour(rng) * np.float32(rng.uniform(0.05, 0.4))
        hub = random_colour(rng)
        painted = []
        for wheel in wheels:
            colors = np.tile(tyre, (len(wheel.offsets), 1)).astype(np.float32)
            colors[wheel.materials == shapes.ROUGH] = hub
            painted.append(dataclasses.replace(wheel, colors=colors))
        out.append(dataclasses.replace(obj, parts=[body, cabin, *mirrors, *painted]))
    return out
