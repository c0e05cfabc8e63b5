"""Tests of the depth U-Net, its DCNv2 layer and its PyTorch key mapping.

Oracles: float64 numpy re-implementations (align-corners bilinear resize, DCNv2 sampling),
the reference state-dict listing in ``../shared/spec/reference_state_dict.md`` (skipped when
absent), and the real KITTI-depth frame's raw calibration for the GAC intrinsics."""

from __future__ import annotations

import math
import re

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import linen as nn
from flax import traverse_util
from numpy.lib.stride_tricks import sliding_window_view

from gac_jax.data.files import read_image
from gac_jax.models import naming
from gac_jax.models.deformable_conv import ModulatedDeformConv, modulated_deform_conv
from gac_jax.models.depth_unet import (
    DepthUNet,
    ResizedConvHead,
    mean_log_depth,
    output_sizes,
    pad_or_crop_to,
    resize_bilinear_align_corners,
)
from gac_jax.models.ground_aware_conv import GroundAwareConv, feature_projection
from gac_jax.models.initializers import torch_conv_bias_init, torch_conv_kernel_init
from gac_jax.models.resnet import plain_formulation
from tests.test_models import abstract_init, count, parse_reference_keys

IMAGE_SIZE = (64, 256)
TINY = {"depth": 18, "width": 8}


# ---------------------------------------------------------------------------------------------
# resize / pad helpers


def np_resize_align_corners(x, size):
    """Direct 2-D formula: out[o, p] = bilinear(x, o (H-1)/(h-1), p (W-1)/(w-1))."""
    B, H, W, C = x.shape
    h, w = size
    out = np.zeros((B, h, w, C))
    for o in range(h):
        y = o * (H - 1) / (h - 1) if h > 1 else 0.0
        for p in range(w):
            xx = p * (W - 1) / (w - 1) if w > 1 else 0.0
            y0, x0 = min(int(math.floor(y)), H - 1), min(int(math.floor(xx)), W - 1)
            y1, x1 = min(y0 + 1, H - 1), min(x0 + 1, W - 1)
            wy, wx = y - y0, xx - x0
            out[:, o, p] = (
                (1 - wy) * (1 - wx) * x[:, y0, x0]
                + (1 - wy) * wx * x[:, y0, x1]
                + wy * (1 - wx) * x[:, y1, x0]
                + wy * wx * x[:, y1, x1]
            )
    return out


@pytest.mark.parametrize("size", [(6, 10), (12, 20), (5, 7), (1, 4)])
def test_resize_bilinear_align_corners_matches_formula(size):
    x = np.random.default_rng(0).normal(size=(2, 3, 5, 2)).astype(np.float32)
    got = np.asarray(resize_bilinear_align_corners(jnp.asarray(x), size))
    np.testing.assert_allclose(got, np_resize_align_corners(x, size), rtol=1e-5, atol=1e-6)
    if size[0] > 1:
        np.testing.assert_allclose(got[:, [0, -1]][:, :, [0, -1]], x[:, [0, -1]][:, :, [0, -1]])


def test_pad_or_crop_to_pads_zeros_around_and_crops():
    x = jnp.ones((1, 3, 4, 2))
    padded = np.asarray(pad_or_crop_to(x, (6, 5)))
    assert padded.shape == (1, 6, 5, 2)
    np.testing.assert_array_equal(padded[0, :, :, 0].sum(axis=1), [0, 4, 4, 4, 0, 0])
    np.testing.assert_array_equal(padded[0, :, :, 0].sum(axis=0), [3, 3, 3, 3, 0])
    y = jnp.arange(20.0).reshape(1, 4, 5, 1)  # larger: negative pads crop, floor(-1/2) = -1
    cropped = np.asarray(pad_or_crop_to(y, (3, 3)))[0, :, :, 0]
    np.testing.assert_array_equal(cropped, np.asarray(y)[0, 1:4, 1:4, 0])


@pytest.mark.parametrize("size", [(12, 20), (9, 13)])
def test_resized_conv_head_equals_conv_of_the_resized_map(size):
    """Taps-first head == conv3x3(resize(x)) (float64 numpy), same variables as nn.Conv, and
    the same gradients as the plain order (``plain_formulation``)."""
    x = np.random.default_rng(1).normal(size=(2, 4, 6, 5)).astype(np.float32)
    head = ResizedConvHead(size)
    variables = head.init(jax.random.key(3), jnp.asarray(x))
    conv = nn.Conv(1, (3, 3), padding=((1, 1), (1, 1)), kernel_init=torch_conv_kernel_init,
                   bias_init=torch_conv_bias_init(9 * 5))  # fmt: skip
    ref_vars = conv.init(jax.random.key(3), jnp.zeros((1, *size, 5)))
    for a, b in zip(jax.tree.leaves(variables), jax.tree.leaves(ref_vars), strict=True):
        np.testing.assert_array_equal(a, b)
    params = jax.tree.map(np.asarray, variables["params"])
    want = np_conv_same(np_resize_align_corners(x.astype(np.float64), size), params["kernel"],
                        params["bias"])  # fmt: skip
    got = head.apply(variables, jnp.asarray(x))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)

    def loss(v, x):
        return jnp.sum(jnp.sin(head.apply(v, x)))

    fast = jax.jit(jax.grad(loss, argnums=(0, 1)))(variables, jnp.asarray(x))
    with plain_formulation():
        plain = jax.jit(jax.grad(loss, argnums=(0, 1)))(variables, jnp.asarray(x))
    for a, b in zip(jax.tree.leaves(fast), jax.tree.leaves(plain), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5 * float(jnp.max(jnp.abs(b))))


# ---------------------------------------------------------------------------------------------
# modulated deformable convolution


def np_conv_same(x, w, b):
    """x (B,H,W,C), w (k,k,C,F) HWIO -> (B,H,W,F), zero padding k//2."""
    k = w.shape[0]
    p = k // 2
    xp = np.pad(x, ((0, 0), (p, p), (p, p), (0, 0)))
    win = sliding_window_view(xp, (k, k), axis=(1, 2))  # (B,H,W,C,k,k)
    return np.einsum("bhwcij,ijcf->bhwf", win, w) + b


def np_bilinear_zero(img, y, x):
    H, W = img.shape[:2]
    y0, x0 = math.floor(y), math.floor(x)
    val = np.zeros(img.shape[2:])
    for yy, wy in ((y0, 1 - (y - y0)), (y0 + 1, y - y0)):
        for xx, wx in ((x0, 1 - (x - x0)), (x0 + 1, x - x0)):
            if 0 <= yy < H and 0 <= xx < W:
                val += wy * wx * img[yy, xx]
    return val


def np_dcn(x, params):
    """DCNv2 in float64 from its definition: offsets/mask from conv_offset, chunked as
    [dy0, dx0, dy1, dx1, ..., mask logits]."""
    x = np.asarray(x, np.float64)
    p = {
        k: np.asarray(v, np.float64) for k, v in traverse_util.flatten_dict(params, sep="/").items()
    }
    raw = np_conv_same(x, p["conv_offset/kernel"], p["conv_offset/bias"])
    B, H, W, C = x.shape
    kernel = p["kernel"]
    out = np.zeros((B, H, W, kernel.shape[-1]))
    for b in range(B):
        for h in range(H):
            for w in range(W):
                for i in range(3):
                    for j in range(3):
                        k = 3 * i + j
                        dy, dx = raw[b, h, w, 2 * k], raw[b, h, w, 2 * k + 1]
                        m = 1 / (1 + np.exp(-raw[b, h, w, 18 + k]))
                        v = np_bilinear_zero(x[b], h - 1 + i + dy, w - 1 + j + dx)
                        out[b, h, w] += m * v @ kernel[i, j]
    return out + p["bias"]


def test_deformable_conv_at_init_is_half_a_regular_conv():
    x = jnp.asarray(np.random.default_rng(1).normal(size=(2, 7, 9, 5)).astype(np.float32))
    layer = ModulatedDeformConv(6)
    params = jax.jit(layer.init)(jax.random.key(0), x)["params"]
    assert not np.asarray(params["conv_offset"]["kernel"]).any()
    params = {**params, "bias": jnp.linspace(-1.0, 1.0, 6)}
    got = np.asarray(jax.jit(layer.apply)({"params": params}, x))
    regular = np_conv_same(np.asarray(x, np.float64), np.asarray(params["kernel"], np.float64), 0)
    np.testing.assert_allclose(got, 0.5 * regular + np.linspace(-1, 1, 6), rtol=1e-4, atol=1e-5)
    bound = 1 / math.sqrt(9 * 5)  # mmdetection init: U(+-1/sqrt(fan_in)), bias 0
    assert np.abs(np.asarray(params["kernel"])).max() <= bound
    assert count(params) == 3 * 3 * 5 * 6 + 6 + 3 * 3 * 5 * 27 + 27


def test_deformable_conv_with_offsets_matches_numpy_sampling():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(2, 5, 6, 3)).astype(np.float32)
    layer = ModulatedDeformConv(4)
    params = jax.device_get(jax.jit(layer.init)(jax.random.key(1), jnp.asarray(x))["params"])
    params["conv_offset"]["kernel"] = rng.normal(0, 0.6, (3, 3, 3, 27)).astype(np.float32)
    params["conv_offset"]["bias"] = rng.normal(0, 1.0, 27).astype(np.float32)
    params["bias"] = rng.normal(size=4).astype(np.float32)
    got = np.asarray(jax.jit(layer.apply)({"params": params}, jnp.asarray(x)))
    np.testing.assert_allclose(got, np_dcn(x, params), rtol=1e-4, atol=1e-4)
    raw = np_conv_same(x.astype(np.float64), params["conv_offset"]["kernel"], 0)
    assert np.abs(raw[..., :18]).max() > 2.0  # some taps sample outside the map


def test_modulated_deform_conv_gradients_reach_offsets_and_masks():
    rng = np.random.default_rng(3)
    x = jnp.asarray(rng.normal(size=(1, 4, 4, 2)).astype(np.float32))
    offsets = jnp.asarray(rng.uniform(-1.5, 1.5, (1, 4, 4, 9, 2)).astype(np.float32))
    mask = jnp.full((1, 4, 4, 9), 0.7)
    kernel = jnp.asarray(rng.normal(size=(3, 3, 2, 3)).astype(np.float32))

    def f(o, m):
        return jnp.sum(modulated_deform_conv(x, o, m, kernel) ** 2)

    f = jax.jit(f)
    go, gm = jax.jit(jax.grad(f, argnums=(0, 1)))(offsets, mask)
    assert np.isfinite(np.asarray(go)).all() and np.abs(np.asarray(go)).max() > 0
    assert np.abs(np.asarray(gm)).max() > 0
    eps = 1e-2  # finite difference on one offset (away from integer positions)
    bumped = offsets.at[0, 1, 2, 4, 0].add(eps)
    fd = (f(bumped, mask) - f(offsets.at[0, 1, 2, 4, 0].add(-eps), mask)) / (2 * eps)
    np.testing.assert_allclose(float(go[0, 1, 2, 4, 0]), float(fd), rtol=2e-2)


# ---------------------------------------------------------------------------------------------
# the U-Net


def _P(batch: int) -> np.ndarray:
    P = np.array([[720.0, 0, 600, 45], [0, 720, 150, 0.2], [0, 0, 1, 0.003]]) / np.array(
        [[4.0], [4.0], [1.0]]
    )
    return np.repeat(P[None], batch, axis=0).astype(np.float32)


def _images(batch: int, seed: int, size=IMAGE_SIZE) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(batch, *size, 3)).astype(np.float32)


def random_variables(model, seed: int):
    """Random variables of the right structure without running (and compiling) ``init``:
    fan-in-scaled kernels, BN near identity, GAC gates 0.5 so the GAC path matters."""
    template = abstract_init(model, jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), train=False)
    rng = np.random.default_rng(seed)
    flat = {}
    for path, leaf in traverse_util.flatten_dict(template).items():
        shape, name = leaf.shape, path[-1]
        if name == "kernel":
            std = np.sqrt(1.0 / np.prod(shape[:-1]))
            value = rng.normal(0, std * (0.1 if "conv_offset" in path else 1.0), shape)
        elif name in ("scale", "var"):
            value = rng.uniform(0.5, 1.5, shape)
        elif name == "alpha":
            value = np.full(shape, 0.5)
        else:
            value = rng.normal(0, 0.1, shape)
        flat[path] = jnp.asarray(value, leaf.dtype)
    return traverse_util.unflatten_dict(flat)


@pytest.fixture(scope="module")
def tiny():
    """Tiny default model (plain convs, GAC), prior_mean 1.5, and ONE jitted forward that
    also captures the raw head outputs; it must never retrace for this input shape."""
    model = DepthUNet(**TINY, prior_mean=1.5)
    variables = random_variables(model, seed=0)

    @jax.jit
    @chex.assert_max_traces(n=1)
    def predict(v, images, P):
        return model.apply(
            v,
            images,
            P,
            train=False,
            capture_intermediates=lambda mdl, _: (
                mdl.name is not None and mdl.name.startswith("out_scale_")
            ),
        )

    return model, variables, predict


def test_depth_unet_output_shapes_and_prior_mean(tiny):
    model, variables, predict = tiny
    out, state = predict(variables, jnp.asarray(_images(2, 1)), jnp.asarray(_P(2)))
    sizes = output_sizes(IMAGE_SIZE)
    assert sizes == {"scale_1": (64, 256), "scale_4": (16, 64), "scale_8": (8, 32)}
    assert output_sizes((352, 1216))["scale_8"] == (44, 152)
    assert set(out) == {"log_depth", "depth", "gac_offsets"}
    for scale, size in sizes.items():
        assert out["log_depth"][scale].shape == (2, *size)
        assert out["log_depth"][scale].dtype == jnp.float32
        # log_depth = prior_mean + the head's residual
        head = np.asarray(state["intermediates"][f"out_{scale}"]["__call__"][0])
        np.testing.assert_allclose(out["log_depth"][scale], 1.5 + head[..., 0], rtol=1e-6)
    assert out["depth"].shape == (2, *IMAGE_SIZE)
    np.testing.assert_allclose(out["depth"], np.exp(out["log_depth"]["scale_1"]), rtol=3e-6)
    assert out["gac_offsets"]["up0"].shape == (2, 4, 16)
    assert out["gac_offsets"]["up1"].shape == (2, 8, 32)
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(out))


def test_jitted_depth_unet_traces_once_per_shape(tiny):
    model, variables, predict = tiny
    first, _ = predict(variables, jnp.asarray(_images(2, 2)), jnp.asarray(_P(2)))
    second, _ = predict(variables, jnp.asarray(_images(2, 3)), jnp.asarray(_P(2) * 1.01))
    assert not np.allclose(first["depth"], second["depth"])
    assert not np.allclose(first["gac_offsets"]["up1"], second["gac_offsets"]["up1"])


def test_training_mode_updates_decoder_batch_stats(tiny):
    model, variables, _ = tiny
    out, state = jax.jit(lambda v, x, p: model.apply(v, x, p, train=True, mutable=["batch_stats"]))(
        variables, jnp.asarray(_images(2, 4)), jnp.asarray(_P(2))
    )
    old = traverse_util.flatten_dict(variables["batch_stats"], sep="/")
    new = traverse_util.flatten_dict(state["batch_stats"], sep="/")
    assert old.keys() == new.keys()
    for key in ("up0/bn1/mean", "up2/bn2/var", "backbone/bn1/mean"):
        assert not np.allclose(np.asarray(new[key]), np.asarray(old[key]))
    assert np.isfinite(np.asarray(out["depth"])).all()


@pytest.mark.parametrize("decoder_conv", ["plain", "deformable"])
def test_base_unet_has_no_gac_and_variant_structure(decoder_conv):
    images, P = jnp.zeros((1, *IMAGE_SIZE, 3)), jnp.zeros((1, 3, 4))
    model = DepthUNet(**TINY, use_gac=False, decoder_conv=decoder_conv, dtype=jnp.bfloat16)
    variables = abstract_init(model, images, P, train=False)
    flat = traverse_util.flatten_dict(variables["params"], sep="/")
    assert not any("gac" in k for k in flat)
    assert any("conv2/conv_offset" in k for k in flat) == (decoder_conv == "deformable")
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(variables))
    out = jax.eval_shape(lambda v: model.apply(v, images, P, train=False), variables)
    assert "gac_offsets" not in out and out["depth"].shape == (1, *IMAGE_SIZE)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(out))
    with pytest.raises(ValueError, match="decoder_conv"):
        abstract_init(DepthUNet(**TINY, decoder_conv="dcn"), images, P, train=False)
    with pytest.raises(ValueError, match="intrinsics_mode"):
        abstract_init(DepthUNet(**TINY, intrinsics_mode="fixed"), images, P, train=False)


# ---------------------------------------------------------------------------------------------
# parameter counts (abstract init: no memory, no compile)


def unet_params(decoder_conv: str, use_gac: bool) -> tuple[int, dict[str, int]]:
    """Decoder parameter counts from the layer list (convs with bias, BN scale + bias)."""

    def conv(i, o, k):
        return i * o * k * k + o

    stages = {"up0": (768, 256, True), "up1": (384, 64, True), "up2": (128, 64, False)}
    counts = {}
    for name, (c, out, gac) in stages.items():
        n = conv(c, c, 5) + 2 * c + conv(c, out, 3) + 2 * out
        if decoder_conv == "deformable":
            n += conv(c, 27, 3)
        if gac and use_gac:
            n += conv(c, 1, 3) + conv(c + 1, c, 1) + 1
        counts[name] = n
    for name in ("out_scale_1", "out_scale_4", "out_scale_8"):
        counts[name] = conv(64, 1, 3)
    return 21_284_672 + sum(counts.values()), counts


@pytest.mark.parametrize(
    ("decoder_conv", "use_gac", "total"),
    [
        ("deformable", True, 43_258_456),  # the reference MonoDepth
        ("plain", True, 42_947_335),  # the paper's convs
        ("plain", False, 42_197_379),  # "Base U-Net"
        ("deformable", False, 42_508_500),
    ],
)
def test_depth_unet_param_counts(decoder_conv, use_gac, total):
    model = DepthUNet(depth=34, decoder_conv=decoder_conv, use_gac=use_gac)
    variables = abstract_init(model, jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), train=False)
    params = variables["params"]
    expected_total, per_module = unet_params(decoder_conv, use_gac)
    assert count(params) == total == expected_total
    assert count(params["backbone"]) == 21_284_672  # torchvision resnet34 minus fc
    for name, n in per_module.items():
        assert count(params[name]) == n, name


def test_reference_state_dict_maps_onto_depth_unet():
    entries = parse_reference_keys("MonoDepth")
    assert len(entries) == 281
    assert sum(int(np.prod(s)) for _, s, kind in entries if kind == "param") == 43_258_456
    zero = np.zeros((), np.float32)
    sd = {key: np.broadcast_to(zero, shape) for key, shape, _ in entries}
    model = DepthUNet(depth=34, decoder_conv="deformable")
    template = abstract_init(model, jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), train=False)
    conv = naming.convert_state_dict(
        sd, naming.depth_unet_rules(), template, naming.DEPTH_UNET_IGNORED
    )
    assert conv.unused == [] and conv.missing == []
    counters = {k for k in conv.ignored if k.endswith(".num_batches_tracked")}
    assert set(conv.ignored) == counters | {"prior_mean"}
    assert len(counters) == 42  # 36 backbone + 6 decoder BatchNorms
    mapped = traverse_util.flatten_dict(conv.variables)
    assert len(mapped) == len(entries) - 43 == len(traverse_util.flatten_dict(template))
    flat = {"/".join(k): v.shape for k, v in mapped.items()}
    assert flat["params/up0/gac/extract/kernel"] == (1, 1, 769, 768)
    assert flat["params/up0/conv1/kernel"] == (5, 5, 768, 768)
    assert flat["params/up1/conv2/kernel"] == (3, 3, 384, 64)
    assert flat["params/up2/conv2/conv_offset/kernel"] == (3, 3, 128, 27)
    assert flat["params/out_scale_1/kernel"] == (3, 3, 64, 1)
    assert flat["batch_stats/up2/bn2/var"] == (64,)
    # a plain-conv model leaves exactly the DCN offset convs unused
    plain = abstract_init(
        DepthUNet(depth=34), jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), False
    )
    conv = naming.convert_state_dict(
        sd, naming.depth_unet_rules(), plain, naming.DEPTH_UNET_IGNORED
    )
    assert conv.missing == [] and len(conv.unused) == 6
    assert all(re.match(r"core\.up\d\.conv\.conv2\.0\.conv_offset\.", k) for k in conv.unused)


# ---------------------------------------------------------------------------------------------
# GAC calibration per decoder stage, on the real KITTI-depth frame


def read_p_rect_02(path) -> np.ndarray:
    for line in path.read_text().splitlines():
        if line.startswith("P_rect_02:"):
            return np.array([float(v) for v in line.split(":", 1)[1].split()]).reshape(3, 4)
    raise AssertionError(f"no P_rect_02 in {path}")


@pytest.mark.parametrize("mode", ["correct", "reference"])
def test_each_gac_stage_gets_the_intrinsics_of_its_stride(kitti_samples, mode):
    raw = kitti_samples / "depth" / "raw" / "2011_09_26"
    P = read_p_rect_02(raw / "calib_cam_to_cam.txt")
    image = read_image(raw / "2011_09_26_drive_0001_sync" / "image_02" / "data" / "0000000005.png")
    top = image.shape[0] - 352  # the depth net's crop: bottom 352 rows, left 1216 columns
    crop = np.array([[1.0, 0, 0], [0, 1, -top], [0, 0, 1]])
    P_crop = crop @ P
    image = image[top:, :1216].astype(np.float32) / 255.0
    image = (image - np.array([0.485, 0.456, 0.406])) / np.array([0.229, 0.224, 0.225])
    assert image.shape == (352, 1216, 3) and top == 23

    # 'reference' runs the reference layout (DCNv2 decoder convs) at full size as well
    decoder_conv = "plain" if mode == "correct" else "deformable"
    model = DepthUNet(depth=18, width=4, intrinsics_mode=mode, decoder_conv=decoder_conv)
    variables = random_variables(model, seed=1)

    shapes = {}  # stage -> GAC input feature shape (static, recorded while tracing)

    def run(v, x, p):
        used = {}

        def record(next_fun, args, kwargs, context):
            if isinstance(context.module, GroundAwareConv) and context.method_name == "__call__":
                feats, P_given = args[:2]  # (x, P, plane)
                stage = context.module.scope.path[-2]
                used[stage] = feature_projection(P_given, context.module.stride)
                shapes[stage] = feats.shape
            return next_fun(*args, **kwargs)

        with nn.intercept_methods(record):
            out = model.apply(v, x, p, train=False)
        return out["depth"], used

    depth, used = jax.jit(run)(
        variables,
        jnp.asarray(image[None], jnp.float32),
        jnp.asarray(P_crop[None], jnp.float32),
    )
    assert set(used) == {"up0", "up1"}  # no GAC at stride 4
    assert depth.shape == (1, 352, 1216)
    for stage, stride, shape in (("up0", 16, (22, 76)), ("up1", 8, (44, 152))):
        assert shapes[stage][1:3] == shape
        P_f = np.asarray(used[stage][0], np.float64)
        if mode == "correct":
            expected = P_crop.copy()
            expected[:2] /= stride
        else:
            expected = P_crop.copy()
            expected[:, 3] = 0.0
            expected[:2] /= 32 * stride  # 512 at stride 16, 256 at stride 8
        np.testing.assert_allclose(P_f, expected, rtol=1e-6, atol=1e-7)
        fy, cy = P_f[1, 1], P_f[1, 2]
        divisor = stride if mode == "correct" else 32 * stride
        np.testing.assert_allclose(
            [fy, cy], [721.5377 / divisor, (172.854 - 23) / divisor], rtol=1e-6
        )


def test_mean_log_depth_over_valid_pixels():
    maps = [np.array([[0.0, 2.0], [0.05, 150.0]]), np.array([[8.0, 0.0, 4.0]])]
    assert mean_log_depth(maps) == pytest.approx((math.log(2) + math.log(8) + math.log(4)) / 3)
    assert mean_log_depth(maps, max_depth=200.0) == pytest.approx(
        (math.log(2) + math.log(8) + math.log(4) + math.log(150)) / 4
    )
    with pytest.raises(ValueError, match="no valid"):
        mean_log_depth([np.zeros((3, 3))])
