"""KITTI depth-prediction metrics, as the KITTI depth devkit (``evaluate_depth.cpp``) defines them.

Per image, over the pixels with valid ground truth (``gt > 0``; the 16-bit
PNG value 0 marks "no measurement"), with ``p`` the prediction and ``g`` the
ground truth in metres and ``d = ln p - ln g``:

=========  =====================================  ==============================
key        definition                             unit (KITTI leaderboard)
=========  =====================================  ==============================
silog      sqrt(mean(d^2) - mean(d)^2)            100 * log(m)
sq_rel     mean(((p - g) / g)^2)                  percent
abs_rel    mean(|p - g| / g)                      percent
irmse      sqrt(mean((1/g - 1/p)^2))              1/km
imae       mean(|1/g - 1/p|)                      1/km
rmse       sqrt(mean((p - g)^2))                  mm
mae        mean(|p - g|)                          mm
delta<k>   fraction with max(p/g, g/p) < 1.25^k   percent (k = 1, 2, 3)
=========  =====================================  ==============================

The dataset value of each metric is the mean of the per-image values (the
devkit averages its per-image error vectors), not a pixel-weighted mean.

Differences from the python port in visualDet3D (``evaluate_depth.py``): it
keeps pixels with ``gt > 0.01 m`` (dropping the PNG values 1 and 2) and
reports unscaled values; we keep every ``gt > 0`` pixel as the devkit does and
report leaderboard units. We compute in float64 (the devkit uses float32
accumulators), and clamp the SILog variance at 0 against rounding.
"""

from __future__ import annotations

import numpy as np

DEPTH_METRICS = (
    "silog",
    "sq_rel",
    "abs_rel",
    "irmse",
    "imae",
    "rmse",
    "mae",
    "delta1",
    "delta2",
    "delta3",
)
DEPTH_UNITS = {
    "silog": "100 log(m)",
    "sq_rel": "%",
    "abs_rel": "%",
    "irmse": "1/km",
    "imae": "1/km",
    "rmse": "mm",
    "mae": "mm",
    "delta1": "%",
    "delta2": "%",
    "delta3": "%",
}


def depth_metrics(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """Metrics of one depth map.

    Args:
      pred: (H, W) predicted depth, metres; must be finite and > 0 wherever ``gt > 0``.
      gt: (H, W) ground-truth depth, metres; 0 (or any value <= 0) = invalid.

    Returns:
      ``{key: value}`` for every key of ``DEPTH_METRICS``, in the units above.

    Raises:
      ValueError: shapes differ, no valid ground-truth pixel, or a prediction
        at a valid pixel is not a finite positive number.
    """
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} differs from ground truth {gt.shape}")
    valid = gt > 0
    n = int(valid.sum())
    if n == 0:
        raise ValueError("ground truth has no valid (> 0) pixel")
    p, g = pred[valid], gt[valid]
    bad = ~(np.isfinite(p) & (p > 0))
    if bad.any():
        raise ValueError(
            f"prediction must be finite and > 0 where the ground truth is valid; "
            f"{int(bad.sum())} of {n} such pixels are not (e.g. value {p[bad][0]!r})"
        )
    err = p - g
    d = np.log(p) - np.log(g)
    inv = 1.0 / g - 1.0 / p
    ratio = np.maximum(p / g, g / p)
    mean_d = d.mean()
    return {
        "silog": 100.0 * float(np.sqrt(max(np.mean(d * d) - mean_d * mean_d, 0.0))),
        "sq_rel": 100.0 * float(np.mean((err / g) ** 2)),
        "abs_rel": 100.0 * float(np.mean(np.abs(err) / g)),
        "irmse": 1000.0 * float(np.sqrt(np.mean(inv * inv))),
        "imae": 1000.0 * float(np.mean(np.abs(inv))),
        "rmse": 1000.0 * float(np.sqrt(np.mean(err * err))),
        "mae": 1000.0 * float(np.mean(np.abs(err))),
        "delta1": 100.0 * float(np.mean(ratio < 1.25)),
        "delta2": 100.0 * float(np.mean(ratio < 1.25**2)),
        "delta3": 100.0 * float(np.mean(ratio < 1.25**3)),
    }


class DepthMetricAccumulator:
    """Averages :func:`depth_metrics` over images (each image weighs the same, as the devkit)."""

    def __init__(self):
        self._values: dict[str, list[float]] = {k: [] for k in DEPTH_METRICS}

    @property
    def count(self) -> int:
        return len(self._values["silog"])

    def update(self, pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
        """Adds one image; returns its metrics."""
        metrics = depth_metrics(pred, gt)
        for k in DEPTH_METRICS:
            self._values[k].append(metrics[k])
        return metrics

    def result(self) -> dict[str, float]:
        """Mean of every metric over the images added so far."""
        if self.count == 0:
            raise ValueError("no image was added")
        return {k: float(np.mean(v)) for k, v in self._values.items()}


def format_depth_table(metrics: dict[str, float], num_images: int | None = None) -> str:
    """Readable one-metric-per-line table of :class:`DepthMetricAccumulator` results."""
    title = "KITTI depth prediction"
    if num_images is not None:
        title += f" ({num_images} images)"
    lines = [title]
    for k in DEPTH_METRICS:
        lines.append(f"  {k:<8} {metrics[k]:>10.4f}  {DEPTH_UNITS[k]}")
    return "\n".join(lines) + "\n"
