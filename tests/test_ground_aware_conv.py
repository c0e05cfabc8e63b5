"""Tests of the ground-aware convolution: helpers against float64 numpy oracles, the module
against an independent NCHW re-implementation of the reference LookGround (torch-layout
weights converted through the naming table), a real KITTI calibration, and gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from gac_jax.data.files import read_image
from gac_jax.data.kitti import read_calib
from gac_jax.models import naming
from gac_jax.models.ground_aware_conv import (
    GroundAwareConv,
    base_offset,
    disparity_prior,
    feature_projection,
    vertical_gather,
)

# ---------------------------------------------------------------------------------------------
# numpy oracles (float64)


def np_vertical_interp(features: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Per-element 1-D linear interpolation along axis 1 with border clamping (loops)."""
    B, H, W, C = features.shape
    out = np.zeros(features.shape, np.float64)
    for b in range(B):
        for v in range(H):
            for u in range(W):
                r = min(max(float(rows[b, v, u]), 0.0), H - 1.0)
                lo, hi = int(np.floor(r)), int(np.ceil(r))
                if lo == hi:
                    out[b, v, u] = features[b, lo, u]
                else:
                    out[b, v, u] = (hi - r) * features[b, lo, u] + (r - lo) * features[b, hi, u]
    return out


def np_conv_nchw(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Stride-1 'same' convolution, x (B,C,H,W), torch weight w (O,I,k,k), bias (O,)."""
    k = w.shape[-1]
    pad = (k - 1) // 2
    xp = np.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)))
    win = sliding_window_view(xp, (k, k), axis=(2, 3))  # (B,C,H,W,k,k)
    return np.einsum("bchwij,ocij->bohw", win, w) + b[None, :, None, None]


def np_grid_sample_border(img: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """2-D bilinear grid_sample(align_corners=True, padding_mode='border'); img (B,C,H,W),
    gx/gy (B,Hg,Wg) normalised to [-1, 1]."""
    B, C, H, W = img.shape
    x = np.clip((gx + 1) / 2 * (W - 1), 0, W - 1)
    y = np.clip((gy + 1) / 2 * (H - 1), 0, H - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    wx, wy = x - x0, y - y0
    out = np.zeros((B, C) + gx.shape[1:], np.float64)
    for b in range(B):
        for yy, xx, wgt in (
            (y0, x0, (1 - wy) * (1 - wx)),
            (y0, x1, (1 - wy) * wx),
            (y1, x0, wy * (1 - wx)),
            (y1, x1, wy * wx),
        ):
            out[b] += img[b][:, yy[b], xx[b]] * wgt[b][None]
    return out


def np_look_ground(x_nchw, P, sd, stride, baseline=0.54, el=1.65, h=1.535):
    """The reference LookGround forward in NCHW from a torch-style state dict ``sd``."""
    x = x_nchw.astype(np.float64)
    B, C, H, W = x.shape
    Pf = np.asarray(P, np.float64).copy()
    Pf[:, 0:2] /= stride
    d = 0.1 * np.tanh(np_conv_nchw(x, sd["disp_create.0.weight"], sd["disp_create.0.bias"]))
    fy, cy, ty = Pf[:, 1, 1, None], Pf[:, 1, 2, None], Pf[:, 1, 3, None]
    v = np.arange(H, dtype=np.float64)[None]
    disp = np.maximum(fy * baseline * (v - cy) / (np.abs(fy * el + ty) + 1e-10), 0)  # (B,H)
    base = np.maximum(h * (v - cy) / (2 * (el - h / 2)), 0) / (H / 2)  # normalised
    gx = np.broadcast_to(np.linspace(-1, 1, W)[None, None, :], (B, H, W))
    gy = np.linspace(-1, 1, H)[None, :, None] + base[:, :, None] + d[:, 0]
    G = np.concatenate([np.broadcast_to(disp[:, None, :, None], (B, 1, H, W)), x], axis=1)
    S = np_grid_sample_border(G, gx, gy)
    y = np_conv_nchw(S, sd["extract.weight"], sd["extract.bias"])
    return np.maximum(x + sd["alpha"][0] * y, 0)


def _kitti_like_P(fy: float, cy: float, ty: float = 0.0) -> np.ndarray:
    return np.array(
        [[fy, 0.0, 600.0, 45.0], [0.0, fy, cy, ty], [0.0, 0.0, 1.0, 0.003]], dtype=np.float64
    )


# ---------------------------------------------------------------------------------------------
# vertical_gather


def test_vertical_gather_matches_numpy_including_out_of_range():
    rng = np.random.default_rng(0)
    B, H, W, C = 2, 6, 5, 3
    features = rng.normal(size=(B, H, W, C))
    rows = rng.uniform(-3.0, H + 2.0, size=(B, H, W))  # many clamp at either border
    rows[0, 0, :3] = [0.0, H - 1.0, 2.0]  # exact integers and the bottom border
    expected = np_vertical_interp(features, rows)
    with jax.enable_x64(True):
        got = np.asarray(vertical_gather(jnp.asarray(features), jnp.asarray(rows)))
    assert (rows < 0).any() and (rows > H - 1).any()
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    got32 = np.asarray(vertical_gather(jnp.asarray(features, jnp.float32), jnp.asarray(rows)))
    np.testing.assert_allclose(got32, expected, rtol=1e-5, atol=1e-5)


def test_vertical_gather_gradients_match_finite_differences():
    rng = np.random.default_rng(1)
    B, H, W, C = 2, 5, 4, 3
    features = rng.normal(size=(B, H, W, C))
    rows = rng.uniform(-2.0, H + 1.0, size=(B, H, W))
    frac = rows - np.round(rows)
    rows = np.where(np.abs(frac) < 0.05, rows + 0.1, rows)  # keep away from kinks
    rows = np.where(np.abs(rows) < 0.05, 0.3, rows)
    rows = np.where(np.abs(rows - (H - 1)) < 0.05, H - 1.3, rows)
    cot = rng.normal(size=(B, H, W, C))
    eps = 1e-6
    with jax.enable_x64(True):
        F, R, T = jnp.asarray(features), jnp.asarray(rows), jnp.asarray(cot)

        @jax.jit
        def outputs(f, r):
            return vertical_gather(f, r) * T

        def loss(f, r):
            return jnp.sum(outputs(f, r))

        g_f, g_r = jax.grad(loss, argnums=(0, 1))(F, R)
        g_f, g_r = np.asarray(g_f), np.asarray(g_r)
        # rows: each output depends on its own row only, so one +-eps shift of all rows gives
        # every partial derivative at once.
        fd_r = np.sum(np.asarray(outputs(F, R + eps) - outputs(F, R - eps)), axis=-1) / (2 * eps)
        fd_f = np.zeros_like(features)
        for idx in np.ndindex(features.shape):
            step = np.zeros_like(features)
            step[idx] = eps
            fd_f[idx] = (float(loss(F + step, R)) - float(loss(F - step, R))) / (2 * eps)
    np.testing.assert_allclose(g_r, fd_r, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(g_f, fd_f, rtol=1e-6, atol=1e-8)
    outside = (rows < 0) | (rows > H - 1)
    assert outside.any() and np.all(g_r[outside] == 0.0)  # clamped rows get no gradient
    assert np.all(np.abs(g_r[~outside]) > 0)


def test_vertical_gather_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="rows"):
        vertical_gather(jnp.zeros((1, 4, 3, 2)), jnp.zeros((1, 4, 2)))


# ---------------------------------------------------------------------------------------------
# geometry helpers


def test_disparity_prior_on_real_kitti_calibration(kitti_object_root):
    frame = "000000"
    calib = read_calib(kitti_object_root / "training" / "calib" / f"{frame}.txt")
    height0 = read_image(kitti_object_root / "training" / "image_2" / f"{frame}.png").shape[0]
    assert height0 == 370
    # The reference test chain, applied to P by hand: crop the top 100 rows, then resize to
    # height 288 (rows 0 and 1 of P scaled by s); the right crop to 1280 leaves P unchanged.
    P = calib.P2.copy()
    P[1, 2] -= 100.0
    P[1, 3] -= 100.0 * P[2, 3]
    s = 288.0 / (height0 - 100)
    P[:2] *= s
    Hf, stride = 18, 16
    got = np.asarray(disparity_prior(Hf, P[None], stride))[0]

    fy, cy, ty = P[1, 1] / stride, P[1, 2] / stride, P[1, 3] / stride
    v = np.arange(Hf, dtype=np.float64)
    expected = np.maximum(fy * 0.54 * (v - cy) / abs(fy * 1.65 + ty), 0.0)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-6)
    # hand-computed for frame 000000 (fy_f = 47.1366, cy_f = 5.3671, Ty_f = -0.0562)
    assert got[17] == pytest.approx(3.80988, rel=1e-4)
    assert np.all(got[:6] == 0.0) and got[6] > 0.0  # horizon between feature rows 5 and 6
    # Physical meaning: the prior is the stride-16 disparity of the ground plane, i.e.
    # fx * B / z_ground / 16 for the ground depth at input row 16 v (P[2,3] ignored: < 0.1 %).
    z_ground = (P[1, 1] * 1.65 + P[1, 3]) / (stride * v[6:] - P[1, 2])
    np.testing.assert_allclose(got[6:], P[0, 0] * 0.54 / z_ground / stride, rtol=1e-3)


def test_feature_projection_scales_rows_0_and_1_only():
    P = _kitti_like_P(720.0, 170.0, 0.2)
    Pf = np.asarray(feature_projection(P, 16))
    np.testing.assert_allclose(Pf[:2], P[:2] / 16, rtol=1e-6)
    np.testing.assert_allclose(Pf[2], P[2], rtol=1e-6)
    with pytest.raises(ValueError, match="3, 4"):
        feature_projection(np.zeros((3, 3)), 16)


def test_base_offset_formulas_against_hand_values():
    # stride 10, cy = 170 px -> cy_f = 17; rows 5 (above the horizon), 17, 20, 27.
    P = _kitti_like_P(700.0, 170.0)[None]
    rows = [5, 17, 20, 27]
    paper = np.asarray(base_offset(28, P, 10, offset_formula="paper"))[0, rows]
    fixed = np.asarray(base_offset(28, P, 10, offset_formula="reference"))[0, rows]
    v1 = np.asarray(base_offset(28, P, 10, offset_formula="reference_v1"))[0, rows]
    # 1.535 / (3.3 - 1.535) = 0.86968838...; 1.535 / 2 * (1.65 - 0.7675) = 0.67731875
    np.testing.assert_allclose(paper, [0.0, 0.0, 2.60906516, 8.69688385], rtol=1e-6)
    np.testing.assert_allclose(fixed, paper, rtol=1e-6)
    np.testing.assert_allclose(v1, [0.0, 0.0, 2.03195625, 6.7731875], rtol=1e-6)
    # other constants: h = 1.0, EL = 2.0 -> 1/3 (paper) and 0.75 (release-1.0 bug)
    P1 = _kitti_like_P(700.0, 0.0)[None]
    got = np.asarray(base_offset(4, P1, 1, 1.0, 2.0, "paper"))[0]
    np.testing.assert_allclose(got, np.arange(4) / 3.0, rtol=1e-6)
    got = np.asarray(base_offset(4, P1, 1, 1.0, 2.0, "reference_v1"))[0]
    np.testing.assert_allclose(got, np.arange(4) * 0.75, rtol=1e-6)
    with pytest.raises(ValueError, match="offset_formula"):
        base_offset(4, P1, 1, offset_formula="bogus")


# ---------------------------------------------------------------------------------------------
# the module


B, H, W, C, STRIDE = 2, 8, 6, 4, 16
# two images with their own calibration (feature cy = 2.0 and 3.5)
P_BATCH = np.stack([_kitti_like_P(720.0, 32.0, 0.2), _kitti_like_P(690.0, 56.0, -0.4)])
GAC_PREFIX = "bbox_head.reg_feature_extraction.0."


def _features(seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 2.0, size=(B, H, W, C)).astype(np.float32)


@pytest.fixture(scope="module")
def gac_init():
    x = jnp.asarray(_features(0))
    module = GroundAwareConv(stride=STRIDE, offset_formula="reference")
    variables = module.init(jax.random.key(0), x, jnp.asarray(P_BATCH))
    return module, variables


def _torch_style_gac(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "alpha": np.array([0.7], np.float32),
        "disp_create.0.weight": rng.normal(0, 0.4, size=(1, C, 3, 3)).astype(np.float32),
        "disp_create.0.bias": rng.normal(0, 0.1, size=(1,)).astype(np.float32),
        "extract.weight": rng.normal(0, 0.5, size=(C, C + 1, 1, 1)).astype(np.float32),
        "extract.bias": rng.normal(0, 0.1, size=(C,)).astype(np.float32),
    }


def test_gac_is_identity_at_init(gac_init):
    module, variables = gac_init
    assert float(variables["params"]["alpha"][0]) == 0.0
    x = _features(1)
    out = module.apply(variables, jnp.asarray(x), jnp.asarray(P_BATCH))
    np.testing.assert_array_equal(np.asarray(out["features"]), x)
    assert out["offset_rows"].shape == (B, H, W) and out["sample_rows"].shape == (B, H, W)
    # offsets = geometric part (scaled by (H-1)/H) + learned part within 0.1 * (H-1)/2 rows
    base = np.asarray(base_offset(H, P_BATCH, STRIDE, offset_formula="reference"))
    learned = np.asarray(out["offset_rows"]) - base[:, :, None] * (H - 1) / H
    assert np.all(np.abs(learned) <= 0.1 * (H - 1) / 2 + 1e-6)
    sample = np.asarray(out["sample_rows"])
    assert sample.min() >= 0.0 and sample.max() == H - 1.0  # bottom rows clamp to the border


def test_gac_matches_numpy_reference_with_torch_weights(gac_init):
    module, variables = gac_init
    sd = _torch_style_gac(2)
    template = {"params": {"head": {"gac": variables["params"]}}}
    conv = naming.convert_state_dict(
        {GAC_PREFIX + k: v for k, v in sd.items()}, naming.HEAD_RULES, template
    )
    assert conv.complete, (conv.unused, conv.missing)
    params = conv.variables["params"]["head"]["gac"]
    x = _features(3)
    out = module.apply({"params": params}, jnp.asarray(x), jnp.asarray(P_BATCH))
    expected = np_look_ground(x.transpose(0, 3, 1, 2), P_BATCH, sd, STRIDE)
    got = np.asarray(out["features"]).transpose(0, 3, 1, 2)
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-4)
    # the module really moved features (the check is not vacuous)
    assert np.abs(expected - x.transpose(0, 3, 1, 2)).max() > 0.1


def test_gac_float64_run_matches_numpy_reference_to_1e9(gac_init):
    """Offsets, sampling rows and features stay float64 in a float64 module (no float32 step)."""
    _, variables = gac_init
    sd = _torch_style_gac(6)
    template = {"params": {"head": {"gac": variables["params"]}}}
    conv = naming.convert_state_dict(
        {GAC_PREFIX + k: v for k, v in sd.items()}, naming.HEAD_RULES, template
    )
    x = _features(7).astype(np.float64) + 1e-3 * np.random.default_rng(8).random((B, H, W, C))
    with jax.enable_x64(True):
        module = GroundAwareConv(
            stride=STRIDE, offset_formula="reference", dtype=jnp.float64, param_dtype=jnp.float64
        )
        params = jax.tree.map(lambda a: jnp.asarray(a, jnp.float64), conv.variables["params"])
        out = module.apply({"params": params["head"]["gac"]}, jnp.asarray(x), P_BATCH)
        assert {str(v.dtype) for v in out.values()} == {"float64"}
        got = np.asarray(out["features"]).transpose(0, 3, 1, 2)
    sd64 = {k: np.asarray(v, np.float64) for k, v in sd.items()}
    expected = np_look_ground(x.transpose(0, 3, 1, 2), P_BATCH, sd64, STRIDE)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    assert np.abs(expected - x.transpose(0, 3, 1, 2)).max() > 0.1


def test_gac_offset_gradient_is_scaled_by_0_05(gac_init):
    _, variables = gac_init
    params = {**variables["params"], "alpha": jnp.array([0.5])}
    x, P = jnp.asarray(_features(4)), jnp.asarray(P_BATCH)
    cot = jnp.asarray(np.random.default_rng(5).normal(size=(B, H, W, C)), jnp.float32)

    def grads(grad_scale):
        module = GroundAwareConv(stride=STRIDE, offset_grad_scale=grad_scale)

        def loss(p):
            return jnp.sum(module.apply({"params": p}, x, P)["features"] * cot)

        return jax.grad(loss)(params)

    scaled, full = grads(0.05), grads(1.0)
    g_scaled = np.asarray(scaled["offset_conv"]["kernel"])
    g_full = np.asarray(full["offset_conv"]["kernel"])
    assert np.abs(g_full).max() > 1e-4
    np.testing.assert_allclose(g_scaled, 0.05 * g_full, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(
        np.asarray(scaled["extract"]["kernel"]), np.asarray(full["extract"]["kernel"]), rtol=1e-6
    )


def test_gac_rejects_bad_calibration_shape(gac_init):
    module, variables = gac_init
    with pytest.raises(ValueError, match="P must have shape"):
        module.apply(variables, jnp.asarray(_features(0)), jnp.zeros((B, 3, 3)))
