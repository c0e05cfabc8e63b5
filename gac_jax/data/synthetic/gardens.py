"""Front gardens: an urban roadside's buildings set back behind lawns and gravel, with
hedges, fences or low walls along the back of the sidewalk and trees in the gardens.

In the default world the facades stand at the back of the sidewalk (0-3 m behind it), so
above the road a monocular network sees walls 5-10 m to the side. KITTI's residential
streets keep their houses 5-15 m behind the kerb, with parked cars, hedges and trees in
front: a network trained only on the narrow streets puts those houses and trees too near.
With ``gardens`` > 0 (:func:`plan`), each urban side of a frame gets front gardens with that
probability; the choices and every garden come from a random stream of their own, and the
buildings keep their own draws (only their front moves back), so a frame without gardens is
the default frame.

Road coordinates ``(t, y, s)`` as in :mod:`scene` (t lateral, right positive; y down; s
along the road); the ground is ``y = b.h``, the sidewalks' top ``y = b.h - kerb``.
"""

from __future__ import annotations

import numpy as np

from gac_jax.data.synthetic import roadside, shapes

DEPTH_RANGE = (3.0, 14.0)  # metres from the back of the sidewalk to the facades
PLOT_LENGTH = (8.0, 25.0)  # one garden along the road (m)
LAWN = np.array([0.20, 0.30, 0.11])
GRAVEL = np.array([0.52, 0.48, 0.40])
# boundary along the sidewalk: hedge, fence, low wall, none
BOUNDARY_WEIGHTS = np.array([0.4, 0.25, 0.15, 0.2])


def plan(rng: np.random.Generator, share: float, sides: dict[int, str]) -> dict[int, float]:
    """Garden depth (m) of each side (-1 left, 1 right): an urban side has front gardens with
    probability ``share``; 0 = none. Draws the same numbers whatever the sides are."""
    out = {}
    for side in (-1, 1):
        draw, depth = rng.random(), rng.uniform(*DEPTH_RANGE)
        out[side] = float(depth) if sides[side] == "urban" and draw < share else 0.0
    return out


def build(b, rng: np.random.Generator) -> None:
    """Adds the gardens of ``b.garden_depths`` to the scene builder ``b`` (after
    :func:`roadside.build`, which already set the buildings back by the garden depth)."""
    for side in (-1, 1):
        depth = b.garden_depths.get(side, 0.0)
        if depth <= 0.0:
            continue
        ground = b.h - b.kerb[side]
        back = b.edges[side] + side * b.sidewalk[side]  # back of the sidewalk
        _plots(b, rng, side, back, depth, ground)
        if rng.random() < 0.6:  # a row of garden trees (off the road users' ground)
            t = back + side * rng.uniform(1.5, max(1.6, depth - 1.0))
            n = len(b.obstacles)
            roadside.trees(b, side, t, ground, spacing=(6.0, 18.0), rng=rng)
            del b.obstacles[n:]


def _plots(b, rng, side, back, depth, ground) -> None:
    """Lawn or gravel plots from the sidewalk to under the facades, each with its boundary."""
    t0, t1 = sorted((back, back + side * (depth + 3.0)))
    s = -20.0
    while s < b.road_end:
        length = rng.uniform(*PLOT_LENGTH)
        lawn = rng.random() < 0.75
        color = (LAWN * rng.uniform(0.7, 1.3, 3)) if lawn else GRAVEL * rng.uniform(0.8, 1.15)
        mats = np.full(6, shapes.FLAT)
        mats[shapes.TOP] = shapes.FLAT if lawn else shapes.PAVING
        kind = int(rng.choice(len(BOUNDARY_WEIGHTS), p=BOUNDARY_WEIGHTS))
        height, thick = rng.uniform(0.6, 1.8), rng.uniform(0.5, 1.0)
        shade = rng.uniform(0.6, 1.4, 3)
        if not roadside.in_cross(b, s, s + length):
            # 2 cm above the sidewalk, so the lawn, not the paving under it, is seen
            b.add_road_solid(
                shapes.box(t0, t1, ground - 0.02, b.h + 0.3, s, s + length, color, mats)
            )
            _boundary(b, kind, side, back, ground, s, s + length - 0.8, height, thick, shade)
        s += length


def _boundary(b, kind, side, back, ground, s0, s1, height, thick, shade) -> None:
    if kind == 3 or s1 <= s0:
        return
    if kind == 0:  # a hedge
        ta, tb = sorted((back + side * 0.1, back + side * (0.1 + thick)))
        solid = shapes.box(ta, tb, ground - height, ground, s0, s1, LAWN * shade, shapes.FOLIAGE)
    elif kind == 1:  # a fence
        ta, tb = back + side * 0.05 - 0.03, back + side * 0.05 + 0.03
        color = np.clip(0.35 * shade, 0.05, 0.9)
        solid = shapes.box(ta, tb, ground - 0.7 * height, ground, s0, s1, color, shapes.ROUGH)
    else:  # a low wall
        ta, tb = sorted((back + side * 0.05, back + side * 0.3))
        color = np.clip(0.55 * shade, 0.2, 0.9)
        solid = shapes.box(ta, tb, ground - 0.5 * height, ground, s0, s1, color, shapes.ROUGH)
    # (not an obstacle: road users stay off the gardens, so their placement, the light and
    # the rest of the scene are the frame's without gardens)
    b.add_road_solid(solid)
