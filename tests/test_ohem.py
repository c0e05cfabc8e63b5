"""OHEM (the paper's Table 3 row "w OHEM"): the easiest half of each image's negatives leave
the loss. Hand-made losses (ties, ignored and positive anchors, images without negatives) and
the loss-level effect against the numpy loop of test_detection_loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.detection.anchor_priors import make_detection_constants
from gac_jax.detection.detection_loss import (
    DetectionLossConfig,
    detection_loss,
    detection_loss_terms,
    ohem_negative_mask,
    sigmoid_focal_loss,
)
from tests.test_detection_loss import _case


def np_ohem(loss, negative, fraction):
    """Reference: per image, sort the negatives by (loss, index) and drop the first
    floor(fraction * count)."""
    keep = np.zeros_like(negative)
    for j in range(loss.shape[0]):
        idx = np.flatnonzero(negative[j])
        ranked = sorted(idx, key=lambda a: (float(loss[j, a]), a))
        n_drop = int(np.floor(fraction * len(idx)))
        keep[j, ranked[n_drop:]] = True
    return keep


def test_ohem_drops_exactly_the_easiest_half_with_ties_and_non_negatives():
    # anchor:        0    1    2     3    4    5    6    7
    loss = np.array(
        [
            [0.3, 0.1, 0.05, 0.0, 0.1, 0.0, 0.9, 0.1],  # 3 positive, 5 ignored (lowest losses)
            [0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2, 0.2],  # all tied, 3 negatives
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # no negatives at all (padding image)
        ],
        np.float32,
    )
    negative = np.array(
        [
            [1, 1, 1, 0, 1, 0, 1, 1],
            [0, 1, 0, 0, 1, 0, 1, 0],
            [0, 0, 0, 0, 0, 0, 0, 0],
        ],
        bool,
    )
    keep = np.asarray(jax.jit(ohem_negative_mask, static_argnums=2)(loss, negative, 0.5))
    # image 0: 6 negatives, drop 3: anchor 2 (0.05) then the 0.1-ties 1 and 4 (lower index
    # first); the tied anchor 7 stays. Positive 3 and ignored 5 are neither kept nor dropped.
    assert np.flatnonzero(keep[0]).tolist() == [0, 6, 7]
    # image 1: 3 tied negatives, floor(1.5) = 1 dropped: the lowest index.
    assert np.flatnonzero(keep[1]).tolist() == [4, 6]
    assert not keep[2].any()
    np.testing.assert_array_equal(keep, np_ohem(loss, negative, 0.5))
    # fraction 0 keeps every negative
    np.testing.assert_array_equal(np.asarray(ohem_negative_mask(loss, negative, 0.0)), negative)


@pytest.mark.parametrize("fraction", [0.5, 0.25, 0.9])
def test_ohem_matches_the_sorting_reference_on_random_tied_losses(fraction):
    rng = np.random.default_rng(3)
    loss = np.round(rng.uniform(0, 1, (4, 300)), 1).astype(np.float32)  # many ties
    negative = rng.uniform(size=(4, 300)) > 0.3
    negative[3] = False
    keep = np.asarray(ohem_negative_mask(loss, negative, fraction))
    np.testing.assert_array_equal(keep, np_ohem(loss, negative, fraction))
    counts = negative.sum(1)
    np.testing.assert_array_equal(keep.sum(1), counts - np.floor(fraction * counts))
    assert not (keep & ~negative).any()


def test_ohem_in_the_loss_removes_the_dropped_negatives_from_sum_and_normaliser():
    anchors, priors, outputs, batch, ground = _case(seed=4)
    const = make_detection_constants(anchors, priors)
    base = DetectionLossConfig(balance_weights=(20.0, 40.0))
    ohem = DetectionLossConfig(balance_weights=(20.0, 40.0), ohem_drop_fraction=0.5)
    traces = []

    def terms_fn(o, b, g, config):
        traces.append(1)
        return detection_loss_terms(o, b, const, g, config)

    run = jax.jit(terms_fn, static_argnums=3)
    t_off = jax.device_get(run(outputs, batch, ground, base))
    t_on = jax.device_get(run(outputs, batch, ground, ohem))
    run(jax.tree.map(lambda x: x + 0, outputs), batch, ground, ohem)
    assert len(traces) == 2  # once per static config, not per call

    # Independent recomputation: the per-anchor focal loss (float64 numpy of the same targets)
    # and the numpy OHEM reference.
    from gac_jax.detection.assignment import IGNORE, assign_anchors

    a = assign_anchors(
        const.anchor_boxes,
        batch["gt_boxes"],
        batch["gt_mask"],
        batch["gt_class"],
        ground_mask=ground,
        prior_valid=const.prior_valid,
    )
    labels, negative = np.asarray(a.labels), np.asarray(a.negative)
    onehot = np.asarray(a.matched_class)[..., None] == np.arange(2)
    targets = np.where((labels == IGNORE)[..., None], -1.0, (labels == 1)[..., None] & onehot)
    raw = np.asarray(
        sigmoid_focal_loss(outputs["cls_logits"], targets, jnp.asarray([20.0, 40.0]), 2.0, 0.0),
        np.float64,
    )
    keep = np_ohem(raw.sum(-1), negative, 0.5)
    dropped = negative & ~keep
    assert dropped.sum() > 100
    counted = np.where(raw < 1e-5, 0.0, raw)
    want_cls = np.where(dropped[..., None], 0.0, counted).sum((1, 2))
    np.testing.assert_allclose(t_on["cls_sum"], want_cls, rtol=1e-5)
    np.testing.assert_allclose(t_off["cls_sum"], counted.sum((1, 2)), rtol=1e-5)
    np.testing.assert_array_equal(t_on["num_neg"], keep.sum(1))
    np.testing.assert_array_equal(t_off["num_neg"], negative.sum(1))
    np.testing.assert_array_equal(
        t_on["num_neg"], t_off["num_neg"] - np.floor(0.5 * t_off["num_neg"])
    )
    # positives and the regression terms are untouched
    np.testing.assert_array_equal(t_on["num_pos"], t_off["num_pos"])
    np.testing.assert_allclose(t_on["reg_sum"], t_off["reg_sum"], rtol=1e-6)
    # dropped negatives get no gradient; kept ones do
    grad = jax.jit(
        jax.grad(
            lambda logits: detection_loss(
                dict(outputs, cls_logits=logits), batch, const, ground, ohem
            )[0]
        )
    )(jnp.asarray(outputs["cls_logits"]))
    g = np.abs(np.asarray(grad)).sum(-1)
    assert not g[dropped].any()
    assert (g[keep & (counted.sum(-1) > 0)] > 0).all()


def test_ohem_fraction_is_validated():
    with pytest.raises(ValueError, match="ohem_drop_fraction"):
        DetectionLossConfig(ohem_drop_fraction=1.0)
    assert DetectionLossConfig(ohem_drop_fraction=0.5).ohem_drop_fraction == 0.5
