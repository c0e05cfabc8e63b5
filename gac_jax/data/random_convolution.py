"""Random convolutions as a training augmentation: the same shapes under random local textures.

A network trained on a rendered world learns that world's textures and colours as much as its
shapes, and a real camera's textures are not the renderer's. Filtering a training image with a
convolution whose weights are drawn at random for each image (RandConv: Xu, Liu, Wang and
Niethammer, "Robust and Generalizable Visual Representation Learning via Random Convolutions",
ICLR 2021) keeps every edge and silhouette where it was and changes what the surfaces between
them look like: a 1x1 kernel mixes the colour channels at random (including negative mixes), a
3x3 to 7x7 kernel also filters the local texture. Blending the result with the image by a
random weight gives every strength between none and full.

:class:`RandomConvolution` changes pixels only: the image size, ``P2``, the labels and the depth
map pass through.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from gac_jax.config import share_of_images

Sample = dict


def random_filter(image: np.ndarray, weights: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Filters an (H, W, 3) float image with ``weights`` (3 out, 3 in, k, k), then moves each
    output channel to the mean and standard deviation of the same input channel.

    The filter is a correlation with reflected borders (``cv2.BORDER_REFLECT_101``: no dark
    frame at the borders); a constant output channel stays at the input channel's mean.
    Returns (H, W, 3) float32.
    """
    x = np.asarray(image, np.float32)
    out_ch, in_ch = weights.shape[:2]
    y = np.zeros(x.shape[:2] + (out_ch,), np.float32)
    for o in range(out_ch):
        for i in range(in_ch):
            kernel = np.ascontiguousarray(weights[o, i], dtype=np.float32)
            y[..., o] += cv2.filter2D(x[..., i], -1, kernel, borderType=cv2.BORDER_REFLECT_101)
    mean_x, std_x = x.mean((0, 1)), x.std((0, 1))
    mean_y, std_y = y.mean((0, 1)), y.std((0, 1))
    return ((y - mean_y) / np.maximum(std_y, eps) * std_x + mean_x).astype(np.float32)


@dataclasses.dataclass
class RandomConvolution:
    """Filter a share ``p`` of the images with a random convolution, blended with the image.

    Input: ``sample["image"]`` (H, W, 3) uint8 or float, 0-255 RGB; output float32 of the same
    shape, in [0, 255]. For an image it draws: a kernel size ``k`` from ``kernel_sizes``; weights
    (3, 3, k, k) from N(0, 1 / (3 k^2)) (He's initialisation for the fan-in); the filtered image
    (:func:`random_filter`: each channel keeps its mean and spread); a weight ``a`` from ``mix``;
    and returns ``a * image + (1 - a) * filtered``. The generator is ``sample["rng"]`` when
    present (the loader's per-sample stream), else this transform's own (``seed``).

    Attributes:
      p: share of the images filtered.
      kernel_sizes: odd kernel sizes drawn from, with equal chances.
      mix: range of the image's own weight in the blend (0: the filtered image alone).
    """

    p: float = 0.5
    kernel_sizes: tuple[int, ...] = (1, 3, 5, 7)
    mix: tuple[float, float] = (0.0, 1.0)
    seed: int | None = None

    def __post_init__(self):
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"random convolution share p={self.p} is not in [0, 1]")
        if not self.kernel_sizes or any(k < 1 or k % 2 == 0 for k in self.kernel_sizes):
            raise ValueError(f"kernel sizes {self.kernel_sizes} must be odd and >= 1")
        self._rng = np.random.default_rng(self.seed)

    def __call__(self, sample: Sample) -> Sample:
        rng = sample.get("rng")
        rng = self._rng if rng is None else rng
        img = np.asarray(sample["image"], np.float32)
        if rng.random() >= self.p:
            return {**sample, "image": img}
        k = int(self.kernel_sizes[int(rng.integers(len(self.kernel_sizes)))])
        weights = rng.normal(0.0, 1.0 / np.sqrt(3.0 * k * k), (3, 3, k, k))
        a = float(rng.uniform(*self.mix))
        out = a * img + (1.0 - a) * random_filter(img, weights)
        return {**sample, "image": np.clip(out, 0.0, 255.0).astype(np.float32)}


def from_config(data) -> RandomConvolution | None:
    """The random-convolution augmentation of a config's ``data`` block, or None when
    ``data.random_convolution`` (the share of training images filtered) is 0 or absent.

    Raises:
      ConfigError: the share is not in [0, 1].
    """
    share = share_of_images(data, "random_convolution")
    if share == 0.0:
        return None
    return RandomConvolution(p=share)
