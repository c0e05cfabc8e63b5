"""Sample transforms that keep image, calibration, depth map and labels consistent.

A sample is a flat dict (see the project brief): ``image`` (H, W, 3), ``P2``
(3, 4) of that image, ``objects`` (:class:`KittiObjects`, optional), ``depth``
(H, W) metres with 0 = invalid (optional), ``image_transform`` (3, 3) and
``original_size`` (H0, W0). Transforms return a new dict; they never modify
their input's arrays in place.

Geometric ops are 3x3 image affines ``A`` on pixel-centre coordinates (pixel
``i`` has its centre at ``i``): a pixel at ``(u, v)`` moves to
``A @ [u, v, 1]``. Each op applies ``A`` to the image, to ``P2`` (``P2' = A @
P2``), to the 2D boxes, and accumulates it into ``image_transform`` (``A @
image_transform``), which therefore maps ORIGINAL pixels to current ones.

* crop of the top ``r`` rows: ``v' = v - r``;
* resize ``(H, W) -> (H', W')`` with ``cv2.resize``: ``u' = sx (u + 0.5) - 0.5``
  with ``sx = W'/W`` (likewise ``v`` with ``sy = H'/H``): exactly the sampling
  grid cv2 uses, so projected labels land on the resized content (the
  reference scales ``P2`` by ``s`` without the half-pixel term, a < 0.2 px shift);
  ``Resize(calibration='authors')`` instead applies the authors' ``diag(s, s, 1)`` with
  ``s = H'/H`` to ``P2``, the boxes and ``image_transform`` (the pixels are resampled as
  before): for KITTI's 375x1242 -> 288x1301 that is fx scaled by 288/275 instead of 1301/1242
  (0.167 px, 2.2e-4 relative), the P2 their released weights were trained with;
* crop/pad on the right: identity; crop of ``c`` columns on the left: ``u' = u - c``;
* horizontal flip of width ``W``: ``u' = W - 1 - u``, and the 3D scene is mirrored
  (``x -> -x``) so ``P2' = F @ P2 @ diag(-1, 1, 1, 1)`` and the ground ``plane``
  ``(a, b, c, d)`` becomes ``(-a, b, c, d)``.

Crops and resizes change pixels only, not the 3D camera frame, so they leave the optional
``plane`` (4,) (camera frame, :func:`gac_jax.geometry.normalize_plane`) as it is.

Random transforms draw from ``sample['rng']`` (a ``np.random.Generator`` the
loader seeds from (seed, epoch, index)) and fall back to their own generator
(``seed`` argument) when the sample has none.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from gac_jax import geometry
from gac_jax.data.kitti import KittiObjects

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
DONTCARE = "DontCare"

Sample = dict
Transform = Callable[[Sample], Sample]


def translation(du: float, dv: float) -> np.ndarray:
    """3x3 affine ``u' = u + du, v' = v + dv``."""
    return np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]])


RESIZE_CALIBRATIONS = ("grid", "authors")


def resize_affine(src_size: tuple[int, int], dst_size: tuple[int, int]) -> np.ndarray:
    """3x3 affine of ``cv2.resize`` from ``(H, W)`` to ``(H', W')``: ``u' = sx (u + 0.5) - 0.5``."""
    sy, sx = dst_size[0] / src_size[0], dst_size[1] / src_size[1]
    return np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])


def authors_resize_affine(src_size: tuple[int, int], dst_size: tuple[int, int]) -> np.ndarray:
    """The reference's calibration update of a resize: ``diag(s, s, 1)``, ``s = H'/H`` (one
    scale for both axes, no half-pixel term), whatever the new width."""
    s = dst_size[0] / src_size[0]
    return np.diag([s, s, 1.0])


def flip_affine(width: int) -> np.ndarray:
    """3x3 affine of a horizontal flip of an image ``width`` pixels wide: ``u' = W - 1 - u``."""
    return np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def transform_boxes(boxes: np.ndarray, A: np.ndarray) -> np.ndarray:
    """Maps (N, 4) xyxy boxes through an axis-aligned affine ``A``; returns sorted xyxy (N, 4)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    xs = A[0, 0] * boxes[:, [0, 2]] + A[0, 1] * boxes[:, [1, 3]] + A[0, 2]
    ys = A[1, 0] * boxes[:, [0, 2]] + A[1, 1] * boxes[:, [1, 3]] + A[1, 2]
    return np.stack([xs.min(1), ys.min(1), xs.max(1), ys.max(1)], axis=1)


def warp_depth(
    depth: np.ndarray, A: np.ndarray, out_size: tuple[int, int], mode: str = "scatter"
) -> np.ndarray:
    """Resamples a sparse depth map (0 = invalid) through affine ``A`` without mixing values.

    ``mode='scatter'``: every valid pixel moves to the nearest target pixel
    ``round(A @ [u, v, 1])``; when several land on one pixel the nearest depth
    wins (like the reference's max-pool of inverse depth). Values are never
    interpolated, and a downscaled map keeps a point wherever any fell.
    ``mode='nearest'``: each target pixel takes the source pixel nearest to
    ``A^-1 @ [u', v', 1]`` (exact values, holes where the source has holes).

    Args:
      depth: (H, W) float metres. A: (3, 3). out_size: (H', W').
    Returns:
      (H', W') float32.
    """
    height, width = out_size
    depth = np.asarray(depth, dtype=np.float32)
    out = np.zeros((height, width), np.float32)
    if mode == "scatter":
        v, u = np.nonzero(depth > 0)
        d = depth[v, u]
        u2 = np.rint(A[0, 0] * u + A[0, 1] * v + A[0, 2]).astype(np.int64)
        v2 = np.rint(A[1, 0] * u + A[1, 1] * v + A[1, 2]).astype(np.int64)
        inside = (u2 >= 0) & (u2 < width) & (v2 >= 0) & (v2 < height)
        flat, d = v2[inside] * width + u2[inside], d[inside]
        order = np.lexsort((d, flat))  # by target pixel, nearest first
        flat, d = flat[order], d[order]
        first = np.unique(flat, return_index=True)[1]
        out.reshape(-1)[flat[first]] = d[first]
    elif mode == "nearest":
        inv = np.linalg.inv(A)
        vv, uu = np.mgrid[0:height, 0:width]
        us = np.rint(inv[0, 0] * uu + inv[0, 1] * vv + inv[0, 2]).astype(np.int64)
        vs = np.rint(inv[1, 0] * uu + inv[1, 1] * vv + inv[1, 2]).astype(np.int64)
        ok = (us >= 0) & (us < depth.shape[1]) & (vs >= 0) & (vs < depth.shape[0])
        out[ok] = depth[vs[ok], us[ok]]
    else:
        raise ValueError(f"depth resampling mode must be 'scatter' or 'nearest', got {mode!r}")
    return out


def apply_affine(
    sample: Sample, A: np.ndarray, image: np.ndarray, depth: np.ndarray | None = None
) -> Sample:
    """A copy of ``sample`` with the new image/depth and ``A`` applied to P2, boxes, transform."""
    out = dict(sample)
    out["image"] = image
    if depth is not None:
        out["depth"] = depth
    out["P2"] = A @ np.asarray(sample["P2"], dtype=np.float64)
    out["image_transform"] = A @ np.asarray(sample["image_transform"], dtype=np.float64)
    objects = sample.get("objects")
    if objects is not None and len(objects):
        out["objects"] = objects.replace(bbox=transform_boxes(objects.bbox, A))
    return out


def _rows(x: np.ndarray, start: int, stop: int, pad_top: int = 0) -> np.ndarray:
    x = x[start:stop]
    if pad_top:
        x = np.concatenate([np.zeros((pad_top,) + x.shape[1:], x.dtype), x], axis=0)
    return x


def _cols(x: np.ndarray, start: int, stop: int, pad_right: int = 0) -> np.ndarray:
    x = x[:, start:stop]
    if pad_right:
        pad = np.zeros((x.shape[0], pad_right) + x.shape[2:], x.dtype)
        x = np.concatenate([x, pad], axis=1)
    return x


def _crop_rows(sample: Sample, top: int, keep: int) -> Sample:
    """Keeps rows ``[top, top + keep)``; a negative ``top`` pads zeros above the image."""
    pad = max(-top, 0)
    start, stop = max(top, 0), top + keep
    image = _rows(sample["image"], start, stop, pad)
    depth = _rows(sample["depth"], start, stop, pad) if "depth" in sample else None
    return apply_affine(sample, translation(0.0, -top), image, depth)


def _crop_cols(sample: Sample, left: int, keep: int) -> Sample:
    """Keeps columns ``[left, left + keep)`` (``left >= 0``); pads zeros on the right if short."""
    width = sample["image"].shape[1]
    pad = max(left + keep - width, 0)
    image = _cols(sample["image"], left, left + keep, pad)
    depth = _cols(sample["depth"], left, left + keep, pad) if "depth" in sample else None
    return apply_affine(sample, translation(-left, 0.0), image, depth)


def _rng(sample: Sample, fallback: np.random.Generator) -> np.random.Generator:
    rng = sample.get("rng")
    return fallback if rng is None else rng


@dataclasses.dataclass
class CropTop:
    """Drops the top ``rows`` rows (the reference detector uses 100): ``v' = v - rows``."""

    rows: int

    def __call__(self, sample: Sample) -> Sample:
        height = sample["image"].shape[0]
        if not 0 <= self.rows < height:
            raise ValueError(
                f"CropTop({self.rows}) needs an image taller than that, got H={height}"
            )
        return _crop_rows(sample, self.rows, height - self.rows)


@dataclasses.dataclass
class CropBottomTo:
    """Keeps the bottom ``height`` rows (the depth net's 352); zero-pads shorter images on top."""

    height: int

    def __call__(self, sample: Sample) -> Sample:
        return _crop_rows(sample, sample["image"].shape[0] - self.height, self.height)


@dataclasses.dataclass
class Resize:
    """Resizes to ``height`` x ``width`` (``width=None``: ``round(W * height / H)``, keeps aspect).

    The image is cast to float32 first and resized in float with ``cv2.resize``
    (``interpolation``), as the reference does (``ConvertToFloat`` before its
    ``Resize``): the output is float32 0-255 values, not re-quantised to uint8
    (a uint8 resize rounds every pixel, up to 0.5 grey levels, and cv2's uint8
    path uses 11-bit fixed-point weights). A depth map is resampled with
    :func:`warp_depth` (``depth_mode``), which keeps sparse validity and never
    interpolates depth values.

    ``calibration``: ``'grid'`` (default) moves ``P2``, the boxes and ``image_transform`` by
    the exact sampling grid (:func:`resize_affine`); ``'authors'`` by the reference's
    :func:`authors_resize_affine` (the convention of the released weights; see the module
    doc). The pixels (and a depth map) are resampled on the exact grid either way.
    """

    height: int
    width: int | None = None
    interpolation: int = cv2.INTER_LINEAR
    depth_mode: str = "scatter"
    calibration: str = "grid"

    def __post_init__(self):
        if self.calibration not in RESIZE_CALIBRATIONS:
            raise ValueError(
                f"Resize calibration must be one of {', '.join(RESIZE_CALIBRATIONS)}, "
                f"got {self.calibration!r}"
            )

    def __call__(self, sample: Sample) -> Sample:
        h, w = sample["image"].shape[:2]
        new_w = self.width if self.width is not None else int(round(w * self.height / h))
        A = resize_affine((h, w), (self.height, new_w))
        image = np.asarray(sample["image"], np.float32)
        image = cv2.resize(image, (new_w, self.height), interpolation=self.interpolation)
        depth = None
        if "depth" in sample:
            depth = warp_depth(sample["depth"], A, (self.height, new_w), self.depth_mode)
        if self.calibration == "authors":
            A = authors_resize_affine((h, w), (self.height, new_w))
        return apply_affine(sample, A, image, depth)


@dataclasses.dataclass
class CropOrPadWidth:
    """Crops columns on the right, or zero-pads on the right, to ``width`` (identity affine)."""

    width: int

    def __call__(self, sample: Sample) -> Sample:
        return _crop_cols(sample, 0, self.width)


@dataclasses.dataclass
class RandomCropWidth:
    """Keeps ``width`` columns from a random offset in ``[0, W - width]`` (``u' = u - offset``).

    Narrower images are zero-padded on the right (offset 0). The reference draws
    ``randint(0, W - width)`` with an exclusive bound; here every offset is possible.
    """

    width: int
    seed: int | None = None

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def __call__(self, sample: Sample) -> Sample:
        slack = sample["image"].shape[1] - self.width
        offset = int(_rng(sample, self._rng).integers(0, slack + 1)) if slack > 0 else 0
        return _crop_cols(sample, offset, self.width)


def mirror_objects(objects: KittiObjects) -> KittiObjects:
    """Mirrors 3D labels about the camera's y-z plane.

    ``x -> -x``, ``ry -> pi - ry``, ``alpha -> pi - alpha`` (wrapped to (-pi, pi]).

    DontCare rows (no 3D box) keep their 3D fields. Boxes are not touched here.
    """
    real = objects.type != DONTCARE
    loc = objects.location.copy()
    loc[real, 0] = -loc[real, 0]
    ry = np.where(real, geometry.wrap_angle(np.pi - objects.rotation_y), objects.rotation_y)
    alpha = np.where(real, geometry.wrap_angle(np.pi - objects.alpha), objects.alpha)
    return objects.replace(location=loc, rotation_y=ry, alpha=alpha)


@dataclasses.dataclass
class HorizontalFlip:
    """Mirrors image, depth and the 3D scene (``x -> -x``).

    ``u' = W - 1 - u`` and ``P2' = F @ P2 @ diag(-1, 1, 1, 1)`` with ``F`` that pixel flip; a
    ground ``plane`` ``(a, b, c, d)`` mirrors to ``(-a, b, c, d)``.

    Projecting mirrored labels through ``P2'`` equals flipping the original
    projection, and the optical centre mirrors too, so alpha (relative to the
    current camera) stays consistent with ry. Applying it twice is the identity.
    """

    def __call__(self, sample: Sample) -> Sample:
        image = np.ascontiguousarray(sample["image"][:, ::-1])
        depth = np.ascontiguousarray(sample["depth"][:, ::-1]) if "depth" in sample else None
        out = apply_affine(sample, flip_affine(image.shape[1]), image, depth)
        out["P2"] = out["P2"] @ np.diag([-1.0, 1.0, 1.0, 1.0])
        if "plane" in out:
            out["plane"] = np.asarray(out["plane"], np.float64) * np.array([-1.0, 1.0, 1.0, 1.0])
        if out.get("objects") is not None and len(out["objects"]):
            out["objects"] = mirror_objects(out["objects"])
        return out


@dataclasses.dataclass
class RandomHorizontalFlip:
    """:class:`HorizontalFlip` with probability ``p``."""

    p: float = 0.5
    seed: int | None = None

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def __call__(self, sample: Sample) -> Sample:
        if _rng(sample, self._rng).random() < self.p:
            return HorizontalFlip()(sample)
        return sample


@dataclasses.dataclass
class PhotometricDistort:
    """The reference's photometric distortion on 0-255 RGB; outputs float32.

    Brightness ``+U(-32, 32)``; then, each with probability 0.5, either
    [contrast ``x U(0.5, 1.5)``, saturation ``x U(0.5, 1.5)``, hue ``+U(-18, 18)``
    degrees] or [saturation, hue, contrast]. Hue/saturation use OpenCV's float HSV
    (H in degrees 0-360, S in 0-1, V in the input's range).

    ``clip`` (default False, like the reference, whose network was trained on
    unclipped values) clamps the result to [0, 255].
    """

    brightness_delta: float = 32.0
    contrast: tuple[float, float] = (0.5, 1.5)
    saturation: tuple[float, float] = (0.5, 1.5)
    hue_delta: float = 18.0
    clip: bool = False
    seed: int | None = None

    def __post_init__(self):
        self._rng = np.random.default_rng(self.seed)

    def __call__(self, sample: Sample) -> Sample:
        rng = _rng(sample, self._rng)
        img = np.asarray(sample["image"], dtype=np.float32)
        img = img + np.float32(rng.uniform(-self.brightness_delta, self.brightness_delta))
        contrast_first = rng.random() < 0.5
        alpha = np.float32(rng.uniform(*self.contrast))
        sat = np.float32(rng.uniform(*self.saturation))
        hue = np.float32(rng.uniform(-self.hue_delta, self.hue_delta))
        if contrast_first:
            img = img * alpha
        hsv = cv2.cvtColor(img, cv2.COLOR_RGB2HSV)
        hsv[..., 1] *= sat
        h = hsv[..., 0] + hue
        h = np.where(h > 360.0, h - 360.0, h)
        hsv[..., 0] = np.where(h < 0.0, h + 360.0, h)
        img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        if not contrast_first:
            img = img * alpha
        if self.clip:
            img = np.clip(img, 0.0, 255.0)
        return {**sample, "image": img.astype(np.float32)}


@dataclasses.dataclass
class Normalize:
    """``image -> (image / 255 - mean) / std`` as float32 (mean/std are RGB on the 0-1 scale)."""

    mean: Sequence[float] = IMAGENET_MEAN
    std: Sequence[float] = IMAGENET_STD

    def __call__(self, sample: Sample) -> Sample:
        image = np.asarray(sample["image"], np.float32)
        channels = image.shape[-1]
        # The same three float32 operations per element, on rows of W * C values with the
        # mean/std tiled along them: numpy's loops over a trailing axis of 3 were ~10x slower.
        rows = np.ascontiguousarray(image).reshape(-1, image.shape[-2] * channels)
        reps = rows.shape[1] // channels
        out = rows / np.float32(255.0)
        out -= np.tile(np.asarray(self.mean, np.float32), reps)
        out /= np.tile(np.asarray(self.std, np.float32), reps)
        return {**sample, "image": out.reshape(image.shape)}


@dataclasses.dataclass
class FilterObjects:
    """The reference training filter.

    Keeps ``type in classes``, ``occluded < max_occlusion``, ``z > min_depth``.

    ``None`` disables a criterion. With ``keep_dontcare`` DontCare rows are kept
    regardless of the other criteria.
    """

    classes: Sequence[str]
    max_occlusion: int | None = None
    min_depth: float | None = None
    keep_dontcare: bool = False

    def __call__(self, sample: Sample) -> Sample:
        objects = sample.get("objects")
        if objects is None:
            return sample
        keep = np.isin(objects.type, list(self.classes))
        if self.max_occlusion is not None:
            keep &= objects.occluded < self.max_occlusion
        if self.min_depth is not None:
            keep &= objects.location[:, 2] > self.min_depth
        if self.keep_dontcare:
            keep |= objects.type == DONTCARE
        return {**sample, "objects": objects.select(keep)}


@dataclasses.dataclass
class ReprojectBoxes:
    """Re-derives 2D boxes and alpha from the 3D boxes through the current ``P2`` (reference §1.6).

    ``bbox`` := min/max of the 8 projected corners (edges clipped at the near
    plane; clipped to the image only when ``clip_to_image``, which the reference
    does not do); ``alpha`` := ``ry - atan2(x - Cx, z - Cz)`` with ``C`` the
    optical centre of ``P2``. DontCare rows are left as they are.
    """

    clip_to_image: bool = False

    def __call__(self, sample: Sample) -> Sample:
        objects = sample.get("objects")
        if objects is None or not len(objects):
            return sample
        real = objects.type != DONTCARE
        P2 = np.asarray(sample["P2"], np.float64)
        size = sample["image"].shape[:2] if self.clip_to_image else None
        corners = geometry.box3d_corners(objects.location, objects.dimensions, objects.rotation_y)
        boxes = geometry.box2d_from_corners(corners, P2, image_size=size)
        alpha = geometry.alpha_from_rotation_y(objects.rotation_y, objects.location, P2)
        bbox = np.where(real[:, None], boxes, objects.bbox)
        alpha = np.where(real, alpha, objects.alpha)
        return {**sample, "objects": objects.replace(bbox=bbox, alpha=alpha)}


class DropGroundPlane:
    """Forgets the frame's ``planes/`` ground plane: the loader then gives the config's level
    plane (``camera_height`` below a level camera), as for a frame without a file. The
    "fixed 1.65 m" arm of the ground-plane comparison (``data.use_planes = False``)."""

    def __call__(self, sample: Sample) -> Sample:
        return {k: v for k, v in sample.items() if k != "plane"}


@dataclasses.dataclass
class Compose:
    """Applies ``transforms`` in order."""

    transforms: Sequence[Transform]

    def __call__(self, sample: Sample) -> Sample:
        for t in self.transforms:
            sample = t(sample)
        return sample
