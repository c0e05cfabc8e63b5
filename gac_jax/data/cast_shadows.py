"""Cast shadows as a training augmentation: dark, bluish patches that are not objects.

Real street frames are full of hard shadows: a building's straight-edged shadow across the
road, the dappled shadow of a tree on a sidewalk. The generated world casts them too, but only
as whole convex hulls on flat ground, so a network trained on it can take a dark, blotchy
region for a near wall or a car. :class:`CastShadows` darkens random regions of a training
image the way the sun's shadow does (the direct light gone, the blue skylight left) and
changes nothing else: the image size, ``P2``, the labels and the depth map pass through.

Shapes, in the image (u right, v down), over the rows below ``top`` (a fraction of the height):

- ``polygon``: a random convex polygon of 3-6 vertices, often reaching an image border (the
  shadow of a building or a wall);
- ``dapple``: coarse random noise, smoothed and cut at a level, inside a random ellipse (the
  shadow of a tree's crown, with sunlit holes).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from gac_jax.config import share_of_images

Sample = dict


def polygon_mask(rng: np.random.Generator, size: tuple[int, int], top: float) -> np.ndarray:
    """(H, W) float32 mask in {0, 1}: a random convex polygon below row ``top * H``.

    The vertices are drawn in a box of 30-100 % of the width and 20-70 % of the height (the
    box may reach past the image's left, right and bottom borders), and their convex hull is
    filled.
    """
    H, W = size
    bw = rng.uniform(0.3, 1.0) * W
    bh = rng.uniform(0.2, 0.7) * H
    u0 = rng.uniform(-0.3 * bw, W - 0.7 * bw)
    v0 = rng.uniform(top * H, H - 0.5 * bh)
    n = int(rng.integers(3, 7))
    pts = np.stack([u0 + rng.uniform(0, bw, n), v0 + rng.uniform(0, bh, n)], axis=1)
    hull = cv2.convexHull(np.round(pts * 4).astype(np.int32))
    mask = np.zeros((H, W), np.float32)
    cv2.fillConvexPoly(mask, hull, 1.0, lineType=cv2.LINE_AA, shift=2)
    return mask


def dapple_mask(rng: np.random.Generator, size: tuple[int, int], top: float) -> np.ndarray:
    """(H, W) float32 mask in [0, 1]: a tree crown's dappled shadow below row ``top * H``.

    Uniform noise on a coarse grid (cells of 2-8 % of the width) resized bicubically to the
    image, kept where it exceeds a level drawn so that 40-80 % of the ellipse is in shadow;
    the ellipse (semi-axes 10-40 % of the width and 8-30 % of the height) holds the crown.
    """
    H, W = size
    cell = max(rng.uniform(0.02, 0.08) * W, 1.0)
    gh, gw = max(int(np.ceil(H / cell)), 2), max(int(np.ceil(W / cell)), 2)
    noise = cv2.resize(
        rng.random((gh, gw)).astype(np.float32), (W, H), interpolation=cv2.INTER_CUBIC
    )
    cover = rng.uniform(0.4, 0.8)
    level = np.quantile(noise, 1.0 - cover)
    ellipse = np.zeros((H, W), np.float32)
    centre = (int(rng.uniform(0, W)), int(rng.uniform(top * H, H)))
    axes = (int(rng.uniform(0.1, 0.4) * W) + 1, int(rng.uniform(0.08, 0.3) * H) + 1)
    angle = float(rng.uniform(-30.0, 30.0))
    cv2.ellipse(ellipse, centre, axes, angle, 0.0, 360.0, 1.0, thickness=-1)
    return ellipse * (noise > level).astype(np.float32)


@dataclasses.dataclass
class CastShadows:
    """Darken 1-``max_shadows`` random shadow shapes on a share ``p`` of the images.

    Input: ``sample["image"]`` (H, W, 3) uint8 or float, 0-255 RGB; output float32 of the same
    shape. In a shadow each channel is multiplied by ``min((1 - d) w_c, 1)``: ``d`` the
    shadow's darkness (``darkness``), ``w = (1, 1 + blue / 2, 1 + blue)`` (the skylight that
    lights a shadow is bluer than the sun). Each shadow's edge is softened by a
    Gaussian of sigma ``edge_sigma`` pixels (a penumbra); overlapping shadows do not darken
    twice. The generator is ``sample["rng"]`` when present (the loader's per-sample stream),
    else this transform's own (``seed``).

    Attributes:
      p: share of the images that get shadows.
      max_shadows: 1 to this many shapes per image.
      dapple_share: share of the shapes that are dappled tree shadows (the rest polygons).
      darkness: range of the fraction of the light a shadow removes.
      blue: range of the skylight's extra blue (``w`` above).
      edge_sigma: range of the penumbra's Gaussian sigma (pixels of the image given).
      top: shadows lie below this fraction of the image's height (the ground and what stands
        on it; the sky is left alone).
    """

    p: float = 0.5
    max_shadows: int = 3
    dapple_share: float = 0.5
    darkness: tuple[float, float] = (0.3, 0.7)
    blue: tuple[float, float] = (0.0, 0.3)
    edge_sigma: tuple[float, float] = (0.3, 2.0)
    top: float = 0.25
    seed: int | None = None

    def __post_init__(self):
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"cast shadow share p={self.p} is not in [0, 1]")
        self._rng = np.random.default_rng(self.seed)

    def mask(self, rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
        """(H, W) float32 in [0, 1]: the union of 1-``max_shadows`` soft-edged shapes."""
        out = np.zeros(size, np.float32)
        for _ in range(int(rng.integers(1, self.max_shadows + 1))):
            make = dapple_mask if rng.random() < self.dapple_share else polygon_mask
            shape = make(rng, size, self.top)
            shape = cv2.GaussianBlur(shape, (0, 0), float(rng.uniform(*self.edge_sigma)))
            out = np.maximum(out, shape)
        out[: int(np.ceil(self.top * size[0]))] = 0.0  # (penumbrae and ellipses reach up)
        return out

    def __call__(self, sample: Sample) -> Sample:
        rng = sample.get("rng")
        rng = self._rng if rng is None else rng
        if rng.random() >= self.p:
            return {**sample, "image": np.asarray(sample["image"], np.float32)}
        img = np.asarray(sample["image"], np.float32)
        d = rng.uniform(*self.darkness)
        b = rng.uniform(*self.blue)
        w = np.array([1.0, 1.0 + b / 2, 1.0 + b])
        factor = np.minimum((1.0 - d) * w, 1.0).astype(np.float32)  # the light left in shadow
        m = self.mask(rng, img.shape[:2])[:, :, None]
        out = img * (1.0 - m + m * factor)
        return {**sample, "image": np.clip(out, 0.0, 255.0).astype(np.float32)}


def from_config(data) -> CastShadows | None:
    """The cast-shadow augmentation of a config's ``data`` block, or None when
    ``data.cast_shadows`` (the share of training images that get shadows) is 0 or absent.

    Raises:
      ConfigError: the share is not in [0, 1].
    """
    share = share_of_images(data, "cast_shadows")
    if share == 0.0:
        return None
    return CastShadows(p=share)
