"""Camera effects as a training augmentation: what differs between cameras and days.

The generated dataset has one camera model; real cameras add their own tone curve, white
balance, defocus, sensor noise and compression. :class:`CameraEffects` draws these per
training image (each with its own probability) so that the detector does not learn one
camera's pixel statistics. It changes only the pixels: the image size, ``P2``, the labels
and every other field of a sample are passed through unchanged.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

Sample = dict


@dataclasses.dataclass
class CameraEffects:
    """Random gamma, white balance, (contrast, sharpening,) blur, noise and JPEG on 0-255 RGB.

    Input: ``sample["image"]`` (H, W, 3) uint8 or float in [0, 255]; output float32 of the
    same shape, clipped to [0, 255]. The generator is ``sample["rng"]`` when present (the
    loader's per-sample stream), else this transform's own (``seed``).

    Attributes:
      gamma: range of the tone curve's exponent ``out = 255 (in / 255)^g``, with ``p_gamma``.
      white_balance: range of each channel's gain, with ``p_white_balance``.
      blur_sigma: Gaussian blur sigma range (pixels of the network input), with ``p_blur``.
      noise_std: range of the std of additive Gaussian noise (grey levels), with ``p_noise``.
      jpeg_quality: range of the JPEG quality the image is re-encoded at, with ``p_jpeg``.
      contrast: range of the gain on each pixel's difference from the image mean, with
        ``p_contrast`` (default 0: off).
      sharpen: range of the unsharp mask's amount ``out = in + a (in - blur(in, s))``, with
        ``sharpen_sigma`` the range of ``s`` (pixels) and ``p_sharpen`` (default 0: off).
        Contrast and sharpening push the generated world's smooth, soft pixels towards a real
        camera's (its verges hold about twice the fine detail and contrast). They draw their
        random numbers only when on, so with both off every draw is as it was without them.
    """

    gamma: tuple[float, float] = (0.7, 1.4)
    p_gamma: float = 0.5
    white_balance: tuple[float, float] = (0.85, 1.15)
    p_white_balance: float = 0.5
    blur_sigma: tuple[float, float] = (0.3, 1.2)
    p_blur: float = 0.3
    noise_std: tuple[float, float] = (1.0, 6.0)
    p_noise: float = 0.3
    jpeg_quality: tuple[int, int] = (30, 90)
    p_jpeg: float = 0.3
    contrast: tuple[float, float] = (1.0, 1.8)
    p_contrast: float = 0.0
    sharpen: tuple[float, float] = (0.5, 2.0)
    sharpen_sigma: tuple[float, float] = (0.7, 1.5)
    p_sharpen: float = 0.0
    seed: int | None = None

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def __call__(self, sample: Sample) -> Sample:
        rng = sample.get("rng")
        rng = self._rng if rng is None else rng
        img = np.asarray(sample["image"], np.float32)
        # every draw is made whether or not the effect applies (a fixed number per image)
        draws = rng.random(5)
        g = rng.uniform(*self.gamma)
        gains = rng.uniform(*self.white_balance, size=3).astype(np.float32)
        sigma = rng.uniform(*self.blur_sigma)
        std = rng.uniform(*self.noise_std)
        quality = int(rng.integers(self.jpeg_quality[0], self.jpeg_quality[1] + 1))
        detail = self.p_contrast > 0 or self.p_sharpen > 0
        if detail:  # (only when on: with both off every draw stays as it was)
            draws2 = rng.random(2)
            c = rng.uniform(*self.contrast)
            amount = rng.uniform(*self.sharpen)
            radius = rng.uniform(*self.sharpen_sigma)
        if draws[0] < self.p_gamma:
            img = np.float32(255.0) * (np.clip(img, 0.0, 255.0) / np.float32(255.0)) ** np.float32(
                g
            )
        if draws[1] < self.p_white_balance:
            img = img * gains
        if detail and draws2[0] < self.p_contrast:
            mean = img.mean()
            img = np.clip(mean + np.float32(c) * (img - mean), 0.0, 255.0)
        if detail and draws2[1] < self.p_sharpen:
            soft = cv2.GaussianBlur(img, (0, 0), float(radius))
            img = np.clip(img + np.float32(amount) * (img - soft), 0.0, 255.0)
        if draws[2] < self.p_blur:
            img = cv2.GaussianBlur(img, (0, 0), float(sigma))
        if draws[3] < self.p_noise:
            img = img + rng.normal(0.0, std, img.shape).astype(np.float32)
        img = np.clip(img, 0.0, 255.0)
        if draws[4] < self.p_jpeg:
            ok, buf = cv2.imencode(
                ".jpg", np.round(img).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality]
            )
            if ok:  # (RGB order is kept: the codec treats the channels alike but for chroma)
                img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).astype(np.float32)
        return {**sample, "image": img.astype(np.float32)}


def from_config(data) -> CameraEffects:
    """The training images' camera effects of a config's ``data`` block.

    ``sharpen_contrast`` (bool) turns on contrast and sharpening, each on a
    ``sharpen_contrast_share`` of the images (default 0.8), with the ranges
    ``contrast_range`` and ``sharpen_range`` (defaults as :class:`CameraEffects`). Keys absent
    from older run folders take these defaults.
    """
    if not data.get("sharpen_contrast", False):
        return CameraEffects()
    share = float(data.get("sharpen_contrast_share", 0.8))
    return CameraEffects(
        p_contrast=share,
        p_sharpen=share,
        contrast=tuple(data.get("contrast_range", CameraEffects.contrast)),
        sharpen=tuple(data.get("sharpen_range", CameraEffects.sharpen)),
    )
