"""Pictures of a detector's results: camera view (3D and 2D boxes, ground truth) + bird's-eye view.

One picture per frame, ``<out_dir>/<frame_id>.png``: the original image with
predicted 3D wireframes, 2D boxes and scores over the ground truth (green,
evaluated classes only), and beside it a bird's-eye view of the same boxes as
tall as the image; plus ``<out_dir>/grid.png`` tiling the frames with captions.
Written by the trainer at every evaluation (``config.eval.num_pictures``), by
``evaluate.py --save-images K`` and by ``python -m gac_jax.cli.predict``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data import transforms
from gac_jax.data.kitti import KittiObjects, read_label
from gac_jax.drawing import boxes, picture_grid

BEV_X_RANGE = (-30.0, 30.0)
BEV_Z_RANGE = (0.0, 70.0)
GRID_MAX_WIDTH = 960  # pixels of one cell of grid.png


def bev_grid_for_height(height: int) -> boxes.BevGrid:
    """A :class:`~gac_jax.drawing.boxes.BevGrid` (x in [-30, 30] m, z in [0, 70] m), ``height``
    pixels tall."""
    ppm = (height - 1) / (BEV_Z_RANGE[1] - BEV_Z_RANGE[0])
    step = 10.0 if ppm >= 3.0 else 20.0
    return boxes.BevGrid(BEV_X_RANGE, BEV_Z_RANGE, pixels_per_metre=ppm, grid_step=step)


def detection_picture(
    image: np.ndarray,
    P2: np.ndarray,
    predictions: KittiObjects | None,
    ground_truth: KittiObjects | None = None,
    *,
    scale: float = 1.0,
) -> np.ndarray:
    """Camera view | bird's-eye view, side by side, drawn into one new picture.

    Args:
      image: (H, W, 3) uint8 RGB original image; P2: (3, 4) its projection.
      predictions, ground_truth: objects in this image's camera frame and pixels.
      scale: size of the picture relative to the image (< 1: the image is shrunk first and
        the boxes drawn on the small one: less to draw and to encode).

    Returns:
      (h, w + Wb, 3) uint8 RGB with ``(h, w) = round(scale (H, W))``, ``Wb`` the width of a
      bird's-eye view ``h`` pixels tall.
    """
    image = picture_grid.check_image(image)
    h, w = image.shape[:2]
    if scale != 1.0:
        size = (max(round(h * scale), 2), max(round(w * scale), 2))
        A = transforms.resize_affine((h, w), size)
        image = cv2.resize(image, size[::-1], interpolation=cv2.INTER_AREA)
        P2 = A @ np.asarray(P2, np.float64)
        predictions, ground_truth = (
            None if o is None else o.replace(bbox=transforms.transform_boxes(o.bbox, A))
            for o in (predictions, ground_truth)
        )
        h, w = size
    grid = bev_grid_for_height(h)
    if grid.size[0] != h:  # rounding of the grid size: drawn apart and resized
        camera = boxes.draw_detections(image, P2, predictions, ground_truth)
        bev = boxes.draw_bev(predictions, ground_truth, grid=grid)
        bev = cv2.resize(bev, (bev.shape[1], h), interpolation=cv2.INTER_AREA)
        return np.concatenate([camera, bev], axis=1)
    out = np.empty((h, w + grid.size[1], 3), np.uint8)
    out[:, :w] = image
    boxes.draw_detections_into(out[:, :w], P2, predictions, ground_truth)
    boxes.draw_bev_into(out[:, w:], predictions, ground_truth, grid)
    return out


def _source_index(source) -> dict[str, int]:
    """Frame id -> index of its left image in ``source``."""
    ids = getattr(source, "frame_ids", None)
    if ids is None:
        ids = [source[i]["frame_id"] for i in range(len(source))]
    return {str(fid): i for i, fid in enumerate(ids)}


def _grid_cell(picture: np.ndarray) -> np.ndarray:
    h, w = picture.shape[:2]
    if w <= GRID_MAX_WIDTH:
        return picture
    size = (GRID_MAX_WIDTH, max(1, round(h * GRID_MAX_WIDTH / w)))
    return cv2.resize(picture, size, interpolation=cv2.INTER_AREA)


def save_pictures(
    source,
    detections: Mapping[str, KittiObjects],
    out_dir: str | os.PathLike,
    class_names: Sequence[str] | None,
    frame_ids: Sequence[str] | None = None,
    grid: bool = True,
) -> list[Path]:
    """Writes :func:`detection_picture` of frames of ``source`` (and ``grid.png``).

    Args:
      source: object source (``source[i]`` gives the original image, ``P2`` and,
        when labelled, ``objects``); frames are found by ``frame_id``.
      detections: frame id -> predicted objects (original-image pixels).
      out_dir: folder of the pictures (created).
      class_names: ground-truth types drawn (None: every type but DontCare).
      frame_ids: frames to draw (default: every frame of ``detections``, sorted).
      grid: also write ``grid.png`` with all pictures, captioned by frame id.

    Returns:
      Paths of the written pictures (``grid.png`` last).
    """
    out_dir = Path(out_dir)
    index = _source_index(source)
    frame_ids = sorted(detections) if frame_ids is None else list(frame_ids)
    written, cells, captions = [], [], []
    for fid in frame_ids:
        sample = source[index[fid]]
        gt = sample.get("objects")
        if gt is not None and class_names is not None:
            gt = gt.select(np.isin(gt.type, list(class_names)))
        pred = detections[fid]
        picture = detection_picture(np.asarray(sample["image"]), sample["P2"], pred, gt)
        path = out_dir / f"{fid}.png"
        picture_grid.save_image(path, picture)
        written.append(path)
        cells.append(_grid_cell(picture))
        n_gt = "" if gt is None else f", {len(gt)} ground truth"
        captions.append(f"{fid}: {len(pred)} detections{n_gt}")
    if grid and cells:
        path = out_dir / "grid.png"
        picture_grid.save_image(path, picture_grid.image_grid(cells, captions, columns=1))
        written.append(path)
    return written


def save_evaluation_pictures(
    source,
    result_dir: str | os.PathLike,
    num_pictures: int,
    class_names: Sequence[str] | None,
    out_dir: str | os.PathLike | None = None,
) -> list[Path]:
    """Pictures of the first ``num_pictures`` frames of ``source`` that have a result file.

    Reads ``result_dir/<frame_id>.txt`` (KITTI result files) and writes to
    ``out_dir`` (default: ``pictures`` beside ``result_dir``). Nothing is
    written when ``num_pictures`` is 0.
    """
    if num_pictures <= 0:
        return []
    result_dir = Path(result_dir)
    out_dir = result_dir.parent / "pictures" if out_dir is None else Path(out_dir)
    chosen: dict[str, KittiObjects] = {}
    for fid in _source_index(source):
        path = result_dir / f"{fid}.txt"
        if path.exists():
            chosen[fid] = read_label(path, with_score=True)
            if len(chosen) == num_pictures:
                break
    return save_pictures(source, chosen, out_dir, class_names, frame_ids=list(chosen))
