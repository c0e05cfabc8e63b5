"""Encoding of 3D box targets relative to anchors and their priors, and its inverse.

The 12 regression channels (reference §2.4), for an anchor with centre
``(px, py)`` and size ``(pw, ph)`` (network-input pixels), its bin's prior
``(mu, sigma)`` of ``[z, sin, cos]`` for the GT's class and the class-global
dimension prior:

====  =====  ==============================  ==========
 #     name   target                          divisor
====  =====  ==============================  ==========
 0     dx     (gx - px) / pw                  0.1
 1     dy     (gy - py) / ph                  0.1
 2     dw     ln(gw / pw)                     0.2
 3     dh     ln(gh / ph)                     0.2
 4     cdx    (u_c - px) / pw                 0.1
 5     cdy    (v_c - py) / ph                 0.1
 6     z      (z_h - mu_z) / sigma_z
 7     sin    (sin 2a - mu_s) / sigma_s
 8     cos    (cos 2a - mu_c) / sigma_c
 9     w3d    (w - mu_w) / sigma_w
 10    h3d    (h - mu_h) / sigma_h
 11    l3d    (l - mu_l) / sigma_l
====  =====  ==============================  ==========

``(gx, gy, gw, gh)`` is the GT 2D box (centre, size), ``(u_c, v_c)`` the
projected 3D box centre, ``z_h`` its homogeneous depth ``z + P2[2, 3]``; the
alpha-sign target is ``1[cos a > 0]``. With ``angle_mode="single"`` (paper)
channels 7/8 use ``sin a, cos a`` and decoding ignores the sign.

Decoding: ``a = atan2(s, c) / 2``, plus pi when ``sigmoid(sign_logit) < 0.5``;
the result lies in (-pi/2, 3pi/2] and is not re-wrapped (reference) unless
``wrap_alpha=True``. Note the order of the dimension channels (w, h, l) versus
the project's dimension order ``(h, w, l)`` used by all inputs / outputs here.

All functions accept any leading shape and work on jnp (default) or numpy
(``*_np`` twins, float64) arrays.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gac_jax.detection.anchor_priors import ANGLE_MODES, DetectionConstants

REGRESSION_NAMES = (
    "dx", "dy", "dw", "dh", "cdx", "cdy", "z", "sin", "cos", "w3d", "h3d", "l3d"
)  # fmt: skip
NUM_REGRESSION = len(REGRESSION_NAMES)
BOX_DELTA_STDS = (0.1, 0.1, 0.2, 0.2, 0.1, 0.1)
_HWL_TO_WHL = (1, 0, 2)  # channels 9..11 hold (w, h, l); dims are (h, w, l)


def _check_mode(angle_mode: str) -> None:
    if angle_mode not in ANGLE_MODES:
        raise ValueError(f"angle_mode must be one of {ANGLE_MODES}, got {angle_mode!r}")


def _cxcywh(xp, boxes):
    w = boxes[..., 2] - boxes[..., 0]
    h = boxes[..., 3] - boxes[..., 1]
    return boxes[..., 0] + 0.5 * w, boxes[..., 1] + 0.5 * h, w, h


def _encode(
    xp,
    anchors,
    gt_boxes,
    gt_center,
    gt_depth,
    gt_dims,
    gt_alpha,
    prior_mean,
    prior_std,
    dims_mean,
    dims_std,
    angle_mode,
    sign_axis=0.0,
):
    _check_mode(angle_mode)
    px, py, pw, ph = _cxcywh(xp, anchors)
    gx, gy, gw, gh = _cxcywh(xp, gt_boxes)
    k = 2.0 if angle_mode == "double" else 1.0
    stds = BOX_DELTA_STDS
    box_terms = [
        (gx - px) / pw / stds[0],
        (gy - py) / ph / stds[1],
        xp.log(gw / pw) / stds[2],
        xp.log(gh / ph) / stds[3],
        (gt_center[..., 0] - px) / pw / stds[4],
        (gt_center[..., 1] - py) / ph / stds[5],
    ]
    values_3d = xp.stack([gt_depth, xp.sin(k * gt_alpha), xp.cos(k * gt_alpha)], axis=-1)
    prior_terms = (values_3d - prior_mean) / prior_std
    dims_terms = (gt_dims - dims_mean) / dims_std
    targets = xp.concatenate(
        [xp.stack(box_terms, axis=-1), prior_terms, dims_terms[..., list(_HWL_TO_WHL)]], axis=-1
    )
    sign = (xp.cos(gt_alpha - sign_axis) > 0).astype(targets.dtype)
    return targets, sign


def _decode(
    xp,
    anchors,
    deltas,
    sign_logit,
    prior_mean,
    prior_std,
    dims_mean,
    dims_std,
    angle_mode,
    wrap_alpha,
    sign_axis=0.0,
):
    _check_mode(angle_mode)
    px, py, pw, ph = _cxcywh(xp, anchors)
    stds = BOX_DELTA_STDS
    cx = px + deltas[..., 0] * stds[0] * pw
    cy = py + deltas[..., 1] * stds[1] * ph
    w = pw * xp.exp(deltas[..., 2] * stds[2])
    h = ph * xp.exp(deltas[..., 3] * stds[3])
    boxes = xp.stack([cx - 0.5 * w, cy - 0.5 * h, cx + 0.5 * w, cy + 0.5 * h], axis=-1)
    center = xp.stack(
        [px + deltas[..., 4] * stds[4] * pw, py + deltas[..., 5] * stds[5] * ph], axis=-1
    )
    values_3d = deltas[..., 6:9] * prior_std + prior_mean
    s, c = values_3d[..., 1], values_3d[..., 2]
    if angle_mode == "double":
        alpha = xp.arctan2(s, c) / 2.0  # (-pi/2, pi/2]; alpha or alpha + pi
        if sign_axis:  # the candidate on the positive side of the axis, then the sign bit
            alpha = xp.where(xp.cos(alpha - sign_axis) >= 0.0, alpha, alpha + np.pi)
        alpha = xp.where(sign_logit < 0.0, alpha + np.pi, alpha)  # sigmoid(x) < 0.5 <=> x < 0
    else:
        alpha = xp.arctan2(s, c)
    if wrap_alpha:
        alpha = xp.mod(alpha + np.pi, 2.0 * np.pi) - np.pi
    dims = deltas[..., 9:12][..., list(_HWL_TO_WHL)] * dims_std + dims_mean
    return {
        "boxes": boxes,
        "center": center,
        "depth": values_3d[..., 0],
        "dims": dims,
        "alpha": alpha,
    }


def encode(
    anchor_boxes,
    gt_boxes,
    gt_center,
    gt_depth,
    gt_dims,
    gt_alpha,
    prior_mean,
    prior_std,
    dims_mean,
    dims_std,
    *,
    angle_mode: str = "double",
    sign_axis: float = 0.0,
) -> tuple[jax.Array, jax.Array]:
    """Regression targets of GT boxes relative to anchors (jnp, broadcasting leading dims ``...``).

    Args:
      anchor_boxes: (..., 4) xyxy anchors.
      gt_boxes: (..., 4) xyxy GT 2D boxes.
      gt_center: (..., 2) projected 3D centre ``(u_c, v_c)``.
      gt_depth: (...) homogeneous depth ``z_h`` of the 3D centre.
      gt_dims: (..., 3) ``(h, w, l)``.
      gt_alpha: (...) observation angle.
      prior_mean, prior_std: (..., 3) anchor-bin prior of ``[z, sin, cos]`` for the GT's class.
      dims_mean, dims_std: (..., 3) class prior of ``(h, w, l)``.
      angle_mode: ``"double"`` (reference) or ``"single"`` (paper).
      sign_axis: direction ``t`` of the sign bit, ``1[cos(a - t) > 0]``: 0 is the
        reference's ``1[cos a > 0]``, which is ambiguous for objects seen from straight
        behind or ahead (``a`` near +-pi/2, the commonest case in driving data); pi/4
        moves the ambiguity to oblique views (see :func:`decode`).

    Returns:
      targets (..., 12) in :data:`REGRESSION_NAMES` order, sign target (...)
      ``1[cos(a - sign_axis) > 0]``.
    """
    args = (gt_boxes, gt_center, gt_depth, gt_dims, gt_alpha, prior_mean, prior_std)
    return _encode(jnp, anchor_boxes, *args, dims_mean, dims_std, angle_mode, sign_axis)


def decode(
    anchor_boxes,
    deltas,
    sign_logit,
    prior_mean,
    prior_std,
    dims_mean,
    dims_std,
    *,
    angle_mode: str = "double",
    wrap_alpha: bool = False,
    sign_axis: float = 0.0,
) -> dict[str, jax.Array]:
    """Inverse of :func:`encode` (jnp).

    With ``angle_mode="double"`` the regression gives ``a0 = atan2(s, c) / 2``, i.e.
    ``a`` up to pi. The candidate of ``{a0, a0 + pi}`` on the positive side of
    ``sign_axis`` is taken, plus pi when the sign bit says so. For ``sign_axis = 0`` this
    is exactly the reference (``a0``, plus pi if ``sigmoid(sign) < 0.5``). Near
    ``a = sign_axis +- pi/2`` both the branch of ``atan2`` and the bit flip on small
    errors; elsewhere the choice is stable.

    Args:
      anchor_boxes: (..., 4); deltas: (..., 12) network regression output;
      sign_logit: (...) alpha-sign logit; priors as in :func:`encode`.

    Returns:
      dict with ``'boxes'`` (..., 4) xyxy, ``'center'`` (..., 2) ``(u_c, v_c)``,
      ``'depth'`` (...) homogeneous depth, ``'dims'`` (..., 3) ``(h, w, l)``,
      ``'alpha'`` (...).
    """
    args = (deltas, sign_logit, prior_mean, prior_std, dims_mean, dims_std)
    return _decode(jnp, anchor_boxes, *args, angle_mode, wrap_alpha, sign_axis)


def encode_np(
    *args, angle_mode: str = "double", sign_axis: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Float64 numpy twin of :func:`encode` (same positional arguments)."""
    args = [np.asarray(a, dtype=np.float64) for a in args]
    return _encode(np, *args, angle_mode, sign_axis)


def decode_np(
    *args, angle_mode: str = "double", wrap_alpha: bool = False, sign_axis: float = 0.0
) -> dict[str, np.ndarray]:
    """Float64 numpy twin of :func:`decode` (same positional arguments)."""
    args = [np.asarray(a, dtype=np.float64) for a in args]
    return _decode(np, *args, angle_mode, wrap_alpha, sign_axis)


def gather_priors(
    constants: DetectionConstants, classes: jax.Array
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Priors of every anchor for a per-anchor class choice.

    Args:
      constants: :class:`DetectionConstants` (``N`` anchors, ``K`` classes).
      classes: (B, N) int class per anchor (clipped into ``[0, K)``).

    Returns:
      ``prior_mean, prior_std`` (B, N, 3), ``dims_mean, dims_std`` (B, N, 3),
      ready for :func:`encode` / :func:`decode`.
    """
    k = jnp.clip(jnp.asarray(classes, jnp.int32), 0, constants.num_classes - 1)
    n = jnp.arange(constants.prior_mean.shape[1])[None, :]
    return (
        constants.prior_mean[k, n],
        constants.prior_std[k, n],
        constants.dims_mean[k],
        constants.dims_std[k],
    )


def decode_outputs(
    outputs: dict[str, jax.Array], constants: DetectionConstants, *, wrap_alpha: bool = False
) -> dict[str, jax.Array]:
    """Decodes every anchor of the network outputs with its highest-scoring class (§5 step 1-3).

    Args:
      outputs: ``'cls_logits'`` (B, N, K), ``'sign_logits'`` (B, N), ``'reg'`` (B, N, 12).
      constants: :class:`DetectionConstants`.

    Returns:
      :func:`decode`'s dict (B, N, ...) plus ``'scores'`` (B, N) max class
      probability, ``'labels'`` (B, N) int32 its class, and ``'prior_valid'`` (B, N)
      whether that class's prior of the anchor's bin is valid (drop the others).
      Ground masking, thresholds and NMS are left to the caller.
    """
    logits = jnp.asarray(outputs["cls_logits"], jnp.float32)
    probs = jax.nn.sigmoid(logits)
    labels = jnp.argmax(probs, axis=-1).astype(jnp.int32)
    prior_mean, prior_std, dims_mean, dims_std = gather_priors(constants, labels)
    decoded = decode(
        constants.anchor_boxes[None],
        jnp.asarray(outputs["reg"], jnp.float32),
        jnp.asarray(outputs["sign_logits"], jnp.float32),
        prior_mean,
        prior_std,
        dims_mean,
        dims_std,
        angle_mode=constants.angle_mode,
        sign_axis=constants.sign_axis,
        wrap_alpha=wrap_alpha,
    )
    n = jnp.arange(labels.shape[1])[None, :]
    decoded["scores"] = jnp.max(probs, axis=-1)
    decoded["labels"] = labels
    decoded["prior_valid"] = constants.prior_valid[labels, n]
    return decoded
