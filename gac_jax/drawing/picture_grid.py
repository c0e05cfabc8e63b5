"""Pictures laid out and written: a grid of captioned pictures, a checked PNG writer."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence

import cv2
import numpy as np

from gac_jax.data.files import write_png

Color = tuple[int, int, int]


def check_image(image: np.ndarray) -> np.ndarray:
    """``image`` if it is an (H, W, 3) uint8 RGB picture; ValueError otherwise."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {image.dtype} {image.shape}")
    return image


def image_grid(
    images: Sequence[np.ndarray],
    captions: Sequence[str] | None = None,
    columns: int = 1,
    *,
    pad: int = 4,
    caption_height: int = 18,
    background: Color = (0, 0, 0),
) -> np.ndarray:
    """Tiles pictures row by row into one RGB uint8 picture.

    Every cell is as large as the largest picture (smaller ones centred); with
    captions each cell has a ``caption_height`` strip of text above it. The
    result is ``(rows * (Hc + caption) + (rows + 1) * pad, columns * Wc +
    (columns + 1) * pad, 3)`` with ``rows = ceil(N / columns)``.

    Args:
      images: (H, W, 3) uint8 RGB or (H, W) uint8 grey pictures.
      captions: one string per picture, or None.
      columns: cells per row.
    """
    if not images:
        raise ValueError("image_grid needs at least one image")
    if captions is not None and len(captions) != len(images):
        raise ValueError(f"{len(captions)} captions for {len(images)} images")
    if columns < 1:
        raise ValueError(f"columns must be >= 1, got {columns}")
    pics = []
    for im in images:
        im = np.asarray(im)
        if im.ndim == 2 and im.dtype == np.uint8:
            im = np.repeat(im[..., None], 3, axis=2)
        pics.append(check_image(im))
    cell_h = max(p.shape[0] for p in pics)
    cell_w = max(p.shape[1] for p in pics)
    strip = caption_height if captions is not None else 0
    columns = min(columns, len(pics))
    rows = math.ceil(len(pics) / columns)
    out = np.empty(
        (rows * (cell_h + strip) + (rows + 1) * pad, columns * cell_w + (columns + 1) * pad, 3),
        np.uint8,
    )
    out[:] = background
    for k, pic in enumerate(pics):
        r, c = divmod(k, columns)
        top = pad + r * (cell_h + strip + pad)
        left = pad + c * (cell_w + pad)
        if captions is not None:
            org = (left + 2, top + strip - 5)
            cv2.putText(
                out,
                str(captions[k]),
                org,
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45,
                (255,) * 3,
                1,
                cv2.LINE_AA,
            )
        y = top + strip + (cell_h - pic.shape[0]) // 2
        x = left + (cell_w - pic.shape[1]) // 2
        out[y : y + pic.shape[0], x : x + pic.shape[1]] = pic
    return out


def save_image(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Writes an RGB uint8 picture as PNG (atomically)."""
    write_png(path, check_image(rgb))
