"""Tests of the depth losses against float64 numpy re-implementations written from the
formulas (per-cell loops for the pooling, explicit sums for SI / smoothness)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.depth import depth_loss as dl

# ---------------------------------------------------------------------------------------------
# numpy references


def np_adaptive_pool(x, size, reduce):
    """Per-cell loop with PyTorch's adaptive bins, x (B,H,W,...)."""
    B, H, W = x.shape[:3]
    h, w = size
    out = np.zeros((B, h, w, *x.shape[3:]))
    for i in range(h):
        r0, r1 = math.floor(i * H / h), math.ceil((i + 1) * H / h)
        for j in range(w):
            c0, c1 = math.floor(j * W / w), math.ceil((j + 1) * W / w)
            cell = np.asarray(x[:, r0:r1, c0:c1], np.float64)
            out[:, i, j] = cell.max(axis=(1, 2)) if reduce == "max" else cell.mean(axis=(1, 2))
    return out


def np_downsample(depth, size, min_depth=0.1):
    """Nearest valid point per cell (explicit min over the cell's points > min_depth)."""
    B, H, W = depth.shape
    h, w = size
    out = np.zeros((B, h, w))
    for b in range(B):
        for i in range(h):
            r0, r1 = math.floor(i * H / h), math.ceil((i + 1) * H / h)
            for j in range(w):
                c0, c1 = math.floor(j * W / w), math.ceil((j + 1) * W / w)
                cell = np.asarray(depth[b, r0:r1, c0:c1], np.float64)
                points = cell[cell > min_depth]
                out[b, i, j] = points.min() if points.size else 0.0
    return out


def np_si(log_pred, gt, lam=0.3, lo=0.1, hi=100.0, clip=1e-3):
    log_pred, gt = np.asarray(log_pred, np.float64), np.asarray(gt, np.float64)
    valid = (gt > lo) & (gt < hi)
    d = log_pred[valid] - np.log(gt[valid])
    d[np.abs(d) <= clip] = 0.0
    n = valid.sum()
    if n == 0:
        return 0.0, 0
    return float((d**2).sum() / n - lam * (d.sum() / n) ** 2), int(n)


def np_smooth(z, image, s=1.0):
    z, image = np.asarray(z, np.float64), np.asarray(image, np.float64)
    B, h, w = z.shape
    total = 0.0
    for b in range(B):
        for i in range(h):
            for j in range(w):
                if j + 1 < w:
                    gi = np.abs(image[b, i, j + 1] - image[b, i, j]).mean()
                    total += abs(z[b, i, j + 1] - z[b, i, j]) * np.exp(-s * gi)
                if i + 1 < h:
                    gi = np.abs(image[b, i + 1, j] - image[b, i, j]).mean()
                    total += abs(z[b, i + 1, j] - z[b, i, j]) * np.exp(-s * gi)
    return total / z.size


def sparse_depth(rng, shape, density=0.3):
    depth = rng.uniform(1.0, 90.0, shape)
    depth[rng.random(shape) > density] = 0.0
    depth[rng.random(shape) < 0.02] = 0.05  # below min_depth: not a point
    depth[rng.random(shape) < 0.02] = 150.0  # beyond max_depth
    return depth.astype(np.float32)


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("size", [(4, 8), (5, 7), (13, 17), (1, 3)])
@pytest.mark.parametrize("reduce", ["max", "mean"])
def test_adaptive_pool_matches_per_cell_reference(size, reduce):
    x = np.random.default_rng(0).normal(size=(2, 16, 32, 3)).astype(np.float32)
    if size == (13, 17):
        x = x[:, :15, :29]
    got = np.asarray(jax.jit(lambda a: dl.adaptive_pool(a, size, reduce))(jnp.asarray(x)))
    np.testing.assert_allclose(got, np_adaptive_pool(x, size, reduce), rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="cannot pool"):
        dl.adaptive_pool(jnp.asarray(x), (x.shape[1] + 1, 2), reduce)


def test_downsample_depth_keeps_nearest_valid_point():
    gt = np.zeros((1, 4, 4), np.float32)
    gt[0, 0, 1], gt[0, 1, 0] = 20.0, 5.0  # cell (0,0): nearest is 5
    gt[0, 0, 2], gt[0, 1, 3] = 0.05, 150.0  # cell (0,1): 0.05 is no point -> 150 (beyond max)
    # cell (1,0) empty; cell (1,1): a single point
    gt[0, 3, 3] = 42.0
    got = np.asarray(dl.downsample_depth(jnp.asarray(gt), (2, 2)))
    np.testing.assert_allclose(got[0], [[5.0, 150.0], [0.0, 42.0]], rtol=1e-6)
    mask = np.asarray(dl.valid_depth(jnp.asarray(got)))
    np.testing.assert_array_equal(mask[0], [[True, False], [False, True]])


@pytest.mark.parametrize("size", [(8, 16), (6, 10)])
def test_downsample_depth_matches_reference(size):
    gt = sparse_depth(np.random.default_rng(1), (2, 32, 64), density=0.1)
    gt[:, :12, :20] = 0.0  # an empty region: cells without a point
    got = np.asarray(jax.jit(lambda g: dl.downsample_depth(g, size))(jnp.asarray(gt)))
    np.testing.assert_allclose(got, np_downsample(gt, size), rtol=1e-5)
    assert (got == 0).any() and (got > 0).any()


def test_scale_invariant_loss_clips_small_residuals_and_pools_the_batch():
    rng = np.random.default_rng(2)
    gt = sparse_depth(rng, (3, 8, 12), density=0.6)
    d = rng.normal(0, 0.2, gt.shape) + np.array([0.3, -0.2, 0.0])[:, None, None]
    d.flat[::7] = 5e-4  # |d| <= 1e-3: zeroed (still counted in n)
    d.flat[1::7] = -2e-3  # just above the clip: kept
    pred = (np.log(np.maximum(gt, 1e-3)) + d).astype(np.float32)
    for lam, clip in [(0.3, 1e-3), (0.0, 1e-3), (1.0, 0.0), (0.5, 0.1)]:
        loss, n = dl.scale_invariant_loss(jnp.asarray(pred), jnp.asarray(gt), lam, 0.1, 100, clip)
        ref, n_ref = np_si(pred, gt, lam, clip=clip)
        assert int(n) == n_ref
        np.testing.assert_allclose(float(loss), ref, rtol=2e-5)
    # pooled over the batch: not the mean of per-image losses
    per_image = np.mean([np_si(pred[b : b + 1], gt[b : b + 1])[0] for b in range(3)])
    assert abs(np_si(pred, gt)[0] - per_image) > 2e-3


def test_scale_invariant_gradient_matches_analytic():
    rng = np.random.default_rng(3)
    gt = sparse_depth(rng, (2, 6, 9), density=0.7)
    d = rng.normal(0, 0.3, gt.shape)
    d.flat[::5] = 1e-4
    pred = (np.log(np.maximum(gt, 1e-3)) + d).astype(np.float32)
    grad = jax.grad(lambda p: dl.scale_invariant_loss(p, jnp.asarray(gt))[0])(jnp.asarray(pred))
    valid = (gt > 0.1) & (gt < 100)
    dd = np.where(valid, pred.astype(np.float64) - np.log(np.where(valid, gt, 1.0)), 0.0)
    dd[np.abs(dd) <= 1e-3] = 0.0
    n = valid.sum()
    expected = np.where(dd != 0, 2 * dd / n - 2 * 0.3 * dd.sum() / n**2, 0.0)
    np.testing.assert_allclose(np.asarray(grad), expected, rtol=1e-4, atol=1e-7)


def test_edge_aware_smoothness_matches_reference():
    rng = np.random.default_rng(4)
    z = rng.normal(size=(2, 5, 7)).astype(np.float32)
    image = rng.normal(size=(2, 5, 7, 3)).astype(np.float32)
    for s in (1.0, 20.0):
        got = float(dl.edge_aware_smoothness(jnp.asarray(z), jnp.asarray(image), s))
        np.testing.assert_allclose(got, np_smooth(z, image, s), rtol=1e-5)
    flat = np.ones((1, 4, 4), np.float32)  # constant depth: no penalty whatever the image
    assert float(dl.edge_aware_smoothness(jnp.asarray(flat), jnp.asarray(image[:1, :4, :4]))) == 0


def multi_scale(rng, B=2, H=16, W=32):
    gt = sparse_depth(rng, (B, H, W), density=0.25)
    image = rng.normal(size=(B, H, W, 3)).astype(np.float32)
    sizes = {"scale_1": (H, W), "scale_4": (H // 4, W // 4), "scale_8": (H // 8, W // 8)}
    preds = {k: rng.normal(2.5, 1.0, (B, *s)).astype(np.float32) for k, s in sizes.items()}
    return preds, gt, image


def test_depth_loss_sums_scales_with_paper_and_reference_options():
    preds, gt, image = multi_scale(np.random.default_rng(5))
    jpreds = {k: jnp.asarray(v) for k, v in preds.items()}
    for options, weights in [
        (dl.PAPER_LOSS_OPTIONS, {"scale_1": 1.0, "scale_4": 1.0, "scale_8": 1.0}),
        (dl.REFERENCE_LOSS_OPTIONS, {"scale_1": 1.0, "scale_4": 1.0, "scale_8": 1.0}),
        ({"smooth_weight": 0.003, "edge_sharpness": 20.0}, {"scale_1": 1.0, "scale_8": 0.5}),
    ]:
        kwargs = {k: v for k, v in options.items() if k != "scale_weights"}
        total, parts = jax.jit(
            lambda p, g, i, kw=kwargs, w=weights: dl.depth_loss(p, g, i, **kw, scale_weights=w)
        )(jpreds, jnp.asarray(gt), jnp.asarray(image))
        alpha = kwargs["smooth_weight"]
        s = kwargs["edge_sharpness"]
        expected = 0.0
        for scale, w in weights.items():
            size = preds[scale].shape[1:]
            g = gt if size == gt.shape[1:] else np_downsample(gt, size)
            si, n = np_si(preds[scale], g)
            sm = np_smooth(preds[scale], np_adaptive_pool(image, size, "mean"), s) if alpha else 0
            np.testing.assert_allclose(float(parts[f"si/{scale}"]), si, rtol=1e-4)
            assert int(parts[f"valid/{scale}"]) == n > 0
            expected += w * (si + alpha * sm)
        assert ("smooth/scale_1" in parts) == bool(alpha)
        assert set(k.split("/")[1] for k in parts) == set(weights)
        np.testing.assert_allclose(float(total), expected, rtol=1e-4)
    assert dl.PAPER_LOSS_OPTIONS["smooth_weight"] == 0.3 == dl.PAPER_LOSS_OPTIONS["si_lambda"]


def test_empty_masks_give_zero_loss_and_finite_gradients():
    preds, gt, image = multi_scale(np.random.default_rng(6))
    jpreds = {k: jnp.asarray(v) for k, v in preds.items()}

    def loss(p, g, smooth):
        return dl.depth_loss(p, g, jnp.asarray(image), smooth_weight=smooth)

    value_and_grad = jax.jit(jax.value_and_grad(loss, has_aux=True), static_argnums=2)
    for empty in (np.zeros_like(gt), np.full_like(gt, 0.05), np.full_like(gt, 300.0)):
        for smooth in (0.0, 0.3):
            (total, parts), grads = value_and_grad(jpreds, jnp.asarray(empty), smooth)
            for scale in preds:
                assert float(parts[f"si/{scale}"]) == 0.0 and float(parts[f"valid/{scale}"]) == 0
            assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))
            if smooth == 0.0:
                assert float(total) == 0.0
                assert all(not np.asarray(g).any() for g in jax.tree.leaves(grads))
            else:
                assert float(total) > 0.0  # the smoothness term still acts


def test_depth_loss_rejects_missing_scales_and_mismatched_inputs():
    preds, gt, image = multi_scale(np.random.default_rng(7))
    del preds["scale_4"]
    with pytest.raises(ValueError, match="scale_4"):
        dl.depth_loss(preds, jnp.asarray(gt), jnp.asarray(image))
    total, parts = dl.depth_loss(
        preds, jnp.asarray(gt), jnp.asarray(image), scale_weights={"scale_1": 1, "scale_4": 0}
    )
    assert set(parts) == {"si/scale_1", "valid/scale_1", "smooth/scale_1"}
    with pytest.raises(ValueError, match="one size"):
        dl.depth_loss(preds, jnp.asarray(gt), jnp.asarray(image[:, :8]))
