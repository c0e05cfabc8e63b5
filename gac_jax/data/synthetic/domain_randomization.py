"""Structured domain randomization: random colours and patterns on the background.

In a share of the generated frames (``randomize``), part of the background solids
(buildings, trees, hedges, poles, street furniture, the far skyline; not sidewalks, which
receive shadows) are repainted with a random colour and one of four random patterns (noise,
stripes, checks, spots) at a random scale from 5 cm to 3 m. Geometry, lighting, shadows,
depth, the cars and the labels are those of the same frame without it. A detector trained
on such frames cannot tell a car from its surroundings by the renderer's own look of a
tree or a wall, only by shape and context, which is what transfers to a real camera
(Tobin et al. 2017, "Domain randomization"; Prakash et al. 2019, "Structured domain
randomization").

The randomness comes from a stream of its own (``frame.make_frame``), so a frame that draws
no randomization is the same bytes as without the option.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.data.synthetic import shapes

PATTERNS = ("noise", "stripes", "checks", "spots")
SOLID_SHARE = 0.6  # of the background solids repainted in a randomized frame
SCALE_RANGE = (0.05, 3.0)  # metres per pattern period (log-uniform)


def random_colour(rng: np.random.Generator) -> np.ndarray:
    """(3,) float32 RGB in [0, 1]: uniform hue, saturation 0-1, value 0.1-0.9."""
    h, s, v = rng.random(), rng.random(), rng.uniform(0.1, 0.9)
    k = (np.array([5.0, 3.0, 1.0]) + 6.0 * h) % 6.0
    rgb = v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return rgb.astype(np.float32)


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
        colors = np.clip(base * rng.uniform(0.85, 1.15, (k, 1)), 0.0, 1.0).astype(np.float32)
        second = random_colour(rng)
        lo, hi = np.log(SCALE_RANGE[0]), np.log(SCALE_RANGE[1])
        params = (
            float(rng.integers(len(PATTERNS))),  # pattern
            float(np.exp(rng.uniform(lo, hi))),  # scale (m)
            float(rng.uniform(0.3, 1.0)),  # contrast
            *(float(c) for c in second),  # second colour
            float(rng.uniform(0.0, np.pi)),  # direction in the ground plane
            float(rng.integers(1 << 20)),  # hash salt
        )
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
