"""Per-anchor 3D priors: each (scale, ratio) anchor bin as a distribution of 3D proposals.

The paper ("Priors Extraction from Anchors") iterates over the training set,
collects the objects that overlap an anchor shape strongly and stores, per
anchor shape, the mean and variance of the depth ``z`` and of the orientation
encoding; the 2D-size / depth correlation makes the depth spread of large
anchors (close objects) much smaller than that of small ones. Dimensions get a
class-global mean/std.

Exact procedure (reference implementation, §2.2 of the spec):

* per frame and class ``k``: IoU of all anchors with that class's GT 2D boxes
  (network-input pixels); an anchor whose max IoU is ``> iou_threshold``
  (strictly, default 0.5) adds its argmax GT's ``[z, sin, cos]`` to the anchor's
  bin: count, sum, sum of squares;
* per bin: ``mean = sum / count``, ``std = sqrt(E[x^2] - mean^2)``; a bin is
  *invalid* when ``count < min_count`` (10) or any channel's std is NaN or
  ``< min_std`` (1e-3). (The reference invalidates channels element-wise and
  calls a bin valid iff its z channel survived; here one bad channel
  invalidates the whole bin, which differs only when an angle channel has
  no spread over >= 10 samples.) Invalid bins are marked by :attr:`AnchorPriors.valid`
  and carry the reference sentinels ``mean = -100, std = 1e10`` in the
  effective arrays fed to the network code;
* dimensions ``(h, w, l)``: mean/std over *all* objects of the class (ddof 0).

Angle statistics (``angle_mode``): the paper says ``sin(alpha), cos(alpha)``;
the reference code uses ``sin(2 alpha), cos(2 alpha)`` plus a separate
``1[cos alpha > 0]`` sign bit predicted by the classification head. The head
layout (a sign logit per anchor) follows the reference, so ``"double"``
(reference) is the default; ``"single"`` gives the paper's statistics (the sign
bit is then redundant and ignored when decoding).
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from gac_jax.data.files import atomic_write
from gac_jax.data.kitti import KittiObjects
from gac_jax.detection.anchors import AnchorLayout, Anchors, box_iou_np, generate_anchors

ANGLE_MODES = ("double", "single")
INVALID_MEAN = -100.0  # reference sentinel for bins without usable statistics
INVALID_STD = 1e10
PRIORS_FORMAT_VERSION = 1


class PriorsMismatchError(ValueError):
    """Stored priors do not belong to the requested anchor layout / classes / angle mode."""


def angle_features(alpha: np.ndarray, angle_mode: str = "double") -> tuple[np.ndarray, np.ndarray]:
    """``(sin, cos)`` of ``2 alpha`` ("double", reference) or ``alpha`` ("single", paper)."""
    if angle_mode not in ANGLE_MODES:
        raise ValueError(f"angle_mode must be one of {ANGLE_MODES}, got {angle_mode!r}")
    k = 2.0 if angle_mode == "double" else 1.0
    a = np.asarray(alpha, dtype=np.float64)
    return np.sin(k * a), np.cos(k * a)


@dataclasses.dataclass(frozen=True, eq=False)
class AnchorPriors:
    """Per-class, per-bin anchor statistics (numpy float64). ``K`` classes, ``A`` bins.

    Attributes:
      layout: anchor layout the statistics were computed for.
      class_names: (K,) names; class index ``k`` is the position here.
      angle_mode: ``"double"`` (channels sin 2a, cos 2a) or ``"single"`` (sin a, cos a).
      count: (K, A) matched GT samples per bin.
      mean, std: (K, A, 3) raw statistics of ``[z, sin, cos]`` (NaN where count = 0).
      valid: (K, A) bins usable for regression (see module docstring).
      dims_mean, dims_std: (K, 3) class-global ``(h, w, l)`` statistics in metres.
      num_objects: (K,) objects seen per class.
      num_frames: frames iterated.
      iou_threshold, min_count, min_std: the settings used.
    """

    layout: AnchorLayout
    class_names: tuple[str, ...]
    angle_mode: str
    count: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    valid: np.ndarray
    dims_mean: np.ndarray
    dims_std: np.ndarray
    num_objects: np.ndarray
    num_frames: int
    iou_threshold: float = 0.5
    min_count: int = 10
    min_std: float = 1e-3

    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    def effective_mean(self) -> np.ndarray:
        """(K, A, 3) mean with the reference sentinel -100 on invalid bins."""
        return np.where(self.valid[..., None], self.mean, INVALID_MEAN)

    def effective_std(self) -> np.ndarray:
        """(K, A, 3) std with the reference sentinel 1e10 on invalid bins."""
        return np.where(self.valid[..., None], self.std, INVALID_STD)

    def check_compatible(
        self,
        layout: AnchorLayout,
        class_names: Iterable[str] | None = None,
        angle_mode: str | None = None,
        source: str | os.PathLike = "<priors>",
    ) -> None:
        """Raises :class:`PriorsMismatchError` (naming ``source``) unless these priors fit."""
        problems = [f"anchor layout {d}" for d in layout.differences(self.layout)]
        if class_names is not None and tuple(class_names) != self.class_names:
            problems.append(f"classes {self.class_names} != requested {tuple(class_names)}")
        if angle_mode is not None and angle_mode != self.angle_mode:
            problems.append(f"angle_mode {self.angle_mode!r} != requested {angle_mode!r}")
        if problems:
            raise PriorsMismatchError(
                f"{os.fspath(source)}: anchor priors do not match this run ("
                + "; ".join(problems)
                + "). Recompute them for this configuration or point to another priors file."
            )


def _as_frame_arrays(frame: Mapping, index: int, num_classes: int) -> tuple[np.ndarray, ...]:
    try:
        boxes = np.asarray(frame["boxes"], dtype=np.float64).reshape(-1, 4)
        classes = np.asarray(frame["classes"]).reshape(-1)
        z = np.asarray(frame["z"], dtype=np.float64).reshape(-1)
        alpha = np.asarray(frame["alpha"], dtype=np.float64).reshape(-1)
        dims = np.asarray(frame["dims"], dtype=np.float64).reshape(-1, 3)
    except KeyError as e:
        raise ValueError(f"priors frame {index}: missing key {e.args[0]!r}") from None
    m = len(boxes)
    if not (len(classes) == len(z) == len(alpha) == len(dims) == m):
        raise ValueError(
            f"priors frame {index}: inconsistent object counts (boxes {m}, classes {len(classes)}, "
            f"z {len(z)}, alpha {len(alpha)}, dims {len(dims)})"
        )
    if not np.issubdtype(classes.dtype, np.integer):
        raise ValueError(f"priors frame {index}: 'classes' must be integer class indices")
    if np.any(classes >= num_classes):
        raise ValueError(
            f"priors frame {index}: class index {int(classes.max())} >= "
            f"number of classes {num_classes}"
        )
    keep = classes >= 0  # negative = padding
    return boxes[keep], classes[keep], z[keep], alpha[keep], dims[keep]


def compute_anchor_priors(
    frames: Iterable[Mapping],
    layout: AnchorLayout,
    class_names: Iterable[str],
    *,
    angle_mode: str = "double",
    iou_threshold: float = 0.5,
    min_count: int = 10,
    min_std: float = 1e-3,
) -> AnchorPriors:
    """Computes :class:`AnchorPriors` from per-frame ground truth.

    Args:
      frames: iterable of mappings, one per frame, with numpy arrays
        ``'boxes'`` (M, 4) xyxy in network-input pixels, ``'classes'`` (M,) int
        class index (negative entries are ignored as padding), ``'z'`` (M,) depth
        in metres (the reference uses the label's camera-frame ``z``), ``'alpha'``
        (M,) observation angle, ``'dims'`` (M, 3) ``(h, w, l)``.
      layout: anchor layout (boxes must be in its input-pixel frame).
      class_names: K class names.
      angle_mode: ``"double"`` (reference) or ``"single"`` (paper); see module doc.
      iou_threshold: an anchor samples its argmax GT if max IoU > this (strict).
      min_count: bins with fewer samples are invalid.
      min_std: bins with a channel std below this (or NaN) are invalid.

    Raises:
      ValueError: a class has no objects at all, or a frame is malformed.
    """
    class_names = tuple(class_names)
    num_classes = len(class_names)
    if angle_mode not in ANGLE_MODES:
        raise ValueError(f"angle_mode must be one of {ANGLE_MODES}, got {angle_mode!r}")
    anchors = generate_anchors(layout)
    num_bins = layout.anchors_per_cell
    count = np.zeros((num_classes, num_bins), dtype=np.int64)
    total = np.zeros((num_classes, num_bins, 3))
    total_sq = np.zeros((num_classes, num_bins, 3))
    dim_n = np.zeros(num_classes, dtype=np.int64)
    dim_sum = np.zeros((num_classes, 3))
    dim_sq = np.zeros((num_classes, 3))
    num_frames = 0
    for index, frame in enumerate(frames):
        num_frames += 1
        boxes, classes, z, alpha, dims = _as_frame_arrays(frame, index, num_classes)
        if not np.all(np.isfinite(boxes)) or not np.all(np.isfinite(z)):
            raise ValueError(f"priors frame {index}: non-finite box or depth")
        sin, cos = angle_features(alpha, angle_mode)
        values = np.stack([z, sin, cos], axis=-1)
        for k in np.unique(classes):
            sel = classes == k
            dim_n[k] += sel.sum()
            dim_sum[k] += dims[sel].sum(0)
            dim_sq[k] += (dims[sel] ** 2).sum(0)
            iou = box_iou_np(anchors.boxes, boxes[sel])  # (N, Mk)
            positive = iou.max(axis=1) > iou_threshold
            matched = values[sel][iou.argmax(axis=1)[positive]]  # (P, 3)
            bins = anchors.bin_index[positive]
            count[k] += np.bincount(bins, minlength=num_bins)
            np.add.at(total[k], bins, matched)
            np.add.at(total_sq[k], bins, matched**2)
    empty = [class_names[k] for k in range(num_classes) if dim_n[k] == 0]
    if empty:
        raise ValueError(f"no ground-truth objects of class(es) {empty} in the priors frames")
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = total / count[..., None]
        var = total_sq / count[..., None] - mean**2
    std = np.sqrt(np.maximum(var, 0.0))
    channel_ok = np.isfinite(std) & (std >= min_std)
    valid = (count >= min_count) & channel_ok.all(axis=-1)
    dims_mean = dim_sum / dim_n[:, None]
    dims_std = np.sqrt(np.maximum(dim_sq / dim_n[:, None] - dims_mean**2, 0.0))
    # A dimension without spread (e.g. a synthetic dataset) is left unnormalised rather than
    # divided by ~0.
    dims_std = np.where(dims_std < min_std, 1.0, dims_std)
    return AnchorPriors(
        layout=layout,
        class_names=class_names,
        angle_mode=angle_mode,
        count=count,
        mean=mean,
        std=std,
        valid=valid,
        dims_mean=dims_mean,
        dims_std=dims_std,
        num_objects=dim_n,
        num_frames=num_frames,
        iou_threshold=float(iou_threshold),
        min_count=int(min_count),
        min_std=float(min_std),
    )


def prior_frame_from_objects(
    objects: KittiObjects,
    class_names: Iterable[str],
    image_transform: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """One :func:`compute_anchor_priors` frame from KITTI labels (reference §2.2 step 1).

    Objects whose type is not in ``class_names`` are dropped (filter occlusion /
    depth beforehand). The *annotated* 2D boxes are mapped by the affine
    ``image_transform`` (3, 3) (original pixels -> network-input pixels, e.g.
    crop-top + resize) as the reference does; ``z`` is the label's camera-frame
    depth and ``alpha`` the label's observation angle.
    """
    class_names = tuple(class_names)
    keep = np.isin(objects.type, class_names)
    objs = objects.select(keep)
    boxes = objs.bbox.copy()
    if image_transform is not None:
        A = np.asarray(image_transform, dtype=np.float64)
        corners = np.stack(
            [boxes[:, [0, 1]], boxes[:, [2, 1]], boxes[:, [0, 3]], boxes[:, [2, 3]]], axis=1
        )  # (M, 4, 2)
        mapped = corners @ A[:2, :2].T + A[:2, 2]
        boxes = np.concatenate([mapped.min(axis=1), mapped.max(axis=1)], axis=1)
    return {
        "boxes": boxes,
        "classes": np.array([class_names.index(t) for t in objs.type], dtype=np.int64),
        "z": objs.location[:, 2].copy(),
        "alpha": objs.alpha.copy(),
        "dims": objs.dimensions.copy(),
    }


_ARRAY_FIELDS = ("count", "mean", "std", "valid", "dims_mean", "dims_std", "num_objects")


def save_priors(path: str | os.PathLike, priors: AnchorPriors) -> None:
    """Atomically writes ``priors`` to an ``.npz`` file that records the anchor layout."""
    meta = {
        "format_version": PRIORS_FORMAT_VERSION,
        "layout": priors.layout.to_dict(),
        "class_names": list(priors.class_names),
        "angle_mode": priors.angle_mode,
        "num_frames": priors.num_frames,
        "iou_threshold": priors.iou_threshold,
        "min_count": priors.min_count,
        "min_std": priors.min_std,
    }
    arrays = {name: getattr(priors, name) for name in _ARRAY_FIELDS}
    with atomic_write(path, "wb") as f:
        np.savez(f, meta=np.array(json.dumps(meta)), **arrays)


def load_priors(
    path: str | os.PathLike,
    layout: AnchorLayout | None = None,
    class_names: Iterable[str] | None = None,
    angle_mode: str | None = None,
) -> AnchorPriors:
    """Reads priors written by :func:`save_priors`.

    With ``layout`` / ``class_names`` / ``angle_mode`` given, priors computed for
    anything else are refused with a :class:`PriorsMismatchError` naming the file.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {name: np.array(data[name]) for name in _ARRAY_FIELDS}
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: anchor priors file not found") from None
    except (KeyError, ValueError, OSError) as e:
        raise ValueError(f"{path}: not an anchor priors file ({e})") from None
    if meta.get("format_version") != PRIORS_FORMAT_VERSION:
        raise ValueError(f"{path}: unsupported priors format version {meta.get('format_version')}")
    priors = AnchorPriors(
        layout=AnchorLayout.from_dict(meta["layout"]),
        class_names=tuple(meta["class_names"]),
        angle_mode=meta["angle_mode"],
        num_frames=int(meta["num_frames"]),
        iou_threshold=float(meta["iou_threshold"]),
        min_count=int(meta["min_count"]),
        min_std=float(meta["min_std"]),
        **arrays,
    )
    if layout is not None:
        priors.check_compatible(layout, class_names, angle_mode, source=path)
    elif class_names is not None or angle_mode is not None:
        priors.check_compatible(priors.layout, class_names, angle_mode, source=path)
    return priors


def load_or_compute_priors(
    path: str | os.PathLike,
    frames: Callable[[], Iterable[Mapping]],
    layout: AnchorLayout,
    class_names: Iterable[str],
    **compute_kwargs,
) -> AnchorPriors:
    """Loads cached priors from ``path`` or computes (``frames()``), saves and returns them.

    A cached file made for another layout / class list / angle mode is refused
    (:class:`PriorsMismatchError`), never silently overwritten. ``frames`` is
    called only when computing.
    """
    class_names = tuple(class_names)
    angle_mode = compute_kwargs.get("angle_mode", "double")
    if Path(path).exists():
        return load_priors(path, layout, class_names, angle_mode)
    priors = compute_anchor_priors(frames(), layout, class_names, **compute_kwargs)
    save_priors(path, priors)
    return priors


@flax.struct.dataclass
class DetectionConstants:
    """Anchors and their priors as float32 device arrays for the jitted step (a pytree).

    ``N`` anchors, ``K`` classes. Invalid bins carry the reference sentinels
    (mean -100, std 1e10); ``prior_valid`` is authoritative.

    Attributes:
      anchor_boxes: (N, 4) xyxy, network-input pixels.
      anchor_centers: (N, 2) ``(u, v)``.
      prior_mean, prior_std: (K, N, 3) ``[z, sin, cos]`` statistics of each anchor's bin.
      prior_valid: (K, N) bool.
      dims_mean, dims_std: (K, 3) class-global ``(h, w, l)``.
      angle_mode: static; ``"double"`` or ``"single"``.
      sign_axis: static; direction of the alpha-sign bit
        (:func:`gac_jax.detection.box_coding.encode`).
    """

    anchor_boxes: jax.Array
    anchor_centers: jax.Array
    prior_mean: jax.Array
    prior_std: jax.Array
    prior_valid: jax.Array
    dims_mean: jax.Array
    dims_std: jax.Array
    angle_mode: str = flax.struct.field(pytree_node=False, default="double")
    sign_axis: float = flax.struct.field(pytree_node=False, default=0.0)

    @property
    def num_classes(self) -> int:
        return int(self.prior_valid.shape[0])


def make_detection_constants(
    anchors: Anchors, priors: AnchorPriors, sign_axis: float = 0.0
) -> DetectionConstants:
    """Gathers the per-bin priors to every anchor (checks that the layouts agree)."""
    priors.check_compatible(anchors.layout, source="<priors given to make_detection_constants>")
    idx = anchors.bin_index
    return DetectionConstants(
        anchor_boxes=jnp.asarray(anchors.boxes, jnp.float32),
        anchor_centers=jnp.asarray(anchors.centers, jnp.float32),
        prior_mean=jnp.asarray(priors.effective_mean()[:, idx], jnp.float32),
        prior_std=jnp.asarray(priors.effective_std()[:, idx], jnp.float32),
        prior_valid=jnp.asarray(priors.valid[:, idx]),
        dims_mean=jnp.asarray(priors.dims_mean, jnp.float32),
        dims_std=jnp.asarray(priors.dims_std, jnp.float32),
        angle_mode=priors.angle_mode,
        sign_axis=float(sign_axis),
    )
