"""Runs a depth predictor over a split: full-size predictions, 16-bit PNGs, metrics, pictures.

Shared by the depth trainer (periodic and final evaluation) and ``evaluate.py --task depth
--workdir W``. Device work is one jitted predict function at the network input size (fixed
batch shape: the last batch is padded); everything else runs on the host.

**Back to the original image.** The network sees the test-time view of a frame (the bottom
``crop_height`` rows, possibly resized, the left columns); ``image_transform`` ``A`` maps
original pixels to network pixels. :func:`to_original_geometry` samples the predicted
log-depth at ``A @ [u, v, 1]`` for every original pixel (separable bilinear; exact for the
integer shifts of the KITTI 352x1216 crop). Original pixels the network did not see - the
rows above the crop, the columns right of the kept width - take the nearest border value
(edge replication), as the reference pads its 352-row predictions by replicating the top
row. Every pixel thus gets a positive depth: the KITTI server wants full-size maps. (Those
pixels have no LiDAR ground truth in KITTI, so the choice hardly moves the metrics.)

**Files.** Depth is clipped to ``[1/256, 65535/256]`` m and written as ``round(256 z)``
16-bit PNGs (the KITTI format; 0 never written), atomically, one per frame, at
:func:`prediction_relpath` - the ground truth's relative path for KITTI-depth frames, so
``evaluate.py --task depth --groundtruth-dir ROOT/data_depth_annotated/val --prediction-dir
DIR`` re-scores a folder; the image's file name for ``depth_selection`` frames (the
submission layout). A frame whose PNG exists is not predicted again (resume). Metrics are
computed on the written (quantised) values against the original-size ground truth, over its
valid pixels only, so both routes give the same numbers.

**Baseline.** :class:`GroundPlanePredictor` predicts, per pixel, the depth of the frame's
ground plane (its ``planes/`` file, else a level road ``camera_height`` below the camera;
:func:`gac_jax.geometry.ground_depth`), clipped to ``max_depth`` (at and above the horizon:
``max_depth``): the prior the GAC network starts from, with no learning.

Batches carry ``plane`` (B, 4); a frame without one has NaN there, and each predictor uses
its own level plane for it (:func:`frame_planes`).
"""

from __future__ import annotations

import dataclasses
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gac_jax import geometry
from gac_jax.data.files import read_depth_png, write_png
from gac_jax.data.loader import Loader, collate
from gac_jax.drawing.depth_pictures import depth_panel
from gac_jax.drawing.picture_grid import save_image
from gac_jax.evaluation.depth_metrics import DepthMetricAccumulator

MIN_WRITTEN_DEPTH = 1.0 / 256.0  # the smallest non-zero 16-bit value
MAX_WRITTEN_DEPTH = 65535.0 / 256.0
BASELINE_CAMERA_HEIGHT = geometry.DEFAULT_CAMERA_HEIGHT  # frames without a planes/ file
BASELINE_MAX_DEPTH = 80.0


# ----------------------------------------------------------------------------- geometry


def _axis_taps(n_out: int, scale: float, offset: float, n_in: int):
    src = np.clip(scale * np.arange(n_out, dtype=np.float64) + offset, 0.0, n_in - 1.0)
    i0 = np.floor(src).astype(np.int64)
    i1 = np.minimum(i0 + 1, n_in - 1)
    return i0, i1, (src - i0).astype(np.float32)


def to_original_geometry(
    log_depth: np.ndarray, image_transform: np.ndarray, original_size: Sequence[int]
) -> np.ndarray:
    """A network-size log-depth map as depth (metres) on the original image grid.

    Args:
      log_depth: (h, w) natural-log depth in network-input pixels.
      image_transform: (3, 3) axis-aligned affine ``A`` mapping original pixel centres to
        network pixel centres (the sample's ``image_transform``).
      original_size: (H0, W0).
    Returns:
      (H0, W0) float32 depth: original pixel ``(u, v)`` reads the bilinear log-depth at
      ``A @ [u, v, 1]``, clamped to the map (edge replication outside it).
    Raises:
      ValueError: ``A`` rotates or shears (the test-time transforms never do).
    """
    A = np.asarray(image_transform, np.float64)
    if abs(A[0, 1]) > 1e-9 or abs(A[1, 0]) > 1e-9 or np.any(A[2] != (0.0, 0.0, 1.0)):
        raise ValueError(f"image_transform must be an axis-aligned affine, got {A.tolist()}")
    lg = np.asarray(log_depth, np.float32)
    H0, W0 = (int(s) for s in original_size)
    r0, r1, wr = _axis_taps(H0, A[1, 1], A[1, 2], lg.shape[0])
    rows = lg[r0] * (1.0 - wr)[:, None] + lg[r1] * wr[:, None]
    c0, c1, wc = _axis_taps(W0, A[0, 0], A[0, 2], lg.shape[1])
    return np.exp(rows[:, c0] * (1.0 - wc) + rows[:, c1] * wc).astype(np.float32)


def quantize_depth(depth: np.ndarray) -> np.ndarray:
    """Metres -> the KITTI 16-bit value ``round(256 z)``, z clipped to [1/256, 65535/256] m."""
    d = np.nan_to_num(np.asarray(depth, np.float64), nan=MAX_WRITTEN_DEPTH)
    d = np.clip(d, MIN_WRITTEN_DEPTH, MAX_WRITTEN_DEPTH)
    return np.round(d * 256.0).astype(np.uint16)


def ground_plane_depth(
    P: np.ndarray,
    size: Sequence[int],
    camera_height: float = BASELINE_CAMERA_HEIGHT,
    max_depth: float = BASELINE_MAX_DEPTH,
    plane: np.ndarray | None = None,
) -> np.ndarray:
    """The ground-plane baseline of an image: (H, W) float32.

    Pixel ``(u, v)`` gets ``min(geometry.ground_depth(v, P, camera_height, u=u, plane=plane),
    max_depth)`` (``plane`` None: the level road ``camera_height`` below the camera, constant
    along each row); pixels at or above the horizon (no ground there) get ``max_depth``.
    """
    H, W = (int(s) for s in size)
    z = geometry.ground_depth_map((H, W), P, camera_height, plane)
    return np.minimum(z, max_depth).astype(np.float32)


def frame_planes(batch: dict, camera_height: float) -> np.ndarray:
    """(B, 4) float64 planes of a batch, NaN rows (frames without one) -> the level plane."""
    planes = np.asarray(batch["plane"], np.float64).copy()
    missing = ~np.isfinite(planes).all(axis=1)
    planes[missing] = geometry.level_plane(camera_height)
    return planes


def prediction_relpath(frame_id: str, camera: int) -> Path:
    """Where a frame's PNG goes under a result folder.

    KITTI-depth frames (``'<drive>/<frame>'``): ``<drive>/proj_depth/groundtruth/image_0C/
    <frame>.png``, the ground truth's path below ``data_depth_annotated/<split>``.
    ``depth_selection`` frames (the image's file stem): ``<stem>.png``.
    """
    if "/" in frame_id:
        drive, frame = frame_id.split("/", 1)
        return Path(drive) / "proj_depth" / "groundtruth" / f"image_0{camera}" / f"{frame}.png"
    return Path(f"{frame_id}.png")


# ----------------------------------------------------------------------------- predictors


class NetworkPredictor:
    """A trained :class:`~gac_jax.models.depth_unet.DepthUNet` as a depth predictor.

    ``__call__(batch)`` runs the jitted network (``train=False``) on ``batch['image']``
    (B, h, w, 3), ``batch['P2']`` and ``batch['plane']`` (:func:`frame_planes`, the model's
    ``camera_height`` for frames without one) and returns B original-geometry depth maps
    (:func:`to_original_geometry` of the ``scale_1`` log-depth).
    """

    def __init__(self, model, variables: dict):
        self.variables = variables

        self.camera_height = model.camera_height

        def predict(variables, images, P, plane):
            out = model.apply(variables, images, P, train=False, plane=plane)
            return out["log_depth"]["scale_1"]

        self._predict = jax.jit(predict)

    def __call__(self, batch: dict) -> list[np.ndarray]:
        planes = frame_planes(batch, self.camera_height).astype(np.float32)
        log_depth = np.asarray(self._predict(self.variables, batch["image"], batch["P2"], planes))
        return [
            to_original_geometry(
                log_depth[b], batch["image_transform"][b], batch["original_size"][b]
            )
            for b in range(len(log_depth))
        ]


class GroundPlanePredictor:
    """The ground-plane baseline (:func:`ground_plane_depth`) as a predictor.

    The original projection is recovered from the batch: ``P0 = A^-1 @ P2``; the plane is
    the batch's (crops and resizes do not move it), ``camera_height`` for frames without one.
    """

    def __init__(
        self, camera_height: float = BASELINE_CAMERA_HEIGHT, max_depth: float = BASELINE_MAX_DEPTH
    ):
        self.camera_height = camera_height
        self.max_depth = max_depth

    def __call__(self, batch: dict) -> list[np.ndarray]:
        out = []
        planes = frame_planes(batch, self.camera_height)
        for b in range(len(batch["P2"])):
            A = np.asarray(batch["image_transform"][b], np.float64)
            P0 = np.linalg.solve(A, np.asarray(batch["P2"][b], np.float64))
            size = batch["original_size"][b]
            out.append(ground_plane_depth(P0, size, self.camera_height, self.max_depth, planes[b]))
        return out


# ----------------------------------------------------------------------------- evaluator


def _input_arrays(sample: dict) -> dict[str, np.ndarray]:
    """What prediction and file naming need from a (transformed) sample."""
    return {
        "image": np.asarray(sample["image"], np.float32),
        "P2": np.asarray(sample["P2"], np.float32),
        "plane": np.asarray(sample.get("plane", np.full(4, np.nan)), np.float32),
        "image_transform": np.asarray(sample["image_transform"], np.float32),
        "original_size": np.asarray(sample["original_size"], np.int32).reshape(2),
        "camera": np.asarray(sample["camera"], np.int32),
        "frame_id": np.asarray(sample["frame_id"], dtype=str),
    }


@dataclasses.dataclass(frozen=True)
class WithoutDepth:
    """Picklable ``transform`` of a sample without its ``depth``: the evaluator scores against
    the original-size ground truth, so resampling it with the image would be wasted work."""

    transform: Callable[[dict], dict]

    def __call__(self, sample: dict) -> dict:
        return self.transform({k: v for k, v in sample.items() if k != "depth"})


def ground_truth_depth(source, index: int) -> np.ndarray | None:
    """Original-size GT depth of a source item (None when the split has none, e.g. test).

    Folder sources read the PNG alone (no image decode); others decode the sample.
    """
    frames = getattr(source, "frames", None)
    layout = getattr(source, "layout", None)
    if frames is not None and layout is not None:
        return read_depth_png(layout.groundtruth(source.split, frames[index]))
    items = getattr(source, "items", None)
    if items is not None:
        gt = items[index].groundtruth
        return None if gt is None else read_depth_png(gt)
    return source[index].get("depth")


def frame_keys(source) -> list[tuple[str, int]] | None:
    """(frame id, camera) of every item when the source can tell without decoding, else None."""
    frames = getattr(source, "frames", None)
    if frames is not None:
        return [(f.frame_id, f.camera) for f in frames]
    items = getattr(source, "items", None)
    if items is not None:
        return [(it.name, 3 if it.name.endswith("image_03") else 2) for it in items]
    return None


def picture_indices(num_items: int, num_pictures: int) -> set[int]:
    """``num_pictures`` item indices spread evenly over the split (the same every evaluation)."""
    if num_pictures <= 0 or num_items == 0:
        return set()
    return {int(i) for i in np.linspace(0, num_items - 1, min(num_pictures, num_items)).round()}


class DepthEvaluator:
    """Predict + map back + write + score + draw one split.

    Args:
      source: a depth source of the split (GT optional: without it frames are only written).
      transform: the test-time transform chain (crop, resize, crop/pad width, normalise).
      batch_size: images per predict call.
      worker_count: loader worker processes.
      num_pictures: image | prediction | ground-truth panels drawn per evaluation.
      max_depth: far end of the pictures' colour scale (metres).
    """

    def __init__(
        self,
        source,
        transform: Callable[[dict], dict],
        *,
        batch_size: int = 4,
        worker_count: int = 0,
        num_pictures: int = 4,
        max_depth: float = 80.0,
    ):
        self.source = source
        self.batch_size = batch_size
        self.max_depth = max_depth
        self.loader = Loader(
            source,
            WithoutDepth(transform),
            _input_arrays,
            batch_size=batch_size,
            shuffle=False,
            drop_remainder=False,
            num_epochs=1,
            worker_count=worker_count,
        )
        self.keys = frame_keys(source)
        self.pictures = picture_indices(len(source), num_pictures)

    def _draw(self, index: int, depth: np.ndarray, gt, picture_dir: Path, key) -> None:
        image = self.source[index]["image"]
        panel = depth_panel(image, depth, gt, max_depth=self.max_depth)
        stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", key[0])
        save_image(picture_dir / f"{index:05d}_{stem}_image_0{key[1]}.png", panel)

    def evaluate(
        self,
        predictor: Callable[[dict], list[np.ndarray]],
        result_dir: str | Path | None = None,
        picture_dir: str | Path | None = None,
        resume: bool = True,
        max_batches: int | None = None,
    ) -> dict[str, Any]:
        """Runs ``predictor`` over the split; returns metrics, counts and timings.

        Args:
          predictor: ``batch -> list of original-geometry depth maps`` (:class:`NetworkPredictor`,
            :class:`GroundPlanePredictor`).
          result_dir: where the 16-bit PNGs go (None: nothing written, no resume).
          picture_dir: where the panels go (None: no pictures).
          resume: reuse PNGs already in ``result_dir`` instead of predicting those frames.
          max_batches: stop after this many batches (None: the whole split).
        Returns:
          ``{'metrics': {name: value} ({} when nothing was scored), 'num_frames',
          'num_predicted', 'num_scored', 'timings': {...}, 'per_image': [{'frame', 'camera',
          name: value, ...}]}`` (``per_image``: each scored image's metrics, in split order;
          ``metrics`` is their mean); frames without ground truth (or with no valid GT pixel)
          are written but not scored.
        """
        result_dir = Path(result_dir) if result_dir is not None else None
        picture_dir = Path(picture_dir) if picture_dir is not None else None
        acc = DepthMetricAccumulator()
        per_image: list[dict[str, Any]] = []
        timings = {"load_s": 0.0, "model_s": 0.0, "write_s": 0.0, "score_s": 0.0}
        counts = {"num_frames": 0, "num_predicted": 0}
        steps = self.loader.steps_per_epoch
        steps = steps if max_batches is None else min(steps, max_batches)
        for step in range(steps):
            t0 = time.perf_counter()
            _, indices = self.loader.step_indices(step)
            keys = [self.keys[i] for i in indices] if self.keys is not None else None
            paths = self._paths(result_dir, keys)
            done = resume and paths is not None and all(p.is_file() for p in paths)
            batch = None
            if not done:
                batch = self.loader.load_batch(step)
                keys = [
                    (str(f), int(c))
                    for f, c in zip(batch["frame_id"], batch["camera"], strict=True)
                ]
                paths = self._paths(result_dir, keys)
            t1 = time.perf_counter()
            predictions: list[np.ndarray | None] = [None] * len(indices)
            missing = [
                b for b in range(len(indices)) if not (resume and paths and paths[b].is_file())
            ]
            if missing:
                predictions = self._predict(predictor, batch)
                counts["num_predicted"] += len(missing)
            t2 = time.perf_counter()
            timings["load_s"] += t1 - t0
            timings["model_s"] += t2 - t1
            for b, index in enumerate(indices):
                t3 = time.perf_counter()
                if b in missing:
                    value = quantize_depth(predictions[b])
                    if paths is not None:
                        write_png(paths[b], value)
                    depth = value.astype(np.float32) / np.float32(256.0)
                else:
                    depth = read_depth_png(paths[b])
                t4 = time.perf_counter()
                gt = ground_truth_depth(self.source, int(index))
                if gt is not None and depth.shape != gt.shape:
                    raise ValueError(
                        f"{keys[b][0]} camera {keys[b][1]}: prediction {depth.shape} and ground "
                        f"truth {gt.shape} sizes differ"
                    )
                if gt is not None and (gt > 0).any():
                    scored = acc.update(depth, gt)
                    frame, camera = keys[b] if keys is not None else (str(index), 2)
                    per_image.append({"frame": frame, "camera": camera, **scored})
                if picture_dir is not None and int(index) in self.pictures:
                    self._draw(int(index), depth, gt, picture_dir, keys[b])
                timings["write_s"] += t4 - t3
                timings["score_s"] += time.perf_counter() - t4
                counts["num_frames"] += 1
        metrics = acc.result() if acc.count else {}
        return {
            "metrics": metrics,
            **counts,
            "num_scored": acc.count,
            "timings": timings,
            "per_image": per_image,
        }

    def _paths(self, result_dir, keys) -> list[Path] | None:
        if result_dir is None or keys is None:
            return None
        return [result_dir / prediction_relpath(f, c) for f, c in keys]

    def _predict(self, predictor, batch: dict) -> list[np.ndarray]:
        n = len(batch["frame_id"])
        if n < self.batch_size:  # pad to the compiled batch shape
            batch = collate(
                [{k: v[min(i, n - 1)] for k, v in batch.items()} for i in range(self.batch_size)]
            )
        return predictor(batch)[:n]
