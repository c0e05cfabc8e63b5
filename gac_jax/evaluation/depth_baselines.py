"""A learned-statistics depth baseline: the training split's mean log-depth of each row.

The ground-plane baseline (:class:`~gac_jax.evaluation.depth_evaluator.GroundPlanePredictor`)
uses geometry alone and has no answer above the horizon. The row-mean baseline is the
strongest predictor that is constant along each image row: row ``r`` (counted from the
bottom, so KITTI drives of 370-376 rows line up on the road) gets the geometric mean of
all valid ground-truth depths of that row in the training split, i.e. the constant that
minimises the squared log error of the row. A network has to beat it to show that it
uses the image content, not just the vertical position. Rows without any valid training
pixel take the value of the nearest row that has one.

    python evaluate.py --task depth --baseline row-mean --workdir W   # fitted on W's train split
"""

from __future__ import annotations

import numpy as np

from gac_jax.data.files import KittiFormatError


def fit_row_log_depth(source, max_rows: int = 2048) -> np.ndarray:
    """Mean log-depth of each row over a split's valid ground truth, float64.

    Args:
      source: a depth source with ground truth (``len(source)`` items; see
        :func:`~gac_jax.evaluation.depth_evaluator.ground_truth_depth`).
      max_rows: rows tracked, counted from the bottom of each image.

    Returns:
      ``(R,)`` float64: entry ``r`` is the mean of ``log(z)`` over valid pixels (z > 0) of
      the ``r``-th row from the bottom of every image; ``R`` is the tallest image's height.
    """
    from gac_jax.evaluation.depth_evaluator import ground_truth_depth

    sums = np.zeros(max_rows, np.float64)
    counts = np.zeros(max_rows, np.int64)
    height = 0
    for index in range(len(source)):
        gt = ground_truth_depth(source, index)
        if gt is None:
            raise KittiFormatError(
                getattr(source, "root", "<source>"), "the row-mean baseline needs ground truth"
            )
        gt = np.asarray(gt, np.float64)[::-1][:max_rows]  # row 0 = bottom row
        height = max(height, gt.shape[0])
        valid = gt > 0
        logs = np.where(valid, np.log(np.where(valid, gt, 1.0)), 0.0)
        sums[: gt.shape[0]] += logs.sum(axis=1)
        counts[: gt.shape[0]] += valid.sum(axis=1)
    sums, counts = sums[:height], counts[:height]
    filled = np.flatnonzero(counts)
    if filled.size == 0:
        raise KittiFormatError(
            getattr(source, "root", "<source>"), "no valid ground-truth pixel in the split"
        )
    means = sums[filled] / counts[filled]
    # Nearest filled row for the others (np.interp would blend two rows; take the nearest).
    rows = np.arange(height)
    nearest = filled[np.abs(rows[:, None] - filled[None, :]).argmin(axis=1)]
    return means[np.searchsorted(filled, nearest)]


class RowMeanPredictor:
    """Predicts ``exp(row_log_depth[r])`` for the ``r``-th row from the bottom of each image.

    ``__call__(batch)`` returns B float32 (H, W) maps of each frame's ``original_size``;
    rows above the fitted range repeat the topmost fitted row.
    """

    def __init__(self, row_log_depth: np.ndarray):
        self.row_log_depth = np.asarray(row_log_depth, np.float64)
        if self.row_log_depth.ndim != 1 or self.row_log_depth.size == 0:
            raise ValueError(
                f"row_log_depth must be (R,) with R > 0, got {self.row_log_depth.shape}"
            )

    def depth(self, height: int, width: int) -> np.ndarray:
        """(height, width) float32 metres."""
        from_bottom = np.minimum(np.arange(height)[::-1], self.row_log_depth.size - 1)
        z = np.exp(self.row_log_depth[from_bottom]).astype(np.float32)
        return np.broadcast_to(z[:, None], (height, width)).copy()

    def __call__(self, batch: dict) -> list[np.ndarray]:
        return [self.depth(int(h), int(w)) for h, w in np.asarray(batch["original_size"])]
