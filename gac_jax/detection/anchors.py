"""Dense 2D anchors of the single stride-16 detection level (numpy, computed once).

Every feature cell ``(row i, col j)`` of the ``ceil(H/16) x ceil(W/16)`` map carries
``A = num_ratios * num_scales`` anchors centred at ``((j + 0.5) * stride, (i + 0.5) * stride)``
in network-input pixels (image frame: u right, v down). Anchor ``a`` of a cell has
``ratio_idx = a // num_scales`` and ``scale_idx = a % num_scales``; its size is
``s = base_size * scales[scale_idx]`` and, with ``r = ratios[ratio_idx]`` (= h / w),
``w = s / sqrt(r)``, ``h = s * sqrt(r)``. The flat anchor index is
``n = (i * Wf + j) * A + a``, the layout of the network's flattened NHWC head outputs.

Each anchor belongs to the (scale, ratio) *bin* ``a``; the per-bin 3D priors
(:mod:`gac_jax.detection.anchor_priors`) are indexed by it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

DEFAULT_SCALES = tuple(2.0 ** (i / 4.0) for i in range(16))


@dataclasses.dataclass(frozen=True)
class AnchorLayout:
    """The shape of the anchor set; everything the anchors (and their priors) depend on.

    Attributes:
      image_size: ``(H, W)`` of the network input in pixels.
      stride: feature stride in pixels (one level).
      base_size: anchor size in pixels at scale 1.
      ratios: anchor aspect ratios ``h / w`` (slow index within a cell).
      scales: size multipliers (fast index within a cell).
    """

    image_size: tuple[int, int]
    stride: int = 16
    base_size: float = 24.0
    ratios: tuple[float, ...] = (0.5, 1.0)
    scales: tuple[float, ...] = DEFAULT_SCALES

    def __post_init__(self):
        size = tuple(int(v) for v in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"image_size must be (H, W) > 0, got {self.image_size!r}")
        if self.stride <= 0 or self.base_size <= 0:
            raise ValueError(
                f"stride and base_size must be > 0, got {self.stride}, {self.base_size}"
            )
        if not self.ratios or not self.scales:
            raise ValueError("ratios and scales must be non-empty")
        if min(self.ratios) <= 0 or min(self.scales) <= 0:
            raise ValueError(f"ratios and scales must be > 0: {self.ratios}, {self.scales}")
        object.__setattr__(self, "image_size", size)
        object.__setattr__(self, "stride", int(self.stride))
        object.__setattr__(self, "base_size", float(self.base_size))
        object.__setattr__(self, "ratios", tuple(float(r) for r in self.ratios))
        object.__setattr__(self, "scales", tuple(float(s) for s in self.scales))

    @property
    def feature_size(self) -> tuple[int, int]:
        """``(Hf, Wf) = (ceil(H / stride), ceil(W / stride))``."""
        h, w = self.image_size
        return math.ceil(h / self.stride), math.ceil(w / self.stride)

    @property
    def num_scales(self) -> int:
        return len(self.scales)

    @property
    def num_ratios(self) -> int:
        return len(self.ratios)

    @property
    def anchors_per_cell(self) -> int:
        """``A = num_ratios * num_scales``, also the number of (scale, ratio) bins."""
        return self.num_ratios * self.num_scales

    @property
    def num_anchors(self) -> int:
        """``N = Hf * Wf * A``."""
        hf, wf = self.feature_size
        return hf * wf * self.anchors_per_cell

    @property
    def sizes(self) -> np.ndarray:
        """(num_scales,) anchor sizes ``base_size * scales`` (pixels)."""
        return self.base_size * np.asarray(self.scales, dtype=np.float64)

    def bin_shapes(self) -> np.ndarray:
        """(A, 2) anchor ``(w, h)`` of every bin ``a = ratio_idx * num_scales + scale_idx``."""
        sizes = self.sizes
        sqrt_r = np.sqrt(np.asarray(self.ratios, dtype=np.float64))
        w = sizes[None, :] / sqrt_r[:, None]
        h = sizes[None, :] * sqrt_r[:, None]
        return np.stack([w.reshape(-1), h.reshape(-1)], axis=-1)

    def to_dict(self) -> dict:
        """JSON/npz-friendly description (inverse: :meth:`from_dict`)."""
        return {
            "image_size": list(self.image_size),
            "stride": self.stride,
            "base_size": self.base_size,
            "ratios": list(self.ratios),
            "scales": list(self.scales),
        }

    @classmethod
    def from_dict(cls, d: dict) -> AnchorLayout:
        return cls(
            image_size=tuple(d["image_size"]),
            stride=d["stride"],
            base_size=d["base_size"],
            ratios=tuple(d["ratios"]),
            scales=tuple(d["scales"]),
        )

    def differences(self, other: AnchorLayout, rtol: float = 1e-6) -> list[str]:
        """Human-readable list of fields where ``other`` differs (empty when equal)."""
        diffs = []
        for key, mine in self.to_dict().items():
            theirs = other.to_dict()[key]
            a, b = np.asarray(mine, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
            if a.shape != b.shape or not np.allclose(a, b, rtol=rtol, atol=0.0):
                diffs.append(f"{key}: {theirs} != {mine}")
        return diffs


@dataclasses.dataclass(frozen=True, eq=False)
class Anchors:
    """All anchors of a layout (numpy, float64).

    Attributes:
      layout: the :class:`AnchorLayout`.
      boxes: (N, 4) xyxy in network-input pixels.
      centers: (N, 2) ``(u, v)`` centres.
      shapes: (N, 2) ``(w, h)``.
      bin_index: (N,) (scale, ratio) bin ``a = ratio_idx * num_scales + scale_idx`` in ``[0, A)``.
      scale_index: (N,) in ``[0, num_scales)``.
      ratio_index: (N,) in ``[0, num_ratios)``.
    """

    layout: AnchorLayout
    boxes: np.ndarray
    centers: np.ndarray
    shapes: np.ndarray
    bin_index: np.ndarray
    scale_index: np.ndarray
    ratio_index: np.ndarray

    def __len__(self) -> int:
        return int(self.boxes.shape[0])


def generate_anchors(layout: AnchorLayout) -> Anchors:
    """Builds the anchors of ``layout`` in the order ``((row * Wf + col) * A + a)``."""
    hf, wf = layout.feature_size
    num_bins = layout.anchors_per_cell
    shapes_per_bin = layout.bin_shapes()  # (A, 2)
    rows, cols = np.meshgrid(np.arange(hf), np.arange(wf), indexing="ij")
    cell_centers = np.stack([(cols + 0.5) * layout.stride, (rows + 0.5) * layout.stride], axis=-1)
    centers = np.repeat(cell_centers.reshape(-1, 2).astype(np.float64), num_bins, axis=0)
    bins = np.tile(np.arange(num_bins), hf * wf)
    shapes = shapes_per_bin[bins]
    boxes = np.concatenate([centers - shapes / 2.0, centers + shapes / 2.0], axis=1)
    return Anchors(
        layout=layout,
        boxes=boxes,
        centers=centers,
        shapes=shapes,
        bin_index=bins.astype(np.int32),
        scale_index=(bins % layout.num_scales).astype(np.int32),
        ratio_index=(bins // layout.num_scales).astype(np.int32),
    )


def nearest_bin(shapes: np.ndarray, layout: AnchorLayout) -> np.ndarray:
    """Bin of boxes with ``(w, h)`` shapes (..., 2) by the reference rule.

    The scale index is the nearest ``sqrt(w * h)`` among the anchor sizes, the
    ratio index the nearest ``h / w`` among the ratios. For generated anchors
    this reproduces :attr:`Anchors.bin_index`.
    """
    shapes = np.asarray(shapes, dtype=np.float64)
    size = np.sqrt(shapes[..., 0] * shapes[..., 1])
    ratio = shapes[..., 1] / shapes[..., 0]
    scale_idx = np.abs(size[..., None] - layout.sizes).argmin(-1)
    ratio_idx = np.abs(ratio[..., None] - np.asarray(layout.ratios)).argmin(-1)
    return (ratio_idx * layout.num_scales + scale_idx).astype(np.int32)


def box_iou_np(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """IoU (N, M) of xyxy boxes (N, 4) and (M, 4) in float64 (union clamped >= 1e-8).

    Continuous-coordinate areas ``(x2 - x1) * (y2 - y1)`` (no +1 pixel convention).
    """
    a = np.asarray(boxes_a, dtype=np.float64)[:, None, :]
    b = np.asarray(boxes_b, dtype=np.float64)[None, :, :]
    iw = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0.0, None)
    ih = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0.0, None)
    inter = iw * ih
    area_a = (a[..., 2] - a[..., 0]) * (a[..., 3] - a[..., 1])
    area_b = (b[..., 2] - b[..., 0]) * (b[..., 3] - b[..., 1])
    return inter / np.maximum(area_a + area_b - inter, 1e-8)
