"""The GAC detector and depth U-Net as ONNX graphs, emitted from Flax variables + the module.

Nothing here traces JAX: each layer of :mod:`gac_jax.models` is re-stated with the ONNX ops of
:class:`~gac_jax.deploy.export.graph.GraphBuilder` in NCHW, reading the weights by their Flax names
and the hyper-parameters from the (configured) Flax module, so the export does not depend on
how JAX lowers the model. Inference mode only: BatchNorm uses its running statistics (folded
into the convolutions) and dropout is the identity.

Graph inputs and outputs (batch ``B`` is a dynamic dimension):

* detector: ``images`` (B,H,W,3) float32 (normalised RGB, as the Flax model takes them),
  ``P2`` (B,3,4), ``plane`` (B,4) -> ``cls_logits`` (B,N,K), ``sign_logits`` (B,N),
  ``reg`` (B,N,12);
* depth U-Net: ``images`` (B,H,W,3), ``P2`` (B,3,4), ``plane`` (B,4) -> ``log_depth``
  (B,H,W) (the ``scale_1`` head) and ``depth`` (B,H,W) metres.

The projection ``P2`` and the ground ``plane`` (``(a, b, c, d)``, unit upward normal, camera
frame; ``(0, -1, 0, camera_height)`` for a level camera) stay live inputs: the GAC's sampling
offsets and disparity prior are computed from them inside the graph by the very formulas of
:mod:`gac_jax.models.ground_plane` (evaluated on symbolic tensors, :class:`_Sym`). A model
without GAC or disparity prior ignores ``plane``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import onnx

from gac_jax.deploy.export.graph import GraphBuilder
from gac_jax.models.depth_unet import DECODER_STAGES, REFERENCE_GAC_STRIDE, DepthUNet
from gac_jax.models.detection_head import NUM_REGRESSION
from gac_jax.models.detector import FEATURE_LAYER, FEATURE_STRIDE, Detector
from gac_jax.models.ground_aware_conv import OFFSET_FORMULAS
from gac_jax.models.ground_plane import ground_disparity, ground_offset, plane_terms
from gac_jax.models.resnet import BOTTLENECK_EXPANSION, RESNET_SPECS, layer_output_size


class ExportError(ValueError):
    """The model (or a variant of it) cannot be exported."""


class _Weights:
    """Read access to ``{'params', 'batch_stats'}`` by Flax module path."""

    def __init__(self, variables: dict):
        self.params = variables["params"]
        self.stats = variables.get("batch_stats", {})

    @staticmethod
    def _walk(tree, path: tuple[str, ...]):
        for key in path:
            tree = tree[key]
        return tree

    def conv(self, *path: str) -> dict:
        """``{'kernel', 'bias'?}`` of the conv at ``path`` and ``'name'``: the path joined
        with ``/`` (the ONNX node's name)."""
        arrays = {k: np.asarray(v) for k, v in self._walk(self.params, path).items()}
        return {**arrays, "name": "/".join(path)}

    def bn(self, *path: str) -> dict:
        p, s = self._walk(self.params, path), self._walk(self.stats, path)
        return {"scale": p["scale"], "bias": p["bias"], "mean": s["mean"], "var": s["var"]}

    def value(self, *path: str) -> np.ndarray:
        return np.asarray(self._walk(self.params, path))


# ----------------------------------------------------------------------------- ResNet


def _resnet(
    g: GraphBuilder, w: _Weights, x: str, depth: int, width: int, stages: int, root: str
) -> dict[str, str]:
    """torchvision ResNet trunk (:class:`gac_jax.models.resnet.ResNet`) -> stage outputs."""
    kind, blocks = RESNET_SPECS[depth]
    x = g.conv(x, w.conv(root, "conv1"), w.bn(root, "bn1"), stride=2, relu=True)
    x = g.max_pool(x)
    outputs = {}
    channels = width
    for stage in range(stages):
        features = width * 2**stage
        for b in range(blocks[stage]):
            stride = 2 if (stage > 0 and b == 0) else 1
            p = f"layer{stage + 1}_{b}"
            if kind == "bottleneck":
                out_features = features * BOTTLENECK_EXPANSION
                y = g.conv(x, w.conv(root, p, "conv1"), w.bn(root, p, "bn1"), relu=True)
                y = g.conv(y, w.conv(root, p, "conv2"), w.bn(root, p, "bn2"), stride=stride)
                y = g.op("Relu", [y])
                y = g.conv(y, w.conv(root, p, "conv3"), w.bn(root, p, "bn3"))
            else:
                out_features = features
                y = g.conv(x, w.conv(root, p, "conv1"), w.bn(root, p, "bn1"), stride=stride)
                y = g.op("Relu", [y])
                y = g.conv(y, w.conv(root, p, "conv2"), w.bn(root, p, "bn2"))
            shortcut = x
            if stride != 1 or channels != out_features:
                shortcut = g.conv(
                    x,
                    w.conv(root, p, "downsample_0"),
                    w.bn(root, p, "downsample_1"),
                    stride=stride,
                    padding=0,
                )
            x = g.op("Relu", [g.op("Add", [y, shortcut])])
            channels = out_features
        outputs[f"layer{stage + 1}"] = x
    return outputs


# ----------------------------------------------------------------------------- GAC


def _binary(op: str, swap: bool = False):
    """A :class:`_Sym` arithmetic method emitting ``op`` (``swap``: the reflected one)."""

    def method(self, x):
        return self._op(op, x, self) if swap else self._op(op, self, x)

    return method


class _Sym:
    """An ONNX tensor with Python arithmetic, so :mod:`gac_jax.models.ground_plane`'s formulas
    (written with ``+ - * /`` only) emit the graph ops of the same computation."""

    def __init__(self, g: GraphBuilder, name: str):
        self.g, self.name = g, name

    def _arg(self, x) -> str:
        return x.name if isinstance(x, _Sym) else self.g.const(np.float32(x))

    def _op(self, op: str, *args) -> _Sym:
        return _Sym(self.g, self.g.op(op, [self._arg(a) for a in args]))

    __add__, __radd__ = _binary("Add"), _binary("Add", swap=True)
    __sub__, __rsub__ = _binary("Sub"), _binary("Sub", swap=True)
    __mul__, __rmul__ = _binary("Mul"), _binary("Mul", swap=True)
    __truediv__, __rtruediv__ = _binary("Div"), _binary("Div", swap=True)

    def __neg__(self):
        return self._op("Neg", self)


_SYM_OPS = SimpleNamespace(
    relu=lambda x: x._op("Relu", x),
    abs=lambda x: x._op("Abs", x),
    maximum=lambda x, y: x._op("Max", x, y),
)


def _frame_entries(g: GraphBuilder, x: str, count: int) -> list[_Sym]:
    """The ``count`` per-frame values of a (B, ...) input, each (B,1,1)."""
    flat = g.reshape(x, [-1, count])
    return [_Sym(g, g.gather_rows(flat, np.array([[i]]), axis=1)) for i in range(count)]


def _feature_projection(
    entries: list[_Sym], divisors: tuple[float, ...], keep_translation: bool
) -> list[list]:
    """``P_f[i][j]`` of a feature map: rows 0-1 times ``1/d`` for each divisor in turn (as
    :func:`~gac_jax.models.ground_aware_conv.feature_projection` does), the translation column
    0 if not ``keep_translation`` (the reference depth intrinsics)."""
    P = [[entries[4 * i + j] for j in range(4)] for i in range(3)]
    if not keep_translation:
        for row in P:
            row[3] = 0.0
    for i in (0, 1):
        for j in range(4):
            for d in divisors:
                P[i][j] = P[i][j] * np.float32(1.0 / d)
    return P


def _plane_maps(
    g: GraphBuilder, P: list[list], plane: list[_Sym], size: tuple[int, int], geometry: dict
) -> tuple[str, str, str]:
    """(B,1,H,W) ground offset rows, cols and disparity prior of
    :mod:`gac_jax.models.ground_plane`."""
    H, W = size
    terms = plane_terms(P, plane)
    u = _Sym(g, g.const(np.arange(W, dtype=np.float32).reshape(1, 1, W), "cols"))
    v = _Sym(g, g.const(np.arange(H, dtype=np.float32).reshape(1, H, 1), "rows"))
    rows, cols = ground_offset(
        terms, u, v, geometry["object_height"], geometry["offset_formula"], _SYM_OPS
    )
    disparity = ground_disparity(terms, u, v, geometry["baseline"], _SYM_OPS)
    return tuple(g.reshape(t.name, [-1, 1, H, W]) for t in (rows, cols, disparity))


def _ground_log_depth(
    g: GraphBuilder, entries: list[_Sym], plane: list[_Sym], size: tuple[int, int], model
) -> str:
    """(B,H,W) :func:`~gac_jax.models.depth_unet.ground_log_depth` of the input pixels."""
    H, W = size
    P = _feature_projection(entries, (1.0,), True)
    u = _Sym(g, g.const(np.arange(W, dtype=np.float32).reshape(1, 1, W), "cols"))
    v = _Sym(g, g.const(np.arange(H, dtype=np.float32).reshape(1, H, 1), "rows"))
    disparity = ground_disparity(plane_terms(P, plane), u, v, 1.0, _SYM_OPS)
    inverse = disparity / _SYM_OPS.abs(P[1][1])
    floor = g.const(np.float32(1.0 / model.prior_max_depth))
    log = g.op("Log", [g.op("Max", [inverse.name, floor])])
    return g.reshape(g.op("Neg", [log]), [-1, H, W])


def _taps(g: GraphBuilder, x: str, n: int) -> tuple[str, str, str]:
    """Border-clamped linear taps of coordinates ``x`` on ``[0, n-1]``: ``(i0, i1, frac)``
    (int64, int64, float), as :func:`~gac_jax.models.ground_aware_conv.bilinear_gather`."""
    x = g.op("Clip", [x, g.const(np.float32(0.0)), g.const(np.float32(n - 1.0))])
    x0 = g.op(
        "Clip",
        [g.op("Floor", [x]), g.const(np.float32(0.0)), g.const(np.float32(max(n - 2, 0)))],
    )
    i0 = g.op("Cast", [x0], to=onnx.TensorProto.INT64)
    i1 = g.op(
        "Min", [g.op("Add", [i0, g.const(1, "one", np.int64)]), g.const(n - 1, "nm1", np.int64)]
    )
    return i0, i1, g.op("Sub", [x, x0])


def _bilinear_gather(g: GraphBuilder, feats: str, rows: str, cols: str, size) -> str:
    """:func:`~gac_jax.models.ground_aware_conv.bilinear_gather` on NCHW ``feats`` with
    (B,1,H,W) ``rows`` / ``cols``: four GatherElements on the flattened H*W axis."""
    H, W = size
    r0, r1, wr = _taps(g, rows, H)
    c0, c1, wc = _taps(g, cols, W)
    flat = g.reshape(feats, [0, 0, H * W])
    shape = g.op("Shape", [flat])

    def at(r, c):
        index = g.op("Add", [g.op("Mul", [r, g.const(W, "w", np.int64)]), c])
        index = g.op("Expand", [g.reshape(index, [0, 1, H * W]), shape])
        return g.reshape(g.op("GatherElements", [flat, index], axis=2), [0, 0, H, W])

    def lerp(a, b, t):
        one_minus = g.op("Sub", [g.const(np.float32(1.0)), t])
        return g.op("Add", [g.op("Mul", [one_minus, a]), g.op("Mul", [t, b])])

    return lerp(lerp(at(r0, c0), at(r1, c0), wr), lerp(at(r0, c1), at(r1, c1), wr), wc)


def _ground_aware_conv(
    g: GraphBuilder,
    w: _Weights,
    path: tuple[str, ...],
    x: str,
    size: tuple[int, int],
    P: list[list],
    plane: list[_Sym],
    geometry: dict,
) -> str:
    """:class:`~gac_jax.models.ground_aware_conv.GroundAwareConv` on NCHW ``x`` (B,C,H,W)."""
    if geometry["offset_formula"] not in OFFSET_FORMULAS:
        raise ExportError(f"offset_formula {geometry['offset_formula']!r} is not exportable")
    H, W = size
    base, base_cols, disp_map = _plane_maps(g, P, plane, size, geometry)  # (B,1,H,W) each
    # the learned residual d = offset_scale * tanh(offset_conv(x))
    d = g.op("Tanh", [g.conv(x, w.conv(*path, "offset_conv"))])  # (B,1,H,W)
    d = g.op("Mul", [d, g.const(np.float32(geometry["offset_scale"]))])
    offset = g.op("Add", [g.op("Mul", [base, g.const(np.float32(1.0 / (H / 2.0)))]), d])
    offset = g.op("Mul", [offset, g.const(np.float32((H - 1) / 2.0))])
    rows = g.op("Add", [g.const(np.arange(H, dtype=np.float32).reshape(1, 1, H, 1)), offset])
    offset_cols = g.op("Mul", [base_cols, g.const(np.float32(1.0 / (W / 2.0)))])
    offset_cols = g.op("Mul", [offset_cols, g.const(np.float32((W - 1) / 2.0))])
    cols = g.op("Add", [g.const(np.arange(W, dtype=np.float32).reshape(1, 1, 1, W)), offset_cols])
    # bilinear interpolation of [disp ‖ x] with border clamping
    feats = g.op("Concat", [disp_map, x], axis=1)
    sampled = _bilinear_gather(g, feats, rows, cols, size)
    alpha = float(w.value(*path, "alpha")[0])
    extracted = g.conv(sampled, w.conv(*path, "extract"), scale=alpha)  # alpha folded in
    return g.op("Relu", [g.op("Add", [x, extracted])])


def _geometry(module, offset_scale: float = 0.1) -> dict:
    return {
        "baseline": module.baseline,
        "camera_height": module.camera_height,
        "object_height": module.object_height,
        "offset_formula": module.offset_formula,
        "offset_scale": offset_scale,
    }


# ----------------------------------------------------------------------------- detector


def detector_graph(
    model: Detector, variables: dict, image_size: tuple[int, int], opset: int
) -> onnx.ModelProto:
    """ONNX graph of a :class:`~gac_jax.models.detector.Detector` (see the module docstring)."""
    H, W = image_size
    Hf, Wf = layer_output_size(H, FEATURE_LAYER), layer_output_size(W, FEATURE_LAYER)
    A, K = model.num_anchors, model.num_classes
    N = Hf * Wf * A
    g, w = GraphBuilder("gac_detector"), _Weights(variables)
    images = g.add_input("images", ["batch", H, W, 3])
    P2 = g.add_input("P2", ["batch", 3, 4])
    plane = _frame_entries(g, g.add_input("plane", ["batch", 4]), 4)
    x = g.op("Transpose", [images], perm=[0, 3, 1, 2])
    x = _resnet(g, w, x, model.depth, model.width, FEATURE_LAYER, "backbone")["layer3"]

    c = x
    for i in (1, 2):
        c = g.conv(c, w.conv("head", f"cls_conv{i}"), relu=True)
    c = g.conv(c, w.conv("head", "cls_out"))
    c = g.reshape(g.op("Transpose", [c], perm=[0, 2, 3, 1]), [-1, N, K + 1])
    g.add_output(g.slice(c, 0, K, axis=2), "cls_logits", ["batch", N, K])
    sign = g.op("Gather", [c, g.const(np.int64(K), "k", np.int64)], axis=2)
    g.add_output(sign, "sign_logits", ["batch", N])

    block = model.regression_block
    geometry = _geometry(model, model.offset_scale)
    if block in ("gac", "disparity_conv"):
        P = _feature_projection(_frame_entries(g, P2, 12), (FEATURE_STRIDE,), True)
    if block == "gac":
        r = _ground_aware_conv(g, w, ("head", "gac"), x, (Hf, Wf), P, plane, geometry)
    elif block == "conv":
        r = g.conv(x, w.conv("head", "plain_conv"), relu=True)
    elif block == "disparity_conv":
        _, _, disp = _plane_maps(g, P, plane, (Hf, Wf), geometry)
        r = g.conv(g.op("Concat", [disp, x], axis=1), w.conv("head", "disparity_conv"), relu=True)
    else:
        raise ExportError(
            f"regression_block={block!r} (e.g. the Table 3 'deformable' row) cannot be exported: "
            "only the gac, conv and disparity_conv blocks are; run this model with --runtime jax"
        )
    for i in (1, 2):
        r = g.conv(r, w.conv("head", f"reg_conv{i}"), w.bn("head", f"reg_bn{i}"), relu=True)
    r = g.conv(r, w.conv("head", "reg_out"))
    r = g.reshape(g.op("Transpose", [r], perm=[0, 2, 3, 1]), [-1, N, NUM_REGRESSION])
    g.add_output(r, "reg", ["batch", N, NUM_REGRESSION])
    return g.model(opset, "GAC monocular 3D detector (gac_jax)")


# ----------------------------------------------------------------------------- depth U-Net


def _pad_or_crop(g: GraphBuilder, x: str, have: tuple[int, int], want: tuple[int, int]) -> str:
    """:func:`~gac_jax.models.depth_unet.pad_or_crop_to` on NCHW: zero-pad / crop H and W."""
    begins, ends = [], []
    for axis, (n, m) in enumerate(zip(have, want, strict=True), start=2):
        diff = m - n
        lo, hi = diff // 2, diff - diff // 2
        if lo < 0 or hi < 0:
            x = g.slice(x, max(-lo, 0), n - max(-hi, 0), axis)
        begins.append(max(lo, 0))
        ends.append(max(hi, 0))
    if any(begins) or any(ends):
        pads = g.const([0, 0, *begins, 0, 0, *ends], "pads", np.int64)
        x = g.op("Pad", [x, pads], mode="constant")
    return x


def _resize(g: GraphBuilder, x: str, size: tuple[int, int]) -> str:
    """Bilinear resize with ``align_corners=True`` to ``size`` (batch and channels kept)."""
    lead = g.slice(g.op("Shape", [x]), 0, 2, axis=0)
    sizes = g.op("Concat", [lead, g.const(list(size), "hw", np.int64)], axis=0)
    return g.op(
        "Resize",
        [x, "", "", sizes],
        mode="linear",
        coordinate_transformation_mode="align_corners",
    )


def _resized_single_channel_conv(
    g: GraphBuilder, x: str, size: tuple[int, int], conv: dict, bias_add: float
) -> str:
    """``Conv3x3(C->1, zero padding 1)(_resize(x, size)) + bias_add`` -> (B,1,*size), computed
    in the cheaper order: the 9 taps first, as a 1x1 conv C->9 on the small map, then the
    resize of those 9 channels and a shifted sum of them.

    Exact up to float32 rounding: a 1x1 conv mixes channels pixel by pixel and the bilinear
    resize mixes pixels channel by channel (weights summing to 1), so they commute; tap
    ``(dy, dx)`` of the 3x3 conv then reads its resized channel at ``(v + dy - 1, u + dx - 1)``,
    0 outside (the conv's zero padding). A 3x3 conv with one output channel on a full-size
    C-channel map is mostly overhead in ONNX Runtime and OpenVINO (the resize writes C full-size
    channels, ORT pads the output channel to its 16-channel blocks): 177 -> 24 ms (ORT) and
    110 -> 32 ms (OpenVINO) for C=64, 88x304 -> 352x1216 on a 2-core EPYC.
    """
    kernel = np.asarray(conv["kernel"], np.float32)  # (3, 3, C, 1) HWIO
    if kernel.shape[:2] != (3, 3) or kernel.shape[3] != 1:
        raise ExportError(f"expected a 3x3 conv with one output channel, got {kernel.shape}")
    taps = kernel[..., 0].reshape(9, -1).T[None, None]  # (1, 1, C, 9): tap k = 3 * dy + dx
    taps_conv = (
        {"kernel": taps, "name": f"{conv['name']}/taps"} if "name" in conv else {"kernel": taps}
    )
    t = _resize(g, g.conv(x, taps_conv), size)  # (B, 9, H, W)
    H, W = size
    t = g.op("Pad", [t, g.const([0, 0, 1, 1, 0, 0, 1, 1], "pads", np.int64)], mode="constant")
    axes = g.const([1, 2, 3], "ax", np.int64)
    parts = [
        g.op(
            "Slice",
            [
                t,
                g.const([3 * dy + dx, dy, dx], "st", np.int64),
                g.const([3 * dy + dx + 1, dy + H, dx + W], "en", np.int64),
                axes,
            ],
        )
        for dy in range(3)
        for dx in range(3)
    ]
    bias = np.asarray(conv.get("bias", np.zeros(1)), np.float32) + np.float32(bias_add)
    return g.op("Add", [g.op("Sum", parts), g.const(bias.reshape(1, 1, 1, 1), "B")])


def depth_graph(
    model: DepthUNet, variables: dict, image_size: tuple[int, int], opset: int
) -> onnx.ModelProto:
    """ONNX graph of a :class:`~gac_jax.models.depth_unet.DepthUNet` (inference outputs)."""
    if model.decoder_conv != "plain":
        raise ExportError(
            f"decoder_conv={model.decoder_conv!r} (DCNv2, e.g. configs/depth_kitti.py:reference) "
            "cannot be exported: only the paper's plain decoder convolutions are; run this "
            "model with --runtime jax"
        )
    H, W = image_size
    g, w = GraphBuilder("gac_depth_unet"), _Weights(variables)
    images = g.add_input("images", ["batch", H, W, 3])
    P2 = g.add_input("P2", ["batch", 3, 4])
    plane = _frame_entries(g, g.add_input("plane", ["batch", 4]), 4)
    x = g.op("Transpose", [images], perm=[0, 3, 1, 2])
    skips = _resnet(g, w, x, model.depth, model.width, 4, "backbone")
    sizes = {f"layer{L}": (layer_output_size(H, L), layer_output_size(W, L)) for L in range(1, 5)}
    entries = _frame_entries(g, P2, 12) if model.use_gac else None
    x, have = skips["layer4"], sizes["layer4"]
    for name, skip, stride, gac in DECODER_STAGES:
        want = sizes[skip]
        up = _resize(g, x, (2 * have[0], 2 * have[1]))
        up = _pad_or_crop(g, up, (2 * have[0], 2 * have[1]), want)
        x = g.op("Concat", [skips[skip], up], axis=1)
        if model.use_gac and gac:
            if model.intrinsics_mode == "correct":
                P = _feature_projection(entries, (stride,), True)
            else:
                P = _feature_projection(entries, (2.0 * stride, REFERENCE_GAC_STRIDE), False)
            x = _ground_aware_conv(g, w, (name, "gac"), x, want, P, plane, _geometry(model))
        x = g.conv(x, w.conv(name, "conv1"), w.bn(name, "bn1"), relu=True, winograd_size=want)
        x = g.conv(x, w.conv(name, "conv2"), w.bn(name, "bn2"), relu=True)
        have = want
    ground = model.output_prior == "ground_plane"
    log_depth = _resized_single_channel_conv(
        g, x, (H, W), w.conv("out_scale_1"), 0.0 if ground else float(model.prior_mean)
    )
    log_depth = g.reshape(log_depth, [-1, H, W])
    if ground:  # the road's log depth at every pixel (DepthUNet's 'ground_plane' prior)
        prior = _ground_log_depth(g, _frame_entries(g, P2, 12), plane, (H, W), model)
        log_depth = g.op("Add", [log_depth, prior])
    g.add_output(log_depth, "log_depth", ["batch", H, W])
    g.add_output(g.op("Exp", [log_depth]), "depth", ["batch", H, W])
    return g.model(opset, "GAC ground-aware depth U-Net (gac_jax)")
