"""Tests of the ResNet backbones, the detection head / detector and the torch-key mapping.

Oracles: torchvision's published parameter totals, key/shape lists generated here from the
torchvision architecture definition, a float64 numpy forward of torchvision's ResNet that
reads torch-layout (OIHW) weights, and the reference state-dict listing in
``../shared/spec/reference_state_dict.md`` (skipped when absent)."""

from __future__ import annotations

import re

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util
from numpy.lib.stride_tricks import sliding_window_view

from gac_jax.models import naming
from gac_jax.models.detection_head import REGRESSION_COMPONENTS
from gac_jax.models.detector import Detector, feature_map_size
from gac_jax.models.resnet import ResNet, layer_channels, layer_output_size
from tests.conftest import SHARED

REFERENCE_STATE_DICT = SHARED / "spec" / "reference_state_dict.md"  # ../shared (optional)


def count(tree) -> int:
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(tree))


def abstract_init(model, *args, **kwargs):
    return jax.eval_shape(lambda: model.init(jax.random.key(0), *args, **kwargs))


# ---------------------------------------------------------------------------------------------
# torchvision ResNet, independently: key -> shape, and a numpy forward over torch weights

BLOCKS = {18: ("basic", [2, 2, 2, 2]), 34: ("basic", [3, 4, 6, 3])}
BLOCKS |= {50: ("bottleneck", [3, 4, 6, 3]), 101: ("bottleneck", [3, 4, 23, 3])}


def _bn(prefix: str, n: int) -> dict[str, tuple[int, ...]]:
    return {f"{prefix}.{leaf}": (n,) for leaf in ("weight", "bias", "running_mean", "running_var")}


def torchvision_shapes(depth: int, width: int = 64, num_stages: int = 4, fc: bool = False):
    """torchvision resnet{depth} state-dict key -> shape (num_batches_tracked left out)."""
    kind, blocks = BLOCKS[depth]
    exp = 4 if kind == "bottleneck" else 1
    shapes = {"conv1.weight": (width, 3, 7, 7), **_bn("bn1", width)}
    inplanes = width
    for s in range(num_stages):
        planes = width * 2**s
        for b in range(blocks[s]):
            p = f"layer{s + 1}.{b}"
            if kind == "basic":
                convs = [(planes, inplanes, 3), (planes, planes, 3)]
            else:
                convs = [(planes, inplanes, 1), (planes, planes, 3), (planes * exp, planes, 1)]
            for i, (o, c, k) in enumerate(convs, start=1):
                shapes[f"{p}.conv{i}.weight"] = (o, c, k, k)
                shapes |= _bn(f"{p}.bn{i}", o)
            if b == 0 and (s > 0 or inplanes != planes * exp):
                shapes[f"{p}.downsample.0.weight"] = (planes * exp, inplanes, 1, 1)
                shapes |= _bn(f"{p}.downsample.1", planes * exp)
            inplanes = planes * exp
    if fc:
        shapes |= {"fc.weight": (1000, inplanes), "fc.bias": (1000,)}
    return shapes


def random_state_dict(shapes, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    sd = {}
    for key, shape in shapes.items():
        if key.endswith("running_var"):
            sd[key] = rng.uniform(0.5, 1.5, shape)
        elif key.endswith("weight") and len(shape) == 4:
            sd[key] = rng.normal(0, np.sqrt(2.0 / np.prod(shape[1:])), shape)
        else:
            sd[key] = rng.normal(0, 0.2, shape) + (1.0 if key.endswith(".weight") else 0.0)
    return {k: v.astype(np.float32) for k, v in sd.items()}


def np_conv(x, w, stride, pad):
    """NCHW conv, torch weight (O,I,k,k), symmetric zero padding."""
    k = w.shape[-1]
    xp = np.pad(x, ((0, 0), (0, 0), (pad, pad), (pad, pad)))
    win = sliding_window_view(xp, (k, k), axis=(2, 3))[:, :, ::stride, ::stride]
    return np.einsum("bchwij,ocij->bohw", win, w.astype(np.float64))


def np_bn(x, sd, prefix, train, stats):
    if train:
        mean, var = x.mean(axis=(0, 2, 3)), x.var(axis=(0, 2, 3))
        stats[prefix] = (mean, var)
    else:
        mean, var = sd[f"{prefix}.running_mean"], sd[f"{prefix}.running_var"]
    y = (x - mean[:, None, None]) / np.sqrt(var[:, None, None] + 1e-5)
    return y * sd[f"{prefix}.weight"][:, None, None] + sd[f"{prefix}.bias"][:, None, None]


def np_resnet(sd, images_nhwc, depth, num_stages, train=False):
    """torchvision ResNet forward (float64); returns ({'layerL': NHWC}, {bn prefix: stats})."""
    kind, blocks = BLOCKS[depth]
    stats: dict = {}
    x = images_nhwc.transpose(0, 3, 1, 2).astype(np.float64)
    x = np.maximum(np_bn(np_conv(x, sd["conv1.weight"], 2, 3), sd, "bn1", train, stats), 0)
    xp = np.pad(x, ((0, 0), (0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    x = sliding_window_view(xp, (3, 3), axis=(2, 3))[:, :, ::2, ::2].max(axis=(-1, -2))
    outs = {}
    for s in range(num_stages):
        for b in range(blocks[s]):
            p = f"layer{s + 1}.{b}"
            stride = 2 if (s > 0 and b == 0) else 1
            n = 2 if kind == "basic" else 3
            y = x
            for i in range(1, n + 1):
                w = sd[f"{p}.conv{i}.weight"]
                conv_stride = stride if (i == 1 and kind == "basic") or (i == 2 and n == 3) else 1
                y = np_bn(
                    np_conv(y, w, conv_stride, w.shape[-1] // 2), sd, f"{p}.bn{i}", train, stats
                )
                if i < n:
                    y = np.maximum(y, 0)
            if f"{p}.downsample.0.weight" in sd:
                x = np_conv(x, sd[f"{p}.downsample.0.weight"], stride, 0)
                x = np_bn(x, sd, f"{p}.downsample.1", train, stats)
            x = np.maximum(x + y, 0)
        outs[f"layer{s + 1}"] = x.transpose(0, 2, 3, 1)
    return outs, stats


# ---------------------------------------------------------------------------------------------
# ResNet


TORCHVISION_TOTALS = {18: 11_689_512, 34: 21_797_672, 50: 25_557_032, 101: 44_549_160}


@pytest.mark.parametrize("depth", [18, 34, 50, 101])
def test_resnet_param_counts_match_torchvision(depth):
    images = jnp.zeros((1, 64, 64, 3))
    variables = abstract_init(ResNet(depth=depth, num_stages=4), images, train=False)
    fc = layer_channels(depth, 4) * 1000 + 1000
    assert count(variables["params"]) + fc == TORCHVISION_TOTALS[depth]
    # the same total from the architecture definition (BN: 2 params; running stats are buffers)
    shapes = torchvision_shapes(depth, fc=True)
    params = [s for k, s in shapes.items() if "running" not in k]
    assert sum(int(np.prod(s)) for s in params) == TORCHVISION_TOTALS[depth]
    # batch_stats: one mean and one var per BN channel
    bn_channels = sum(s[0] for k, s in shapes.items() if k.endswith("running_mean"))
    assert count(variables["batch_stats"]) == 2 * bn_channels


def test_resnet101_through_layer3_matches_reference_backbone():
    variables = abstract_init(
        ResNet(depth=101, num_stages=3), jnp.zeros((1, 64, 64, 3)), train=False
    )
    assert count(variables["params"]) == 27_535_424  # reference core.backbone


@pytest.mark.parametrize(("depth", "num_stages"), [(18, 4), (50, 2)])
def test_resnet_with_converted_torch_weights_matches_numpy_forward(depth, num_stages):
    width, size = 4, (40, 45)  # even and odd sizes: PyTorch padding and rounding
    sd = random_state_dict(torchvision_shapes(depth, width, num_stages), seed=depth)
    model = ResNet(depth=depth, num_stages=num_stages, width=width)
    images = np.random.default_rng(1).normal(size=(2, *size, 3)).astype(np.float32)
    template = abstract_init(model, jnp.asarray(images), train=False)
    conv = naming.convert_state_dict(sd, naming.resnet_rules(), template)
    assert conv.complete, (conv.unused, conv.missing)

    out = model.apply(conv.variables, jnp.asarray(images), train=False)
    expected, _ = np_resnet(sd, images, depth, num_stages)
    assert set(out) == set(expected) == {f"layer{i + 1}" for i in range(num_stages)}
    for name, ref in expected.items():
        layer = int(name[-1])
        assert out[name].shape == (2, *(layer_output_size(n, layer) for n in size), ref.shape[-1])
        assert ref.shape[-1] == layer_channels(depth, layer, width)
        np.testing.assert_allclose(np.asarray(out[name]), ref, rtol=2e-4, atol=2e-4)

    if depth == 18:  # training mode: batch statistics and PyTorch-momentum running averages
        out, updates = model.apply(
            conv.variables, jnp.asarray(images), train=True, mutable=["batch_stats"]
        )
        expected, stats = np_resnet(sd, images, depth, num_stages, train=True)
        np.testing.assert_allclose(np.asarray(out["layer4"]), expected["layer4"], atol=5e-4)
        new = traverse_util.flatten_dict(updates["batch_stats"], sep="/")
        mean, var = stats["layer2.0.downsample.1"]
        np.testing.assert_allclose(
            np.asarray(new["layer2_0/downsample_1/mean"]),
            0.9 * sd["layer2.0.downsample.1.running_mean"] + 0.1 * mean,
            rtol=1e-4,
            atol=1e-5,
        )
        np.testing.assert_allclose(
            np.asarray(new["layer2_0/downsample_1/var"]),
            0.9 * sd["layer2.0.downsample.1.running_var"] + 0.1 * var,
            rtol=1e-4,
        )


def test_resnet_rejects_bad_options():
    with pytest.raises(ValueError, match="depth"):
        abstract_init(ResNet(depth=42), jnp.zeros((1, 32, 32, 3)), train=False)
    with pytest.raises(ValueError, match="return_layers"):
        model = ResNet(depth=18, num_stages=2, return_layers=("layer3",))
        abstract_init(model, jnp.zeros((1, 32, 32, 3)), train=False)


def test_torchvision_checkpoint_reports_fc_and_layer4_unused_for_3_stages():
    sd = {k: np.zeros(s, np.float32) for k, s in torchvision_shapes(18, 4, fc=True).items()}
    template = abstract_init(
        ResNet(depth=18, num_stages=3, width=4), jnp.zeros((1, 32, 32, 3)), train=False
    )
    conv = naming.convert_state_dict(sd, naming.resnet_rules(), template)
    assert not conv.missing
    unused = {u.split(" ")[0] for u in conv.unused}
    assert unused == {k for k in sd if k.startswith(("layer4.", "fc."))}


# ---------------------------------------------------------------------------------------------
# Detector (tiny: ResNet-18 of width 8, 64x256 input -> 4x16 features)

TINY = dict(depth=18, width=8, num_classes=2, num_anchors=4, cls_features=16, reg_features=32)
IMAGE_SIZE = (64, 256)


def _P2(batch: int) -> np.ndarray:
    P = np.array([[720.0, 0, 600, 45], [0, 720, 170, 0.2], [0, 0, 1, 0.003]]) / np.array(
        [[4.0], [4.0], [1.0]]
    )
    return np.repeat(P[None], batch, axis=0).astype(np.float32)


def _images(batch: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(batch, *IMAGE_SIZE, 3)).astype(np.float32)


@pytest.fixture(scope="module")
def tiny():
    model = Detector(**TINY)
    variables = jax.jit(lambda k, x, p: model.init(k, x, p, train=False))(
        jax.random.key(0), jnp.asarray(_images(2, 0)), jnp.asarray(_P2(2))
    )
    return model, variables


def test_detector_output_shapes_and_zero_init(tiny):
    model, variables = tiny
    out = jax.jit(lambda v, x, p: model.apply(v, x, p, train=False))(
        variables, jnp.asarray(_images(2, 1)), jnp.asarray(_P2(2))
    )
    Hf, Wf = feature_map_size(IMAGE_SIZE)
    assert (Hf, Wf) == (4, 16) and feature_map_size((288, 1280)) == (18, 80)
    N = Hf * Wf * TINY["num_anchors"]
    assert out["cls_logits"].shape == (2, N, TINY["num_classes"])
    assert out["sign_logits"].shape == (2, N)
    assert out["reg"].shape == (2, N, len(REGRESSION_COMPONENTS)) == (2, N, 12)
    assert out["gac_offsets"].shape == (2, Hf, Wf)
    assert all(out[k].dtype == jnp.float32 for k in out)
    np.testing.assert_array_equal(np.asarray(out["reg"]), 0.0)
    np.testing.assert_array_equal(np.asarray(jax.nn.sigmoid(out["cls_logits"])), 0.5)
    np.testing.assert_array_equal(np.asarray(jax.nn.sigmoid(out["sign_logits"])), 0.5)
    assert float(variables["params"]["head"]["gac"]["alpha"][0]) == 0.0


def test_detector_flat_anchor_order_matches_conv_channels(tiny):
    model, variables = tiny
    K, A = TINY["num_classes"], TINY["num_anchors"]
    flat = traverse_util.flatten_dict(jax.device_get(variables), sep="/")
    rng = np.random.default_rng(2)
    for name in ("params/head/cls_out/kernel", "params/head/reg_out/kernel"):
        flat[name] = rng.normal(0, 0.1, flat[name].shape).astype(np.float32)
    variables = traverse_util.unflatten_dict(flat, sep="/")
    apply = jax.jit(
        lambda v, x, p: model.apply(
            v,
            x,
            p,
            train=False,
            capture_intermediates=lambda mdl, _: mdl.name in ("cls_out", "reg_out"),
        )
    )
    out, state = apply(variables, jnp.asarray(_images(1, 3)), jnp.asarray(_P2(1)))
    raw_cls = np.asarray(state["intermediates"]["head"]["cls_out"]["__call__"][0])
    raw_reg = np.asarray(state["intermediates"]["head"]["reg_out"]["__call__"][0])
    Hf, Wf = raw_cls.shape[1:3]
    cls, sign, reg = (np.asarray(out[k]) for k in ("cls_logits", "sign_logits", "reg"))
    for row, col, a in [(0, 0, 0), (1, 5, 3), (3, 15, 2), (2, 7, 1)]:
        n = (row * Wf + col) * A + a  # flat anchor index
        np.testing.assert_array_equal(
            cls[0, n], raw_cls[0, row, col, a * (K + 1) : a * (K + 1) + K]
        )
        assert sign[0, n] == raw_cls[0, row, col, a * (K + 1) + K]  # last component: sign bit
        np.testing.assert_array_equal(reg[0, n], raw_reg[0, row, col, a * 12 : (a + 1) * 12])
    assert np.abs(reg).max() > 0


def test_detector_training_mode_updates_stats_and_drops_whole_channels(tiny):
    model, variables = tiny
    apply = jax.jit(
        lambda v, x, p: model.apply(
            v,
            x,
            p,
            train=True,
            mutable=["batch_stats", "intermediates"],
            rngs={"dropout": jax.random.key(5)},
            capture_intermediates=lambda mdl, _: mdl.name in ("cls_conv1", "Dropout_0"),
        )
    )
    out, state = apply(variables, jnp.asarray(_images(2, 4)), jnp.asarray(_P2(2)))
    old = traverse_util.flatten_dict(variables["batch_stats"], sep="/")
    new = traverse_util.flatten_dict(state["batch_stats"], sep="/")
    assert old.keys() == new.keys()
    assert any("head/reg_bn1" in k for k in new)
    assert not np.allclose(np.asarray(new["head/reg_bn1/mean"]), old["head/reg_bn1/mean"])
    conv = np.asarray(state["intermediates"]["head"]["cls_conv1"]["__call__"][0])
    dropped = np.asarray(state["intermediates"]["head"]["Dropout_0"]["__call__"][0])
    kept = np.all(np.isclose(dropped, conv / 0.7, rtol=1e-5, atol=1e-6), axis=(1, 2))  # (B,C)
    zero = np.all(dropped == 0.0, axis=(1, 2))
    assert np.all(kept ^ zero)  # Dropout2d: each (image, channel) is kept or dropped entirely
    assert 0.1 < zero.mean() < 0.6


def test_jitted_detector_traces_once_per_shape(tiny):
    model, variables = tiny

    @jax.jit
    @chex.assert_max_traces(n=1)
    def predict(v, images, P2):
        return model.apply(v, images, P2, train=False)

    P2 = jnp.asarray(_P2(2))
    first = predict(variables, jnp.asarray(_images(2, 6)), P2)
    second = predict(variables, jnp.asarray(_images(2, 7)), P2 * 1.01)
    assert not np.allclose(np.asarray(first["gac_offsets"]), np.asarray(second["gac_offsets"]))


# ---------------------------------------------------------------------------------------------
# parameter counts of the full-size variants (abstract: no memory, no compile)


def head_params(C, K, A, cls, reg, block):
    """Head parameter count from the layer list (3x3 convs with bias, BN scale + bias)."""

    def conv(i, o, k=3):
        return i * o * k * k + o

    n = conv(C, cls) + conv(cls, cls) + conv(cls, A * (K + 1))
    n += conv(C, reg) + conv(reg, reg) + 2 * 2 * reg + conv(reg, A * 12)
    block_params = {
        "gac": conv(C, 1) + conv(C + 1, C, 1) + 1,
        "conv": conv(C, C),
        "disparity_conv": conv(C + 1, C),
    }
    return n + block_params[block]


@pytest.mark.parametrize(
    ("block", "K", "A", "total"),
    [
        ("gac", 1, 32, 58_388_994),  # the reference GroundAwareYolo3D (Car only)
        ("conv", 1, 32, 66_767_360),
        ("disparity_conv", 1, 32, 66_776_576),
        ("gac", 3, 48, 60_748_610),  # Car/Pedestrian/Cyclist with ratios [0.5, 1, 2]
    ],
)
def test_detector_param_counts(block, K, A, total):
    model = Detector(depth=101, num_classes=K, num_anchors=A, regression_block=block)
    variables = abstract_init(model, jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), train=False)
    params = variables["params"]
    assert count(params) == total
    assert count(params["backbone"]) == 27_535_424
    assert count(params["head"]) == head_params(1024, K, A, 512, 1024, block)


def test_detector_output_structure_per_variant_and_dtype():
    images, P2 = jnp.zeros((2, *IMAGE_SIZE, 3)), jnp.zeros((2, 3, 4))
    for block in ("conv", "disparity_conv"):
        model = Detector(**TINY, regression_block=block, dtype=jnp.bfloat16)
        variables = abstract_init(model, images, P2, train=False)
        out = jax.eval_shape(lambda v, m=model: m.apply(v, images, P2, train=False), variables)
        assert set(out) == {"cls_logits", "sign_logits", "reg"}
        assert out["reg"].shape == (2, 4 * 16 * 4, 12) and out["reg"].dtype == jnp.float32
        assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(variables))
    with pytest.raises(ValueError, match="regression_block"):
        abstract_init(Detector(**TINY, regression_block="dcn"), images, P2, train=False)


# ---------------------------------------------------------------------------------------------
# the reference state dict maps 1:1 onto the Flax detector


def parse_reference_keys(section: str) -> list[tuple[str, tuple[int, ...], str]]:
    if not REFERENCE_STATE_DICT.is_file():
        pytest.skip(f"reference state-dict listing not found at {REFERENCE_STATE_DICT}")
    text = REFERENCE_STATE_DICT.read_text()
    body = text.split(f"### {section}: every state_dict entry", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(
        r"^\|\s*\d+\s*\|\s*`([^`]+)`\s*\|\s*\[([\d,\s]*)\]\s*\|\s*\w+\s*\|\s*(\w+)", body, re.M
    )
    return [
        (k, tuple(int(s) for s in shape.split(",") if s.strip()), kind) for k, shape, kind in rows
    ]


def test_reference_state_dict_maps_onto_detector():
    entries = parse_reference_keys("GroundAwareYolo3D")
    assert len(entries) == 594
    assert sum(int(np.prod(s)) for _, s, kind in entries if kind == "param") == 58_388_994
    zero = np.zeros((), np.float32)
    sd = {key: np.broadcast_to(zero, shape) for key, shape, _ in entries}  # no memory
    model = Detector(depth=101, num_classes=1, num_anchors=32)
    template = abstract_init(model, jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4)), train=False)
    conv = naming.convert_state_dict(sd, naming.detector_rules(), template, naming.DETECTOR_IGNORED)
    assert conv.unused == [] and conv.missing == []
    loss_constants = {
        "bbox_head.balance_weights",
        "bbox_head.loss_cls.balance_weights",
        "bbox_head.regression_weight",
    }
    counters = {k for k in conv.ignored if k.endswith(".num_batches_tracked")}
    assert set(conv.ignored) == counters | loss_constants
    assert len(counters) == 96  # one per BatchNorm
    mapped = traverse_util.flatten_dict(conv.variables)
    assert len(mapped) == len(entries) - 99 == len(traverse_util.flatten_dict(template))
    flat = {"/".join(k): v.shape for k, v in mapped.items()}
    assert flat["params/head/gac/extract/kernel"] == (1, 1, 1025, 1024)
    assert flat["params/backbone/layer3_22/conv3/kernel"] == (1, 1, 256, 1024)
    assert flat["batch_stats/head/reg_bn2/var"] == (1024,)


def test_conversion_rejects_duplicate_targets_and_bad_shapes():
    rules = (naming.Rule(r"a|b", "x", "conv"),)
    with pytest.raises(ValueError, match="both map to params/x/bias"):
        naming.convert_state_dict({"a.bias": np.zeros(2), "b.bias": np.zeros(2)}, rules)
    template = {"params": {"x": {"bias": np.zeros(3, np.float32)}}}
    with pytest.raises(ValueError, match=r"a\.bias.*\(2,\).*\(3,\)"):
        naming.convert_state_dict({"a.bias": np.zeros(2)}, rules, template)
    conv = naming.convert_state_dict(
        {"a.gamma": np.zeros(3), "c.bias": np.zeros(3)}, rules, template
    )
    assert len(conv.unused) == 2 and conv.missing == ["params/x/bias"] and not conv.complete
    base = {"params": {"x": {"bias": np.ones(3, np.float32), "kernel": np.ones((1, 1, 1, 3))}}}
    ok = naming.convert_state_dict({"a.bias": np.full(3, 7.0)}, rules, template)
    merged = ok.merged_into(base)
    np.testing.assert_array_equal(merged["params"]["x"]["bias"], 7.0)
    np.testing.assert_array_equal(merged["params"]["x"]["kernel"], 1.0)
