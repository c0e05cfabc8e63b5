"""Detection losses vs float64 numpy references; batch semantics; jit / multi-device behaviour."""

from __future__ import annotations

import functools
import os
import subprocess
import sys
from pathlib import Path

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.detection.anchor_priors import AnchorPriors, make_detection_constants
from gac_jax.detection.anchors import AnchorLayout, box_iou_np, generate_anchors
from gac_jax.detection.assignment import assign_anchors
from gac_jax.detection.box_coding import encode, encode_np, gather_priors
from gac_jax.detection.detection_loss import (
    REGRESSION_WEIGHTS,
    DetectionLossConfig,
    binary_cross_entropy_with_logits,
    combine_loss_terms,
    detection_loss,
    detection_loss_terms,
    sigmoid_focal_loss,
    smooth_l1_loss,
)

LAYOUT = AnchorLayout(image_size=(48, 96), base_size=16.0, scales=(1.0, 1.5, 2.0, 3.0))
CONFIG = DetectionLossConfig(balance_weights=(20.0, 40.0))
_loss = jax.jit(functools.partial(detection_loss, config=CONFIG))
_terms = jax.jit(functools.partial(detection_loss_terms, config=CONFIG))


def _np_focal(x, t, bw, gamma=2.0, min_loss=1e-5):
    x, t = np.asarray(x, np.float64), np.asarray(t, np.float64)
    p = 1.0 / (1.0 + np.exp(-x))
    bce = -t * np.log(p) * bw - (1 - t) * np.log(1 - p)
    fw = np.where(t == 1, (1 - p) ** gamma, p**gamma)
    loss = np.where(t == -1, 0.0, fw * bce)
    return np.where(loss < min_loss, 0.0, loss)


def _np_smooth_l1(pred, target, beta=0.04, min_residual=0.01):
    d = np.abs(np.asarray(pred, np.float64) - np.asarray(target, np.float64))
    loss = np.where(d <= beta, 0.5 * d**2 / beta, d - 0.5 * beta)
    return np.where(d <= min_residual, 0.0, loss)


def _np_bce(x, t):
    p = 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))
    return -t * np.log(p) - (1 - t) * np.log(1 - p)


def test_focal_loss_matches_numpy_including_ignores_and_the_small_loss_clip():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal(0, 3, 200), [-9.0, 9.0, -9.0, 9.0]])
    t = np.concatenate([rng.integers(-1, 2, 200), [0, 1, 1, 0]]).astype(np.float64)
    bw = np.where(np.arange(204) % 2 == 0, 20.0, 40.0)
    got = np.asarray(sigmoid_focal_loss(x.reshape(102, 2), t.reshape(102, 2), [20.0, 40.0]))
    want = _np_focal(x, t, bw).reshape(102, 2)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=1e-7)
    assert got.reshape(-1)[200] == 0.0 and got.reshape(-1)[201] == 0.0  # tiny losses clipped
    assert np.all(got.reshape(-1)[t == -1] == 0.0)
    unclipped = np.asarray(sigmoid_focal_loss(x[200:202], t[200:202], 1.0, min_loss=0.0))
    assert 0.0 < unclipped[0] < 1e-5 and 0.0 < unclipped[1] < 1e-5
    # gamma 0 and weight 1 is plain BCE.
    plain = np.asarray(sigmoid_focal_loss(x[:50], np.abs(t[:50]), 1.0, gamma=0.0, min_loss=0.0))
    np.testing.assert_allclose(plain, _np_bce(x[:50], np.abs(t[:50])), rtol=1e-5, atol=1e-7)
    # Saturated probabilities (p == 0 or 1 in float32) keep finite gradients for any gamma.
    for gamma in (0.0, 1.5, 2.0):
        grad = jax.grad(
            lambda z, g=gamma: sigmoid_focal_loss(z, jnp.array([1.0, 0.0]), 20.0, g, 0.0).sum()
        )(jnp.array([60.0, -60.0]))
        assert np.all(np.isfinite(np.asarray(grad))), gamma


def test_smooth_l1_matches_numpy_at_the_thresholds():
    d = np.array([0.0, 0.005, 0.01, 0.0101, 0.02, 0.04, 0.05, 0.1, 1.0, -0.02, -1.0])
    got = np.asarray(smooth_l1_loss(d, np.zeros_like(d)))
    np.testing.assert_allclose(got, _np_smooth_l1(d, 0 * d), rtol=1e-5, atol=1e-8)
    expected_by_hand = [0, 0, 0, 12.5 * 0.0101**2, 0.005, 0.02, 0.03, 0.08, 0.98, 0.005, 0.98]
    np.testing.assert_allclose(got, expected_by_hand, rtol=1e-5, atol=1e-8)
    np.testing.assert_allclose(
        binary_cross_entropy_with_logits([-3.0, 0.0, 4.0], [1.0, 0.0, 1.0]),
        _np_bce([-3.0, 0.0, 4.0], np.array([1.0, 0.0, 1.0])),
        rtol=1e-6,
    )


def _priors(rng, num_classes=2):
    a = LAYOUT.anchors_per_cell
    valid = rng.uniform(size=(num_classes, a)) > 0.25
    valid[:, :2] = True
    return AnchorPriors(
        layout=LAYOUT,
        class_names=("Car", "Pedestrian")[:num_classes],
        angle_mode="double",
        count=np.full((num_classes, a), 50),
        mean=np.stack(
            [
                rng.uniform(5, 40, (num_classes, a)),
                rng.uniform(-0.3, 0.3, (num_classes, a)),
                rng.uniform(-0.3, 0.3, (num_classes, a)),
            ],
            -1,
        ),  # fmt: skip
        std=rng.uniform(0.3, 3.0, (num_classes, a, 3)),
        valid=valid,
        dims_mean=rng.uniform([1.4, 0.6, 0.8], [1.6, 1.7, 4.0], (num_classes, 3)),
        dims_std=rng.uniform(0.1, 0.4, (num_classes, 3)),
        num_objects=np.full(num_classes, 100),
        num_frames=20,
    )


def _case(seed=0, batch=4, max_gt=6, num_classes=2):
    """A batch with uneven GT counts (image 3 empty), padding garbage, a ground mask."""
    rng = np.random.default_rng(seed)
    anchors = generate_anchors(LAYOUT)
    priors = _priors(rng, num_classes)
    n = len(anchors)
    picks = rng.integers(0, n, (batch, max_gt))
    centers = anchors.centers[picks] + rng.normal(0, 3, (batch, max_gt, 2))
    shapes = anchors.shapes[picks] * rng.uniform(0.8, 1.25, (batch, max_gt, 2))
    gt_mask = np.zeros((batch, max_gt), bool)
    for j, count in enumerate([6, 1, 3, 0][:batch]):
        gt_mask[j, :count] = True
    gt_class = np.where(gt_mask, rng.integers(0, num_classes, (batch, max_gt)), -1)
    boxes = np.concatenate([centers - shapes / 2, centers + shapes / 2], -1)
    boxes[~gt_mask] = -1.0  # reference-style padding
    batch_arrays = {
        "gt_mask": gt_mask,
        "gt_class": gt_class.astype(np.int32),
        "gt_boxes": boxes.astype(np.float32),
        "gt_center": (centers + rng.normal(0, 4, centers.shape)).astype(np.float32),
        "gt_depth": rng.uniform(4, 50, (batch, max_gt)).astype(np.float32),
        "gt_dims": rng.uniform([1.3, 0.5, 0.6], [1.9, 1.9, 4.5], (batch, max_gt, 3)).astype(
            np.float32
        ),
        "gt_alpha": rng.uniform(-3.0, 3.0, (batch, max_gt)).astype(np.float32),
    }
    outputs = {
        "cls_logits": rng.normal(-1, 2, (batch, n, num_classes)).astype(np.float32),
        "sign_logits": rng.normal(0, 2, (batch, n)).astype(np.float32),
        "reg": rng.normal(0, 1, (batch, n, 12)).astype(np.float32),
    }
    ground = rng.uniform(size=(batch, n)) > 0.15
    return anchors, priors, outputs, batch_arrays, ground


def _np_reference_loss(anchors, priors, outputs, batch, ground, config, normalize_by="reference"):
    """Per-image float64 loop following reference §4 literally."""
    mean_eff, std_eff = priors.effective_mean(), priors.effective_std()
    weights = np.asarray(REGRESSION_WEIGHTS)
    cls_j, reg_j, n_j, pos_j = [], [], [], []
    cls_sums, reg_sums = [], []
    for j in range(batch["gt_mask"].shape[0]):
        real = np.flatnonzero(batch["gt_mask"][j] & (batch["gt_class"][j] >= 0))
        n_j.append(len(real))
        if len(real) == 0:
            cls_j.append(0.0), reg_j.append(np.zeros(13)), pos_j.append(0)
            cls_sums.append(0.0), reg_sums.append(np.zeros(13))
            continue
        iou = box_iou_np(anchors.boxes, batch["gt_boxes"][j, real])
        best, arg = iou.max(1), real[iou.argmax(1)]
        labels = np.full(len(anchors), -1)
        for a in range(len(anchors)):
            if not ground[j, a]:
                continue
            k = batch["gt_class"][j, arg[a]]
            if best[a] >= 0.5 and priors.valid[k, anchors.bin_index[a]]:
                labels[a] = 1
            elif best[a] < 0.4:
                labels[a] = 0
        pos = np.flatnonzero(labels == 1)
        t = np.where(labels[:, None] == -1, -1.0, 0.0) * np.ones((1, priors.num_classes))
        t[pos, batch["gt_class"][j, arg[pos]]] = 1.0
        focal = _np_focal(outputs["cls_logits"][j], t, np.asarray(config.balance_weights))
        num_neg = (labels == 0).sum()
        cls_sums.append(focal.sum())
        cls_j.append(focal.sum() / (len(pos) + num_neg))
        pos_j.append(len(pos))
        if len(pos) == 0:
            reg_j.append(np.zeros(13)), reg_sums.append(np.zeros(13))
            continue
        m, k, b = arg[pos], batch["gt_class"][j, arg[pos]], anchors.bin_index[pos]
        targets, sign = encode_np(
            anchors.boxes[pos], batch["gt_boxes"][j, m], batch["gt_center"][j, m],
            batch["gt_depth"][j, m], batch["gt_dims"][j, m], batch["gt_alpha"][j, m],
            mean_eff[k, b], std_eff[k, b], priors.dims_mean[k], priors.dims_std[k],
        )  # fmt: skip
        per = np.concatenate(
            [_np_smooth_l1(outputs["reg"][j, pos], targets),
             _np_bce(outputs["sign_logits"][j, pos], sign)[:, None]], axis=1,
        ) * weights  # fmt: skip
        reg_sums.append(per.sum(0))
        reg_j.append(per.mean(0))
    n_j, reg_j = np.asarray(n_j, np.float64), np.asarray(reg_j)
    if normalize_by == "reference":
        cls = np.mean(cls_j)
        reg_vec = (n_j[:, None] * reg_j).sum(0) / (n_j.sum() + 1e-6)
    else:
        total = max(sum(pos_j), 1)
        cls = np.sum(cls_sums) / total
        reg_vec = np.sum(reg_sums, 0) / total
    return cls + reg_vec.mean(), cls, reg_vec, sum(pos_j)


@pytest.mark.parametrize("normalize_by", ["reference", "num_positives"])
def test_batch_loss_matches_a_per_image_numpy_loop(normalize_by):
    anchors, priors, outputs, batch, ground = _case(seed=1)
    config = DetectionLossConfig(balance_weights=(20.0, 40.0), normalize_by=normalize_by)
    const = make_detection_constants(anchors, priors)
    loss_fn = jax.jit(functools.partial(detection_loss, config=config))
    loss, metrics = loss_fn(outputs, batch, const, ground)
    want, cls, reg_vec, num_pos = _np_reference_loss(
        anchors, priors, outputs, batch, ground, config, normalize_by
    )
    assert num_pos >= 10 and metrics["num_positives"] == num_pos
    np.testing.assert_allclose(metrics["cls_loss"], cls, rtol=1e-4)
    for i, name in enumerate(["dx", "dy", "dw", "dh", "cdx", "cdy", "z", "sin", "cos", "w3d"]):
        np.testing.assert_allclose(metrics[f"reg/{name}"], reg_vec[i], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(metrics["reg/sign"], reg_vec[12], rtol=1e-4)
    np.testing.assert_allclose(loss, want, rtol=1e-4)
    assert metrics["num_gt"] == 10


def test_images_without_gt_count_in_the_classification_mean():
    anchors, priors, outputs, batch, ground = _case(seed=2)
    const = make_detection_constants(anchors, priors)
    terms = _terms(outputs, batch, const, ground)
    assert terms["num_pos"][3] == 0 and terms["num_neg"][3] == 0 and terms["cls_sum"][3] == 0
    _, metrics = combine_loss_terms(terms, CONFIG)
    per_image = terms["cls_sum"][:3] / (terms["num_pos"][:3] + terms["num_neg"][:3])
    np.testing.assert_allclose(metrics["cls_loss"], per_image.sum() / 4, rtol=1e-6)
    empty = dict(batch, gt_mask=np.zeros_like(batch["gt_mask"]))
    loss, metrics = _loss(outputs, empty, const, ground)
    assert float(loss) == 0.0 and metrics["num_gt"] == 0


def test_perfect_prediction_gives_zero_loss():
    anchors, priors, _, batch, ground = _case(seed=3)
    const = make_detection_constants(anchors, priors)
    assign = jax.jit(assign_anchors)(
        const.anchor_boxes, batch["gt_boxes"], batch["gt_mask"], batch["gt_class"],
        ground_mask=ground, prior_valid=const.prior_valid,
    )  # fmt: skip
    m = assign.matched_gt

    def take(x):
        return jnp.take_along_axis(jnp.asarray(x), m.reshape(m.shape + (1,) * (x.ndim - 2)), 1)

    pm, ps, dm, ds = gather_priors(const, assign.matched_class)
    anchor_boxes = jnp.broadcast_to(const.anchor_boxes, m.shape + (4,))
    gt_boxes = jnp.where(assign.positive[..., None], take(batch["gt_boxes"]), anchor_boxes)
    targets, sign = encode(
        anchor_boxes, gt_boxes, take(batch["gt_center"]), take(batch["gt_depth"]),
        take(batch["gt_dims"]), take(batch["gt_alpha"]), pm, ps, dm, ds,
    )  # fmt: skip
    onehot = assign.matched_class[..., None] == jnp.arange(2)
    outputs = {
        "cls_logits": jnp.where(assign.positive[..., None] & onehot, 25.0, -25.0),
        "sign_logits": jnp.where(sign > 0.5, 25.0, -25.0),
        "reg": jnp.where(assign.positive[..., None], targets, 0.0),
    }
    loss, metrics = _loss(outputs, batch, const, ground)
    assert metrics["num_positives"] >= 10
    assert float(metrics["cls_loss"]) == 0.0
    for name in ("dx", "dy", "dw", "dh", "cdx", "cdy", "z", "sin", "cos", "w3d", "h3d", "l3d"):
        assert float(metrics[f"reg/{name}"]) == 0.0, name
    assert float(metrics["reg/sign"]) < 1e-9 and float(loss) < 1e-9
    # Off by 0.5 on the depth channel: only the z term (weight 3) is non-zero.
    shifted = dict(outputs, reg=outputs["reg"].at[..., 6].add(0.5))
    _, m2 = _loss(shifted, batch, const, ground)
    np.testing.assert_allclose(m2["reg/z"], 3 * (0.5 - 0.02) * 10 / (10 + 1e-6), rtol=1e-5)
    assert float(m2["reg/dx"]) == 0.0 and float(m2["cls_loss"]) == 0.0


def test_loss_traces_once_per_shape_and_has_finite_gradients():
    anchors, priors, outputs, batch, ground = _case(seed=4)
    const = make_detection_constants(anchors, priors)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def step(outputs, batch, ground):
        return jax.value_and_grad(lambda o: detection_loss(o, batch, const, ground, CONFIG)[0])(
            outputs
        )

    loss_a, grads = step(outputs, batch, ground)
    _, _, outputs_b, batch_b, ground_b = _case(seed=5)
    loss_b, _ = step(outputs_b, batch_b, ground_b)
    assert float(loss_a) != float(loss_b)
    for g in jax.tree.leaves(grads):
        assert np.all(np.isfinite(np.asarray(g)))
    assert np.abs(np.asarray(grads["reg"])).sum() > 0 and np.abs(grads["cls_logits"]).sum() > 0


def test_split_batch_recombines_to_the_full_batch_loss():
    anchors, priors, outputs, batch, ground = _case(seed=6)
    const = make_detection_constants(anchors, priors)
    full, _ = _loss(outputs, batch, const, ground)
    halves = []
    for sl in (slice(0, 2), slice(2, 4)):
        part = (
            jax.tree.map(lambda x, sl=sl: x[sl], outputs),
            jax.tree.map(lambda x, sl=sl: x[sl], batch),
        )
        halves.append(_terms(*part, const, ground[sl]))
    merged = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), *halves)
    combined, _ = combine_loss_terms(merged, CONFIG)
    np.testing.assert_allclose(combined, full, rtol=1e-6)
    # The reference's multi-GPU semantics (per-half loss, then averaged) is different.
    per_half = [combine_loss_terms(h, CONFIG)[0] for h in halves]
    assert abs(float(np.mean(per_half)) - float(full)) > 1e-3 * float(full)


def _two_device_check() -> None:
    """Run in a subprocess with 2 host devices: sharded-batch loss/grad == one-device result."""
    assert jax.device_count() == 2, jax.devices()
    anchors, priors, outputs, batch, ground = _case(seed=7)
    const = make_detection_constants(anchors, priors)

    def loss_and_grad(outputs, batch, ground):
        fn = lambda o: detection_loss(o, batch, const, ground, CONFIG)[0]  # noqa: E731
        return jax.value_and_grad(fn)(outputs)

    single = jax.jit(loss_and_grad)(outputs, batch, ground)
    mesh = jax.make_mesh((2,), ("data",), (jax.sharding.AxisType.Auto,))
    shard = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("data"))
    args = jax.device_put((outputs, batch, ground), shard)
    sharded = jax.jit(loss_and_grad)(*args)
    assert len(args[0]["reg"].sharding.device_set) == 2
    np.testing.assert_allclose(sharded[0], single[0], rtol=1e-6)
    for a, b in zip(jax.tree.leaves(sharded[1]), jax.tree.leaves(single[1]), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-9)
    print("two-device loss", float(sharded[0]), float(single[0]))


def test_loss_with_the_batch_sharded_over_two_devices_equals_one_device():
    tests_dir = Path(__file__).resolve().parent
    # the session's fast-compile flags (tests/conftest.py) stay, two CPU devices are added
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    env["PYTHONPATH"] = os.pathsep.join([str(tests_dir.parent), str(tests_dir)])
    code = "import test_detection_loss as t; t._two_device_check()"
    result = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert "two-device loss" in result.stdout
