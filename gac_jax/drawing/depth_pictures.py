"""Pictures of depth maps: colourised depth and the image | prediction | ground-truth panel
that the depth evaluator writes (RGB uint8, depth in metres)."""

from __future__ import annotations

import functools

import cv2
import numpy as np

from gac_jax.drawing.picture_grid import check_image, image_grid


@functools.cache
def _colormap_lut(colormap: int) -> np.ndarray:
    """(256, 3) RGB table of an OpenCV colour map."""
    ramp = np.arange(256, dtype=np.uint8).reshape(256, 1)
    return cv2.cvtColor(cv2.applyColorMap(ramp, colormap), cv2.COLOR_BGR2RGB)[:, 0]


def colorize_depth(
    depth: np.ndarray,
    *,
    min_depth: float = 1.0,
    max_depth: float = 80.0,
    scale: str = "log",
    colormap: int = cv2.COLORMAP_MAGMA,
    dilate: int = 0,
    lowest_index: int = 24,
) -> np.ndarray:
    """Colours an (H, W) depth map (metres; <= 0, NaN or inf = invalid) as RGB uint8.

    Near is bright: the colour-map index grows with ``-log(depth)`` (``scale =
    'log'``, default: spreads 5-80 m street scenes well) or ``1/depth``
    (``'inverse'``, the disparity view) over the fixed range
    ``[min_depth, max_depth]`` (values outside are clamped), so pictures of
    different frames compare. Indices start at ``lowest_index`` so that the
    farthest valid depth is never confused with the black of invalid pixels.

    Args:
      dilate: odd kernel size (pixels) to grow sparse ground truth; where
        points compete the nearest wins (max filter on inverse depth).
    """
    d = np.asarray(depth, np.float64)
    if d.ndim != 2:
        raise ValueError(f"expected an (H, W) depth map, got shape {d.shape}")
    if not 0 < min_depth < max_depth:
        raise ValueError(f"need 0 < min_depth < max_depth, got {min_depth}, {max_depth}")
    valid = np.isfinite(d) & (d > 0)
    if dilate > 1:
        inv = np.where(valid, 1.0 / np.where(valid, d, 1.0), 0.0).astype(np.float32)
        inv = cv2.dilate(inv, np.ones((dilate, dilate), np.uint8))
        valid = inv > 0
        d = np.where(valid, 1.0 / np.where(valid, inv, 1.0), 0.0)
    dc = np.clip(np.where(valid, d, max_depth), min_depth, max_depth)
    if scale == "inverse":
        t = (1.0 / dc - 1.0 / max_depth) / (1.0 / min_depth - 1.0 / max_depth)
    elif scale == "log":
        t = (np.log(max_depth) - np.log(dc)) / (np.log(max_depth) - np.log(min_depth))
    else:
        raise ValueError(f"scale must be 'inverse' or 'log', got {scale!r}")
    index = np.round(lowest_index + t * (255 - lowest_index)).astype(np.int64)
    out = _colormap_lut(colormap)[index]
    out[~valid] = 0
    return out


def depth_panel(
    image: np.ndarray,
    prediction: np.ndarray,
    ground_truth: np.ndarray | None = None,
    *,
    min_depth: float = 1.0,
    max_depth: float = 80.0,
    scale: str = "log",
    gt_dilate: int = 3,
    columns: int = 1,
) -> np.ndarray:
    """Image | predicted depth | sparse ground truth (dilated), tiled with captions.

    Depth maps of another size than the image are resized to it (nearest).
    With ``columns = 1`` (default, suits wide KITTI frames) the panels stack
    vertically.
    """
    image = check_image(image)
    size = image.shape[1], image.shape[0]

    def panel(depth, dilate):
        pic = colorize_depth(
            depth, min_depth=min_depth, max_depth=max_depth, scale=scale, dilate=dilate
        )
        if pic.shape[:2] != image.shape[:2]:
            pic = cv2.resize(pic, size, interpolation=cv2.INTER_NEAREST)
        return pic

    rng = f"{min_depth:g}-{max_depth:g} m, {scale}"
    pics = [image, panel(prediction, 0)]
    captions = ["image", f"prediction ({rng})"]
    if ground_truth is not None:
        pics.append(panel(ground_truth, gt_dilate))
        captions.append(f"ground truth ({rng})")
    return image_grid(pics, captions, columns)
