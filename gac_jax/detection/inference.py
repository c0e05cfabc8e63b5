"""From images to KITTI detections: the jitted predict function and host post-processing.

Device side (:func:`make_predict_fn`, one ``jax.jit``): backbone + heads,
decoding of every anchor with its best class (anchor priors compiled in as
constants), the ground-plane anchor filter and invalid-prior mask, and the
``top_k`` best candidates per image (static shapes; ``None`` = every anchor). It
also counts, per image, the filter-kept anchors above the score threshold
(``num_candidates``): the reference keeps all of them, so a count above ``top_k``
means the cap dropped some, and the evaluator reports how often that happened.

Host side (:func:`postprocess`): score threshold, 2D clipping, NMS, optional
hill-climbing of the observation angle, back-projection to 3D, and mapping of
2D boxes back to original-image pixels through the inverse of the sample's
``image_transform``. Results are :class:`~gac_jax.data.kitti.KittiObjects`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gac_jax import geometry
from gac_jax.data.kitti import KittiObjects
from gac_jax.data.transforms import transform_boxes
from gac_jax.detection.anchor_filter import ground_mask_from_constants
from gac_jax.detection.anchor_priors import DetectionConstants
from gac_jax.detection.box_coding import decode_outputs
from gac_jax.detection.hill_climbing import optimize_rotation_y_batch
from gac_jax.detection.nms import batched_nms

CANDIDATE_KEYS = ("scores", "labels", "boxes", "center", "depth", "dims", "alpha")


@dataclasses.dataclass(frozen=True)
class PostprocessConfig:
    """Host-side post-processing settings (reference values in comments).

    Attributes:
      score_threshold: keep candidates above this (reference 0.75).
      nms_iou: 2D NMS IoU threshold (0.5).
      class_agnostic_nms: the reference is (accidentally) always class-agnostic.
      hill_climbing: refine the observation angle on 2D-3D box consistency.
      min_depth_hill_climbing: only objects farther than this are refined (3 m).
      hill_climbing_labels: class indices that are refined; the reference
        refines only label 0 (its first class), None refines every class.
      max_detections: cap per image after NMS (None: no cap).
    """

    score_threshold: float = 0.75
    nms_iou: float = 0.5
    class_agnostic_nms: bool = True
    hill_climbing: bool = True
    min_depth_hill_climbing: float = 3.0
    hill_climbing_labels: tuple[int, ...] | None = (0,)
    max_detections: int | None = None


def select_candidates(
    outputs: dict,
    constants: DetectionConstants,
    P2: jax.Array,
    top_k: int | None,
    filter_options: dict | None = None,
    *,
    use_ground_filter: bool = True,
    score_threshold: float | None = None,
    plane: jax.Array | None = None,
) -> dict:
    """Network outputs -> the ``top_k`` best decoded candidates per image (jit-compatible).

    The part of :func:`make_predict_fn` after the network, shared with the exported
    runtimes (:mod:`gac_jax.deploy.runtimes`), which compute ``outputs`` (``cls_logits`` (B,N,K),
    ``sign_logits`` (B,N), ``reg`` (B,N,12)) outside JAX. ``top_k`` and
    ``score_threshold`` as in :func:`make_predict_fn`; the result is its dict. ``plane``
    (B, 4): each image's ground plane for the anchor filter (None: the level plane of
    ``filter_options['camera_height']``).
    """
    filter_options = dict(filter_options or {})
    threshold = -1.0 if score_threshold is None else float(score_threshold)
    decoded = decode_outputs(outputs, constants)
    keep = decoded["prior_valid"]
    if use_ground_filter:
        keep = keep & ground_mask_from_constants(constants, P2, plane, **filter_options)
    scores = jnp.where(keep, decoded["scores"], -1.0)
    num_candidates = jnp.sum(keep & (decoded["scores"] > threshold), axis=1)
    k = scores.shape[1] if top_k is None else min(top_k, scores.shape[1])
    top_scores, index = jax.lax.top_k(scores, k)

    def take(x):
        idx = index.reshape(index.shape + (1,) * (x.ndim - 2))
        return jnp.take_along_axis(x, idx, axis=1)

    out = {key: take(decoded[key]) for key in CANDIDATE_KEYS if key != "scores"}
    out["scores"] = top_scores
    out["num_candidates"] = num_candidates.astype(jnp.int32)
    return out


def make_predict_fn(
    model,
    constants: DetectionConstants,
    *,
    top_k: int | None = 4096,
    score_threshold: float | None = None,
    filter_options: dict | None = None,
    use_ground_filter: bool = True,
) -> Callable:
    """Builds ``predict(variables, images, P2, plane=None) -> candidates`` (jitted).

    Args:
      model: a :class:`gac_jax.models.detector.Detector`.
      constants: anchors and priors (closed over: compiled-in constants).
      top_k: candidates per image (static); ``None`` or more than the anchor count:
        every anchor (the reference's uncapped selection; ``K = N``).
      score_threshold: the post-processing threshold, used only for the
        ``num_candidates`` count (``None``: count every filter-kept anchor).
      filter_options: keyword options of :func:`gac_jax.detection.anchor_filter.ground_filter_mask`.

    Returns:
      A jitted function of ``variables`` ({'params', 'batch_stats'}), ``images``
      (B, H, W, 3) float32 normalised, ``P2`` (B, 3, 4) and ``plane`` (B, 4) (each image's
      ground plane, a live input like ``P2``; None: the model's level plane) giving a dict of
      (B, K, ...) arrays, ``K = min(top_k, N)``, best score first: ``scores``,
      ``labels``, ``boxes`` (xyxy, input pixels), ``center`` (u, v), ``depth``
      (homogeneous), ``dims`` (h, w, l), ``alpha`` (padding candidates have score
      -1); and ``num_candidates`` (B,) int32, the filter-kept anchors with score
      above ``score_threshold`` (more than ``K``: the cap dropped some).
    """
    filter_options = dict(filter_options or {})
    if top_k is not None and top_k < 1:
        raise ValueError(f"top_k must be >= 1 or None (every anchor), got {top_k}")

    @jax.jit
    def predict(variables, images, P2, plane=None):
        outputs = model.apply(variables, images, P2, train=False, plane=plane)
        return select_candidates(
            outputs,
            constants,
            P2,
            top_k,
            filter_options,
            use_ground_filter=use_ground_filter,
            score_threshold=score_threshold,
            plane=plane,
        )

    return predict


def candidates_to_objects(
    candidates: dict[str, np.ndarray],
    P2: np.ndarray,
    image_transform: np.ndarray,
    input_size: tuple[int, int],
    original_size: tuple[int, int],
    class_names: Sequence[str],
    config: PostprocessConfig,
) -> KittiObjects:
    """Post-processes one image's candidates into KITTI objects in original-image pixels.

    Args:
      candidates: one image's slice of :func:`make_predict_fn`'s output (numpy;
        only :data:`CANDIDATE_KEYS` are read).
      P2: (3, 4) projection of the network input (after crop/resize).
      image_transform: (3, 3) affine original -> input pixels.
      input_size: (H, W) of the network input.
      original_size: (H0, W0) of the original image.
    """
    c = {k: np.asarray(candidates[k], np.float64) for k in CANDIDATE_KEYS}
    sel = c["scores"] > config.score_threshold
    c = {k: v[sel] for k, v in c.items()}
    h, w = input_size
    boxes = c["boxes"].copy()
    boxes[:, [0, 2]] = np.clip(boxes[:, [0, 2]], 0.0, w)
    boxes[:, [1, 3]] = np.clip(boxes[:, [1, 3]], 0.0, h)
    labels = c["labels"].astype(np.int64)
    keep = batched_nms(boxes, c["scores"], labels, config.nms_iou, config.class_agnostic_nms)
    if config.max_detections is not None:
        keep = keep[: config.max_detections]
    boxes, labels = boxes[keep], labels[keep]
    c = {k: v[keep] for k, v in c.items()}
    n = len(keep)
    P2 = np.asarray(P2, np.float64)
    centre = geometry.unproject(c["center"], c["depth"], P2).reshape(n, 3)
    dims = c["dims"].reshape(n, 3)
    location = centre + np.stack([np.zeros(n), dims[:, 0] / 2.0, np.zeros(n)], axis=1)
    # alpha is measured from the current camera's optical centre (ReprojectBoxes' convention).
    ry = geometry.rotation_y_from_alpha(c["alpha"], location, P2)
    if config.hill_climbing and n:
        refine = centre[:, 2] > config.min_depth_hill_climbing
        if config.hill_climbing_labels is not None:
            refine &= np.isin(labels, np.asarray(config.hill_climbing_labels, np.int64))
        idx = np.flatnonzero(refine)
        ry[idx] = optimize_rotation_y_batch(
            boxes[idx], location[idx], dims[idx], ry[idx], P2, input_size
        )
    alpha_kitti = geometry.alpha_from_rotation_y(ry, location, None)
    inverse = np.linalg.inv(np.asarray(image_transform, np.float64))
    boxes_orig = transform_boxes(boxes, inverse)
    h0, w0 = original_size
    boxes_orig[:, [0, 2]] = np.clip(boxes_orig[:, [0, 2]], 0.0, w0 - 1.0)
    boxes_orig[:, [1, 3]] = np.clip(boxes_orig[:, [1, 3]], 0.0, h0 - 1.0)
    names = np.asarray(class_names, dtype="<U16")
    return KittiObjects.from_arrays(
        type=names[labels] if n else np.zeros((0,), "<U16"),
        truncated=np.full(n, -1.0),
        occluded=np.full(n, -1),
        alpha=alpha_kitti,
        bbox=boxes_orig,
        dimensions=dims,
        location=location,
        rotation_y=ry,
        score=c["scores"],
    )


def postprocess(
    candidates: dict[str, jax.Array],
    batch: dict[str, np.ndarray],
    class_names: Sequence[str],
    config: PostprocessConfig,
) -> list[KittiObjects]:
    """:func:`candidates_to_objects` for every image of a batch (host numpy)."""
    cand = {k: np.asarray(jax.device_get(v)) for k, v in candidates.items()}
    input_size = tuple(np.asarray(batch["image"]).shape[1:3])
    results = []
    for b in range(cand["scores"].shape[0]):
        results.append(
            candidates_to_objects(
                {k: v[b] for k, v in cand.items()},
                batch["P2"][b],
                batch["image_transform"][b],
                input_size,
                tuple(int(x) for x in batch["original_size"][b]),
                class_names,
                config,
            )
        )
    return results
