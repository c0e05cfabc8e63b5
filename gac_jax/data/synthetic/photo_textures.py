"""Photo textures: the fine detail of foliage, rough surfaces and verges from real photographs.

The renderer's own textures are band-limited noise: smooth where a real camera sees the
chaotic detail of leaves, grass and gravel. In a share of the generated frames (``photo``),
the background's foliage (trees, hedges, bushes, a skyline of trees), its rough solids
(fences, bins, random boxes) and the grass verges beside the road take their detail from one
of two photographs (``textures/``: grass and gravel, CC0, 512 x 512 grayscale) at a random
scale, contrast and offset per solid. The photographs only modulate brightness: colours,
lighting, shadows, depth, the cars and the labels are those of the same frame without them.

Textures are sampled like the rest of the renderer's, by metric surface coordinates, so their
detail shrinks with distance as the geometry does; a mip pyramid (each level the 2 x 2 mean of
the one below) is read at the level whose texels are about the size of the pixel's footprint,
so a far hedge shows the averaged photograph, not aliasing noise.

The randomness comes from a stream of its own (``frame.make_frame``), so a frame that draws no
photo textures is the same bytes as without the option.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.synthetic import shapes

TEXTURE_DIR = Path(__file__).with_name("textures")
# name -> sha256 of the PNG (textures/README.md: their origin and licence)
TEXTURES = {
    "grass": "b6b6022426b38936c43a4ac09635cd78af074e90f42ffa8227ac8b7452d39f89",
    "gravel": "c48615b451bf1e606fbd72c0aa9f8cc0f068ab7111ef7d93bb9b0f2586440c12",
}
NAMES = tuple(TEXTURES)
GRASS, GRAVEL = range(len(NAMES))
HIGH_PASS_SIGMA = 48.0  # texels: the photographs' uneven lighting is removed, their detail kept

# per solid, drawn log-uniformly / uniformly
FOLIAGE_METRES = (0.5, 2.5)  # metres one photograph spans on foliage
ROUGH_METRES = (0.3, 1.5)  # ... on rough solids
VERGE_METRES = (0.4, 1.5)  # ... on the verges
CONTRAST = (0.25, 0.5)  # std of the brightness modulation


@functools.cache
def pyramids() -> tuple[tuple[np.ndarray, ...], ...]:
    """Per texture, its mip levels: float32 (N, N), N = 1024, 512, ..., 4.

    Level 0 is the photograph high-passed, normalized to zero mean and unit std, and mirrored
    into a 1024 x 1024 tile that wraps around without seams.
    """
    out = []
    for name, digest in TEXTURES.items():
        path = TEXTURE_DIR / f"{name}.png"
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != digest:
            raise ValueError(f"{path}: not the texture the generator was made for (sha256)")
        x = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE).astype(np.float32)
        x -= cv2.GaussianBlur(x, (0, 0), HIGH_PASS_SIGMA, borderType=cv2.BORDER_REFLECT)
        tile = np.block([[x, x[:, ::-1]], [x[::-1], x[::-1, ::-1]]])
        tile = (tile - tile.mean()) / tile.std()
        levels = [tile.astype(np.float32)]
        while levels[-1].shape[0] > 4:
            n = levels[-1].shape[0] // 2
            levels.append(cv2.resize(levels[-1], (n, n), interpolation=cv2.INTER_AREA))
        out.append(tuple(levels))
    return tuple(out)


def sample(texture: int, a, b, metres: float, pixel_metres) -> np.ndarray:
    """(n,) float32 detail of photograph ``texture`` at surface coordinates ``(a, b)`` (metres).

    Args:
      texture: index into :data:`NAMES`.
      a, b: (n,) coordinates along the texture's width / height (metres).
      metres: how many metres one photograph spans.
      pixel_metres: (n,) size of the pixel's footprint on the surface (metres).
    """
    levels = pyramids()[texture]
    size0 = levels[0].shape[0]
    texels_per_metre = size0 / (2.0 * metres)  # (the mirrored tile holds the photograph twice)
    footprint = np.maximum(np.asarray(pixel_metres, np.float32) * texels_per_metre, 1.0)
    level = np.minimum(np.floor(np.log2(footprint)).astype(np.int32), len(levels) - 1)
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    out = np.empty(a.shape, np.float32)
    for k in np.unique(level):
        sel = np.flatnonzero(level == k)
        tile = levels[k]
        scale = np.float32(texels_per_metre / 2**k)
        mask = tile.shape[0] - 1
        ia = np.floor(a[sel] * scale).astype(np.int64) & mask
        ib = np.floor(b[sel] * scale).astype(np.int64) & mask
        out[sel] = tile[ib, ia]
    return out


def _log_uniform(rng: np.random.Generator, lo_hi) -> float:
    return float(np.exp(rng.uniform(np.log(lo_hi[0]), np.log(lo_hi[1]))))


def photo_params(rng: np.random.Generator, texture: int, metres_range) -> tuple:
    """A solid's or verge's draw: texture, metres per photograph, contrast, offsets (m)."""
    return (
        float(texture),
        _log_uniform(rng, metres_range),
        float(rng.uniform(*CONTRAST)),
        float(rng.uniform(0.0, 100.0)),
        float(rng.uniform(0.0, 100.0)),
    )


def photo_background(background: list[shapes.Solid], road, rng: np.random.Generator, share):
    """The background solids and road, with photo textures in a ``share`` of the calls.

    Args:
      background: the scene's background solids (road frame).
      road: the scene's :class:`~gac_jax.data.synthetic.scene.Road`.
      rng: the frame's photo-texture stream.
      share: probability in [0, 1] that this frame gets photo textures at all.

    Returns:
      ``(background, road)``: new objects (the inputs are not modified); the same objects when
      the frame draws none. Foliage and rough faces become :data:`shapes.PHOTO` faces whose
      ``params`` are :func:`photo_params` plus 1 for foliage (0 for rough); the road gets
      ``verge_photo`` (grass).
    """
    if share <= 0.0 or rng.random() >= share:
        return background, road
    out = []
    for solid in background:
        foliage = solid.materials == shapes.FOLIAGE
        rough = solid.materials == shapes.ROUGH
        # (solids whose other faces need their params, like facades, keep their look)
        if not (foliage.any() or rough.any()) or solid.params:
            out.append(solid)
            continue
        is_foliage = bool(foliage.any())
        likely = GRASS if is_foliage else GRAVEL
        texture = likely if rng.random() < 0.7 else 1 - likely
        params = photo_params(rng, texture, FOLIAGE_METRES if is_foliage else ROUGH_METRES)
        materials = np.where(foliage | rough, shapes.PHOTO, solid.materials)
        out.append(
            dataclasses.replace(solid, materials=materials, params=(*params, float(is_foliage)))
        )
    road = dataclasses.replace(road, verge_photo=photo_params(rng, GRASS, VERGE_METRES))
    return out, road
