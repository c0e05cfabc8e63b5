"""Detection losses: sigmoid focal, modified smooth-L1, alpha-sign BCE and their batch combination.

Per image ``j`` (reference §4): anchors are assigned (:mod:`gac_jax.detection.assignment`);

* ``cls_j = sum(focal over anchors and classes) / (num_pos_j + num_neg_j)`` (0 for
  an image without GT, which still counts in the batch mean);
* ``r_j`` (13,) = regression-term weights * mean over the image's positives of
  [12 smooth-L1 terms, sign-bit BCE] (0 without positives).

Batch (``normalize_by="reference"``, default):
``cls = mean_j cls_j``; ``reg_vec = sum_j n_j r_j / (sum_j n_j + 1e-6)`` with
``n_j`` the number of GT objects of image ``j``; ``reg = mean(reg_vec)``;
``loss = cls + reg``. Every sum runs over the *global* batch, so a jitted step
with the batch sharded over devices computes exactly the single-device loss
(the reference normalises per GPU, which is why its multi-GPU runs lose AP).
``normalize_by="num_positives"`` (RetinaNet style) divides the batch's summed
focal loss and summed per-positive regression losses by the batch's number of
positives instead.

Online hard example mining (``ohem_drop_fraction = f > 0``, the paper's Table 3 row
"w OHEM"): per image, the ``floor(f * num_neg_j)`` negative anchors with the lowest
classification loss (the per-anchor focal loss summed over classes, before the
``focal_min_loss`` zeroing; ties broken towards the lower anchor index) are left out of
the loss exactly as if they were ignored: they add nothing to ``cls_sum`` and are not
counted in ``num_neg`` (so under ``"reference"`` normalisation the per-image divisor
``num_pos + num_neg`` shrinks with them, as it does for anchors the ground filter
removes). The selection is per image, not per batch, so it does not depend on how a
batch is split over devices, and it is a constant of the step (no gradient flows through
the ranking). It acts on top of the focal loss, which already down-weights easy negatives
by ``p^gamma``; positives, ignored anchors and the regression terms are untouched.
:func:`ohem_negative_mask` is the selection alone.

:func:`detection_loss_terms` returns the per-image partial sums and
:func:`combine_loss_terms` the batch formula, so any split of a batch can be
recombined exactly.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from gac_jax.detection.anchor_priors import DetectionConstants
from gac_jax.detection.assignment import IGNORE, assign_anchors
from gac_jax.detection.box_coding import (
    NUM_REGRESSION,
    REGRESSION_NAMES,
    encode,
    gather_priors,
)

REGRESSION_WEIGHTS = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 3.0, 1.0, 1.0, 0.5, 0.5, 0.5, 1.0)
LOSS_TERM_NAMES = (*REGRESSION_NAMES, "sign")
NORMALIZATIONS = ("reference", "num_positives")


@dataclasses.dataclass(frozen=True)
class DetectionLossConfig:
    """Static loss settings (hashable; pass as a static argument or close over it).

    Attributes:
      balance_weights: (K,) focal positive-term weight per class (reference Car: 20;
        Car/Pedestrian/Cyclist: (20, 40, 40)).
      gamma: focal exponent.
      focal_min_loss: focal losses below this are zeroed (reference 1e-5; 0 disables).
      smooth_l1_beta: smooth-L1 transition (reference 1/25 = 0.04).
      smooth_l1_min_residual: residuals ``|d| <=`` this give zero loss (reference 0.01;
        a negative value disables).
      regression_weights: 13 weights of [12 regression terms, sign bit].
      pos_iou, neg_iou, match_low_quality: assignment (:func:`assign_anchors`).
      normalize_by: ``"reference"`` or ``"num_positives"`` (module docstring).
      ohem_drop_fraction: fraction of each image's negatives, the easiest by
        classification loss, left out of the loss (0 = off; the paper's OHEM row: 0.5).
    """

    balance_weights: tuple[float, ...] = (20.0,)
    gamma: float = 2.0
    focal_min_loss: float = 1e-5
    smooth_l1_beta: float = 0.04
    smooth_l1_min_residual: float = 0.01
    regression_weights: tuple[float, ...] = REGRESSION_WEIGHTS
    pos_iou: float = 0.5
    neg_iou: float = 0.4
    match_low_quality: bool = False
    normalize_by: str = "reference"
    ohem_drop_fraction: float = 0.0

    def __post_init__(self):
        object.__setattr__(self, "balance_weights", tuple(float(w) for w in self.balance_weights))
        object.__setattr__(
            self, "regression_weights", tuple(float(w) for w in self.regression_weights)
        )
        if len(self.regression_weights) != NUM_REGRESSION + 1:
            raise ValueError(
                f"regression_weights needs {NUM_REGRESSION + 1} values, "
                f"got {self.regression_weights}"
            )
        if self.normalize_by not in NORMALIZATIONS:
            raise ValueError(
                f"normalize_by must be one of {NORMALIZATIONS}, got {self.normalize_by!r}"
            )
        if not 0.0 <= self.ohem_drop_fraction < 1.0:
            raise ValueError(f"ohem_drop_fraction must be in [0, 1), got {self.ohem_drop_fraction}")
        if not self.neg_iou <= self.pos_iou:
            raise ValueError(f"neg_iou {self.neg_iou} must be <= pos_iou {self.pos_iou}")


def sigmoid_focal_loss(
    logits: jax.Array,
    targets: jax.Array,
    balance_weights: jax.Array,
    gamma: float = 2.0,
    min_loss: float = 1e-5,
) -> jax.Array:
    """Element-wise sigmoid focal loss with ignore targets (reference form, no alpha = 0.25).

    ``bce = -t * bw * log(p) - (1 - t) * log(1 - p)``, weighted by ``(1 - p)^gamma``
    for ``t = 1`` and ``p^gamma`` for ``t = 0``; zero where ``t = -1`` (ignored) or
    where the loss is below ``min_loss``.

    Args:
      logits: (..., K); targets: (..., K) in {-1, 0, 1}; balance_weights: (K,)
        weight of the positive term per class.
    """
    x = jnp.asarray(logits, jnp.float32)
    t = jnp.asarray(targets, jnp.float32)
    p = jax.nn.sigmoid(x)
    positive = t == 1.0
    bce = jnp.where(
        positive,
        jnp.asarray(balance_weights, jnp.float32) * jax.nn.softplus(-x),
        jax.nn.softplus(x),
    )
    base = jnp.where(positive, 1.0 - p, p)
    # An integer exponent keeps the gradient finite where p saturates to exactly 0 or 1.
    focal_weight = base ** int(gamma) if float(gamma).is_integer() else base**gamma
    loss = jnp.where(t < 0.0, 0.0, focal_weight * bce)
    return jnp.where(loss < min_loss, 0.0, loss)


def smooth_l1_loss(
    pred: jax.Array, target: jax.Array, beta: float = 0.04, min_residual: float = 0.01
) -> jax.Array:
    """Element-wise modified smooth-L1 of ``d = |pred - target|``.

    ``0.5 d^2 / beta`` for ``d <= beta``, else ``d - 0.5 beta``; 0 where ``d <= min_residual``.
    """
    d = jnp.abs(jnp.asarray(pred, jnp.float32) - jnp.asarray(target, jnp.float32))
    loss = jnp.where(d <= beta, 0.5 * d * d / beta, d - 0.5 * beta)
    return jnp.where(d <= min_residual, 0.0, loss)


def binary_cross_entropy_with_logits(logits: jax.Array, targets: jax.Array) -> jax.Array:
    """Element-wise ``-t log sigmoid(x) - (1 - t) log sigmoid(-x)`` (stable)."""
    x = jnp.asarray(logits, jnp.float32)
    t = jnp.asarray(targets, jnp.float32)
    return t * jax.nn.softplus(-x) + (1.0 - t) * jax.nn.softplus(x)


def ohem_negative_mask(
    anchor_loss: jax.Array, negative: jax.Array, drop_fraction: float
) -> jax.Array:
    """Negatives kept by online hard example mining (per image; pure, jit-able).

    Args:
      anchor_loss: (B, N) classification loss per anchor (only negatives' values matter).
      negative: (B, N) bool, the anchors that are negatives (positives, ignored and padded
        anchors are False and never counted or dropped).
      drop_fraction: f in [0, 1): drop ``floor(f * num_neg_j)`` negatives of image ``j``.

    Returns:
      (B, N) bool: ``negative`` minus, per image, the ``floor(f * num_neg_j)`` negatives with
      the lowest loss; among equal losses the lower anchor index is dropped first.
    """
    loss = jax.lax.stop_gradient(jnp.asarray(anchor_loss, jnp.float32))
    negative = jnp.asarray(negative, bool)
    num_anchors = negative.shape[-1]
    num_drop = jnp.floor(drop_fraction * negative.sum(axis=-1)).astype(jnp.int32)  # (B,)
    # Negatives first, in increasing loss; a stable sort keeps index order among ties.
    # Non-negatives are keyed +inf and sorted after all of them (index order again).
    key = jnp.where(negative, loss, jnp.inf)
    order = jnp.argsort(key, axis=-1, stable=True)
    positions = jnp.broadcast_to(jnp.arange(num_anchors, dtype=jnp.int32), key.shape)
    rank = jnp.zeros_like(positions).at[jnp.arange(key.shape[0])[:, None], order].set(positions)
    return negative & (rank >= num_drop[:, None])


def _take(values: jax.Array, index: jax.Array) -> jax.Array:
    """``values`` (B, M, ...) gathered at ``index`` (B, N) along M -> (B, N, ...)."""
    idx = index.reshape(index.shape + (1,) * (values.ndim - 2))
    return jnp.take_along_axis(values, idx, axis=1)


def detection_loss_terms(
    outputs: dict[str, jax.Array],
    batch: dict[str, jax.Array],
    constants: DetectionConstants,
    ground_mask: jax.Array | None = None,
    config: DetectionLossConfig = DetectionLossConfig(),
) -> dict[str, jax.Array]:
    """Per-image partial sums of the detection loss (B images, N anchors, M GT, K classes).

    Args:
      outputs: ``'cls_logits'`` (B, N, K), ``'sign_logits'`` (B, N), ``'reg'`` (B, N, 12).
      batch: ``'gt_mask'`` (B, M) bool, ``'gt_class'`` (B, M) int (-1 pad),
        ``'gt_boxes'`` (B, M, 4) xyxy, ``'gt_center'`` (B, M, 2), ``'gt_depth'`` (B, M)
        homogeneous depth, ``'gt_dims'`` (B, M, 3) ``(h, w, l)``, ``'gt_alpha'`` (B, M).
      constants: :class:`DetectionConstants` of the anchors / priors.
      ground_mask: (B, N) bool anchors kept by the ground filter (None: all).
      config: :class:`DetectionLossConfig`.

    Returns:
      dict of per-image arrays: ``'cls_sum'`` (B,) summed focal loss, ``'reg_sum'``
      (B, 13) weighted loss terms summed over positives, ``'num_pos'``, ``'num_neg'``,
      ``'num_gt'`` (B,) float32 counts (``num_neg`` without the negatives OHEM dropped).
    """
    cls_logits = jnp.asarray(outputs["cls_logits"], jnp.float32)
    num_classes = cls_logits.shape[-1]
    if num_classes != constants.num_classes or len(config.balance_weights) != num_classes:
        raise ValueError(
            f"class count mismatch: cls_logits have {num_classes}, priors "
            f"{constants.num_classes}, balance_weights {len(config.balance_weights)}"
        )
    gt_mask = jnp.asarray(batch["gt_mask"], bool) & (jnp.asarray(batch["gt_class"]) >= 0)
    assignment = assign_anchors(
        constants.anchor_boxes,
        batch["gt_boxes"],
        gt_mask,
        batch["gt_class"],
        ground_mask=ground_mask,
        prior_valid=constants.prior_valid,
        pos_iou=config.pos_iou,
        neg_iou=config.neg_iou,
        match_low_quality=config.match_low_quality,
    )
    positive = assignment.positive  # (B, N)

    # Classification: one-hot on positives, 0 on negatives, -1 on ignored anchors.
    onehot = assignment.matched_class[..., None] == jnp.arange(num_classes)
    cls_targets = jnp.where(
        (assignment.labels == IGNORE)[..., None], -1.0, (positive[..., None] & onehot) * 1.0
    )
    negative = assignment.negative
    if config.ohem_drop_fraction > 0.0:
        focal = sigmoid_focal_loss(
            cls_logits,
            cls_targets,
            jnp.asarray(config.balance_weights, jnp.float32),
            config.gamma,
            0.0,
        )
        kept = ohem_negative_mask(focal.sum(axis=-1), negative, config.ohem_drop_fraction)
        dropped = negative & ~kept
        focal = jnp.where(dropped[..., None] | (focal < config.focal_min_loss), 0.0, focal)
        negative = kept
    else:
        focal = sigmoid_focal_loss(
            cls_logits,
            cls_targets,
            jnp.asarray(config.balance_weights, jnp.float32),
            config.gamma,
            config.focal_min_loss,
        )

    # Regression targets of every anchor's matched GT (garbage is masked to 0 off positives).
    anchors = jnp.broadcast_to(constants.anchor_boxes[None], positive.shape + (4,))
    m = assignment.matched_gt
    gt_boxes = jnp.where(positive[..., None], _take(jnp.asarray(batch["gt_boxes"]), m), anchors)
    prior_mean, prior_std, dims_mean, dims_std = gather_priors(constants, assignment.matched_class)
    targets, sign_targets = encode(
        anchors,
        gt_boxes.astype(jnp.float32),
        _take(jnp.asarray(batch["gt_center"], jnp.float32), m),
        _take(jnp.asarray(batch["gt_depth"], jnp.float32), m),
        _take(jnp.asarray(batch["gt_dims"], jnp.float32), m),
        _take(jnp.asarray(batch["gt_alpha"], jnp.float32), m),
        prior_mean,
        prior_std,
        dims_mean,
        dims_std,
        angle_mode=constants.angle_mode,
        sign_axis=constants.sign_axis,
    )
    targets = jax.lax.stop_gradient(jnp.where(positive[..., None], targets, 0.0))
    reg = smooth_l1_loss(
        outputs["reg"], targets, config.smooth_l1_beta, config.smooth_l1_min_residual
    )
    sign = binary_cross_entropy_with_logits(outputs["sign_logits"], sign_targets)
    terms = jnp.concatenate([reg, sign[..., None]], axis=-1)
    terms = terms * jnp.asarray(config.regression_weights, jnp.float32)
    terms = jnp.where(positive[..., None], terms, 0.0)
    return {
        "cls_sum": focal.sum(axis=(1, 2)),
        "reg_sum": terms.sum(axis=1),
        "num_pos": positive.sum(axis=1).astype(jnp.float32),
        "num_neg": negative.sum(axis=1).astype(jnp.float32),
        "num_gt": gt_mask.sum(axis=1).astype(jnp.float32),
    }


def combine_loss_terms(
    terms: dict[str, jax.Array], config: DetectionLossConfig = DetectionLossConfig()
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Batch combination of :func:`detection_loss_terms` (module docstring).

    Returns:
      ``(loss, metrics)``: scalar float32 loss and a dict of scalars: ``'loss'``,
      ``'cls_loss'``, ``'reg_loss'``, ``'reg/<term>'`` for the 13 terms (weighted,
      batch-combined), ``'num_positives'``, ``'num_negatives'``, ``'num_gt'``.
    """
    num_pos, num_neg, num_gt = terms["num_pos"], terms["num_neg"], terms["num_gt"]
    if config.normalize_by == "reference":
        has_gt = num_gt > 0
        cls_per_image = jnp.where(
            has_gt, terms["cls_sum"] / jnp.maximum(num_pos + num_neg, 1.0), 0.0
        )
        cls_loss = jnp.mean(cls_per_image)
        reg_per_image = terms["reg_sum"] / jnp.maximum(num_pos, 1.0)[:, None]  # 0 without positives
        reg_vec = (num_gt[:, None] * reg_per_image).sum(0) / (num_gt.sum() + 1e-6)
    else:
        total_pos = jnp.maximum(num_pos.sum(), 1.0)
        cls_loss = terms["cls_sum"].sum() / total_pos
        reg_vec = terms["reg_sum"].sum(0) / total_pos
    reg_loss = jnp.mean(reg_vec)
    loss = cls_loss + reg_loss
    metrics = {"loss": loss, "cls_loss": cls_loss, "reg_loss": reg_loss}
    metrics.update({f"reg/{name}": reg_vec[i] for i, name in enumerate(LOSS_TERM_NAMES)})
    metrics.update(num_positives=num_pos.sum(), num_negatives=num_neg.sum(), num_gt=num_gt.sum())
    return loss, metrics


def detection_loss(
    outputs: dict[str, jax.Array],
    batch: dict[str, jax.Array],
    constants: DetectionConstants,
    ground_mask: jax.Array | None = None,
    config: DetectionLossConfig = DetectionLossConfig(),
) -> tuple[jax.Array, dict[str, jax.Array]]:
    """Total detection loss ``cls + reg`` of a (global) batch and scalar metrics.

    Arguments as in :func:`detection_loss_terms`; result as in :func:`combine_loss_terms`.
    Jit-able with static shapes; ``config`` must be static (it is hashable).
    """
    terms = detection_loss_terms(outputs, batch, constants, ground_mask, config)
    return combine_loss_terms(terms, config)
