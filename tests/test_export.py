"""ONNX export (gac_jax.deploy.export): exported float32 networks vs the jitted Flax models.

Tiny models with perturbed weights (non-trivial BatchNorm statistics, GAC ``alpha`` != 0, non-zero
output convs) so every branch contributes; outputs compared at 1e-4 relative (max |diff| / max
|reference|) at batch 1 and 2 under ONNX Runtime. Skipped without the deploy extra.
"""

from __future__ import annotations

import functools
from pathlib import Path

import jax
import numpy as np
import pytest

onnx = pytest.importorskip("onnx", reason="deploy extra (onnx) not installed")
ort = pytest.importorskip("onnxruntime", reason="deploy extra (onnxruntime) not installed")

from gac_jax.builders import depth as depth_builders  # noqa: E402
from gac_jax.builders import detect3d as det_builders  # noqa: E402
from gac_jax.config import apply_overrides, load_config  # noqa: E402
from gac_jax.deploy.export.networks import ExportError, depth_graph, detector_graph  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
RTOL = 1e-4


def perturb(variables: dict, seed: int = 0) -> dict:
    """Random but well-conditioned weights: noisy kernels/biases/BN, positive variances."""
    rng = np.random.default_rng(seed)

    def f(path, x):
        x = np.asarray(x, np.float32)
        name = jax.tree_util.keystr(path)
        if "'var'" in name:
            return (np.abs(x) + rng.uniform(0.5, 1.5, x.shape)).astype(np.float32)
        if "alpha" in name:
            return np.full_like(x, 0.7)
        # kernels He-scaled, so activations neither vanish nor explode
        scale = (2.0 / max(np.prod(x.shape[:-1]), 1)) ** 0.5 if "kernel" in name else 0.2
        return (x + rng.normal(0.0, scale, x.shape)).astype(np.float32)

    return jax.tree_util.tree_map_with_path(f, variables)


def projections(batch: int, height: int, width: int, scale: float = 1.0) -> np.ndarray:
    """(B,3,4) KITTI-like projections, different per image; ``scale`` != 1 also moves the
    principal point down by a third of the image."""
    P = np.array(
        [[700.0, 0, width / 2, 45.0], [0, 700.0, height / 4, -0.3], [0, 0, 1, 0.005]], np.float64
    )
    out = []
    for b in range(batch):
        Pb = P.copy()
        Pb[:2] *= scale * (1 + 0.15 * b)
        Pb[1, 2] += 3.0 * b + (height / 3 if scale != 1.0 else 0.0)
        out.append(Pb)
    return np.stack(out).astype(np.float32)


def planes(batch: int) -> np.ndarray:
    """(B,4) tilted ground planes, different per image: pitched down 20 degrees (the authors'
    issue #69), then also rolled and lower (``(a, b, c, d)``, unit upward normal)."""
    out = []
    for b in range(batch):
        pitch, roll = np.radians(20.0 - 8.0 * b), np.radians(5.0 * b)
        n = np.array([np.sin(roll), -np.cos(roll) * np.cos(pitch), -np.cos(roll) * np.sin(pitch)])
        out.append(np.append(n, 1.65 - 0.3 * b))
    return np.stack(out).astype(np.float32)


def session(model) -> ort.InferenceSession:
    return ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])


def run(sess, images, P2, plane) -> dict:
    names = [o.name for o in sess.get_outputs()]
    feed = {"images": images, "P2": P2, "plane": plane}
    return dict(zip(names, sess.run(None, feed), strict=True))


def rel_error(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-12))


def random_variables(model, config, init) -> dict:
    """Perturbed weights in the shapes of ``init`` (traced abstractly: nothing is compiled)."""
    shapes = jax.eval_shape(lambda: init(model, config, 0))
    zeros = jax.tree.map(lambda s: np.zeros(s.shape, np.float32), shapes)
    return perturb(zeros)


@functools.cache
def case(kind: str, variant: str):
    """``(model, variables, image size, ONNX session, jitted apply)`` of a variant (cached)."""
    spec, *overrides = (DETECTOR_VARIANTS if kind == "detect3d" else DEPTH_VARIANTS)[variant]
    config = load_config(str(REPO / "configs" / spec))
    apply_overrides(config, list(overrides))
    d = config.data
    if kind == "detect3d":
        layout = det_builders.anchor_layout(config)
        model = det_builders.build_model(config, layout.anchors_per_cell)
        variables = random_variables(model, config, det_builders.init_variables)
        size, graph = (d.height, d.width), detector_graph
    else:
        model = depth_builders.build_model(config, 2.3)
        variables = random_variables(model, config, depth_builders.init_variables)
        size, graph = (d.height, d.eval_width), depth_graph
    sess = session(graph(model, variables, size, 17))
    apply = jax.jit(lambda v, x, P, plane: model.apply(v, x, P, train=False, plane=plane))
    return model, variables, size, sess, apply


def inputs(size: tuple[int, int], scale: float = 1.0):
    """Two images, their projections and tilted ground planes."""
    images = np.random.default_rng(0).normal(size=(2, *size, 3)).astype(np.float32)
    return images, projections(2, *size, scale=scale), planes(2)


DETECTOR_VARIANTS = {
    "gac": ("detect3d_default.py:tiny",),
    "conv": ("detect3d_default.py:tiny,conv",),
    "disparity_conv": ("detect3d_default.py:tiny", "model.regression_block=disparity_conv"),
    "bottleneck_reference_v1": (
        "detect3d_default.py:tiny",
        "model.backbone_depth=50",
        "model.gac.offset_formula=reference_v1",
    ),
}
DEPTH_VARIANTS = {
    "gac": ("depth_default.py:tiny",),
    "base": ("depth_default.py:tiny,base",),
    "reference_intrinsics": ("depth_default.py:tiny", "model.intrinsics_mode=reference"),
    "ground_plane_prior": ("depth_default.py:tiny", "model.output_prior=ground_plane"),
}


@pytest.mark.parametrize("variant", list(DETECTOR_VARIANTS))
def test_detector_export_matches_jit(variant):
    """Batch 2 against the jitted model, and batch 1 against its first image (the Flax model
    in eval mode treats images independently), so one compile serves both."""
    model, variables, size, sess, apply = case("detect3d", variant)
    images, P2, plane = inputs(size)
    ref = apply(variables, images, P2, plane)
    for batch in (2, 1):
        out = run(sess, images[:batch], P2[:batch], plane[:batch])
        assert set(out) == {"cls_logits", "sign_logits", "reg"}
        for key, value in out.items():
            assert value.shape == ref[key][:batch].shape, key
            assert rel_error(value, ref[key][:batch]) < RTOL, (variant, batch, key)


@pytest.mark.parametrize("variant", list(DEPTH_VARIANTS))
def test_depth_export_matches_jit(variant):
    model, variables, size, sess, apply = case("depth", variant)
    images, P2, plane = inputs(size)
    ref = apply(variables, images, P2, plane)
    for batch in (2, 1):
        out = run(sess, images[:batch], P2[:batch], plane[:batch])
        assert out["log_depth"].shape == (batch, *size)
        assert rel_error(out["log_depth"], ref["log_depth"]["scale_1"][:batch]) < RTOL
        assert rel_error(out["depth"], ref["depth"][:batch]) < RTOL


@pytest.mark.parametrize("live", ["P2", "plane"])
@pytest.mark.parametrize("kind", ["detect3d", "depth"])
def test_p2_and_plane_are_live_inputs(kind, live):
    """Another calibration, or the level plane instead of the tilted ones, changes the exported
    outputs exactly as it changes the Flax ones."""
    model, variables, size, sess, apply = case(kind, "gac")
    images, Pa, plane_a = inputs(size)
    Pb, plane_b = Pa, plane_a
    if live == "P2":
        _, Pb, _ = inputs(size, scale=1.4)
    else:
        plane_b = np.tile(np.float32([0.0, -1.0, 0.0, model.camera_height]), (2, 1))
    key = "reg" if kind == "detect3d" else "log_depth"

    def pick(out):
        return out[key] if kind == "detect3d" or key not in out else out[key]["scale_1"]

    ref_change = np.asarray(pick(apply(variables, images, Pb, plane_b))) - np.asarray(
        pick(apply(variables, images, Pa, plane_a))
    )
    out_change = run(sess, images, Pb, plane_b)[key] - run(sess, images, Pa, plane_a)[key]
    # the input matters (far above float32 noise, ~1e-6 here) ...
    assert np.abs(ref_change).max() > 3e-4
    assert rel_error(out_change, ref_change) < 1e-2  # ... and the same in both


def test_deformable_decoder_is_refused():
    config = load_config(str(REPO / "configs" / "depth_default.py:tiny"))
    apply_overrides(config, ["model.decoder_conv=deformable"])
    model = depth_builders.build_model(config, 2.3)
    variables = random_variables(model, config, depth_builders.init_variables)
    with pytest.raises(ExportError, match="deformable.*cannot be exported"):
        depth_graph(model, variables, (config.data.height, config.data.eval_width), 17)


def test_deformable_detector_head_is_refused():
    """Table 3's deformable regression block has no ONNX form here: one clear refusal."""
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny,deformable"))
    layout = det_builders.anchor_layout(config)
    model = det_builders.build_model(config, layout.anchors_per_cell)
    variables = random_variables(model, config, det_builders.init_variables)
    with pytest.raises(ExportError, match="'deformable'.*cannot be exported.*--runtime jax"):
        detector_graph(model, variables, (config.data.height, config.data.width), 17)


def _resize_align_corners_np(x: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """float64 bilinear resize, align_corners=True, of NCHW ``x`` (independent reference)."""
    for axis, n_out in ((2, size[0]), (3, size[1])):
        n_in = x.shape[axis]
        src = np.arange(n_out) * ((n_in - 1) / max(n_out - 1, 1))
        i0 = np.minimum(np.floor(src).astype(int), n_in - 1)
        i1 = np.minimum(i0 + 1, n_in - 1)
        shape = [1, 1, 1, 1]
        shape[axis] = n_out
        w1 = (src - i0).reshape(shape)
        x = np.take(x, i0, axis=axis) * (1 - w1) + np.take(x, i1, axis=axis) * w1
    return x


@pytest.mark.parametrize("small,size", [((5, 7), (17, 26)), ((4, 4), (9, 13))])
def test_resized_single_channel_conv_matches_resize_then_conv(small, size):
    """The depth head's emitted form (9 taps on the small map, resize, shifted sum) equals a
    zero-padded 3x3 conv C->1 of the resized map (float64 numpy), at batch 2."""
    from gac_jax.deploy.export.graph import GraphBuilder
    from gac_jax.deploy.export.networks import _resized_single_channel_conv

    rng = np.random.default_rng(1)
    C = 6
    kernel = rng.normal(size=(3, 3, C, 1)).astype(np.float32)
    bias = rng.normal(size=(1,)).astype(np.float32)
    g = GraphBuilder("head")
    x = g.add_input("x", ["batch", C, *small])
    y = _resized_single_channel_conv(g, x, size, {"kernel": kernel, "bias": bias}, 2.3)
    g.add_output(y, "y", ["batch", 1, *size])
    xs = rng.normal(size=(2, C, *small)).astype(np.float32)
    out = session(g.model(17)).run(None, {"x": xs})[0]

    up = np.pad(
        _resize_align_corners_np(xs.astype(np.float64), size), ((0, 0), (0, 0), (1, 1), (1, 1))
    )
    H, W = size
    ref = np.full((2, 1, H, W), float(bias[0]) + 2.3)
    for dy in range(3):
        for dx in range(3):
            patch = up[:, :, dy : dy + H, dx : dx + W]
            ref[:, 0] += np.einsum("bchw,c->bhw", patch, kernel[dy, dx, :, 0].astype(np.float64))
    assert out.shape == ref.shape
    assert rel_error(out, ref) < 1e-5


def test_winograd_f2_5_is_the_5_tap_correlation():
    """A^T ((G g) * (B^T d)) == [sum_k g[k] d[i + k]]_i for random g, d (float64)."""
    from gac_jax.deploy.export.graph import WINOGRAD_F2_5

    AT, G, BT = (np.asarray(m, np.float64) for m in WINOGRAD_F2_5)
    rng = np.random.default_rng(3)
    for _ in range(5):
        g, d = rng.normal(size=5), rng.normal(size=6)
        ref = [np.dot(g, d[i : i + 5]) for i in range(2)]
        np.testing.assert_allclose(AT @ ((G @ g) * (BT @ d)), ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("size", [(7, 9), (6, 10)])
def test_winograd_conv_matches_direct_conv(size):
    """conv5x5_winograd (odd and even maps, batch 2) vs a float64 zero-padded 5x5 conv."""
    from gac_jax.deploy.export.graph import GraphBuilder

    rng = np.random.default_rng(2)
    C, O = 5, 4
    kernel = rng.normal(size=(5, 5, C, O)).astype(np.float32)
    bias = rng.normal(size=(O,)).astype(np.float32)
    g = GraphBuilder("wino")
    x = g.add_input("x", ["batch", C, *size])
    y = g.conv5x5_winograd(x, C, size, {"kernel": kernel, "bias": bias}, relu=False)
    g.add_output(y, "y", ["batch", O, *size])
    xs = rng.normal(size=(2, C, *size)).astype(np.float32)
    out = session(g.model(17)).run(None, {"x": xs})[0]
    H, W = size
    padded = np.pad(xs.astype(np.float64), ((0, 0), (0, 0), (2, 2), (2, 2)))
    ref = np.broadcast_to(bias.astype(np.float64)[None, :, None, None], (2, O, H, W)).copy()
    for dy in range(5):
        for dx in range(5):
            patch = padded[:, :, dy : dy + H, dx : dx + W]
            ref += np.einsum("bchw,co->bohw", patch, kernel[dy, dx].astype(np.float64))
    assert rel_error(out, ref) < 1e-5


def test_winograd_rewrite_of_the_depth_net_matches_jit():
    """Every marked decoder conv rewritten (no size limits), batch 2 and 1, vs the jitted model;
    the file's own graph keeps direct convs and the marks."""
    from gac_jax.deploy.export.winograd import apply_winograd, marked_convs

    model, variables, size, _, apply = case("depth", "gac")
    proto = depth_graph(model, variables, size, 17)
    assert len(marked_convs(proto)) == 3  # conv1 of every decoder stage
    assert apply_winograd(proto, min_channels=10**6) == 0
    assert apply_winograd(proto, min_channels=0, min_pixels=0) == 3
    assert not any(
        n.op_type == "Conv" and n.output[0] in marked_convs(proto) for n in proto.graph.node
    )
    onnx.checker.check_model(proto)
    sess = session(proto)
    images, P2, plane = inputs(size)
    ref = apply(variables, images, P2, plane)
    for batch in (2, 1):
        out = run(sess, images[:batch], P2[:batch], plane[:batch])
        assert rel_error(out["log_depth"], ref["log_depth"]["scale_1"][:batch]) < RTOL
