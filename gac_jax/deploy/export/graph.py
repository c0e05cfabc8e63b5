"""A small NCHW ONNX graph builder over ``onnx.helper``: the ops the GAC networks need.

Every method appends nodes (and float32 initializers) to one graph and returns the name of
its output tensor. Convolutions take Flax kernels (``(kh, kw, Cin, Cout)``, HWIO) and an
optional eval-mode BatchNorm, which is folded into the kernel and bias::

    y = BN(conv(x, W) + b) = conv(x, W * s) + (b - mean) * s + beta,  s = gamma / sqrt(var + eps)

so the exported graph has no BatchNorm node. Tensors are NCHW (ONNX's native layout), so the
graph needs no transposes between layers.
"""

from __future__ import annotations

import json

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

BN_EPSILON = 1e-5  # every BatchNorm of the project (PyTorch's default)
WINOGRAD_KEY = "gac_jax.winograd_convs"  # model metadata: {conv output: [Cin, H, W]}

# Winograd F(2, 5) (Toom-Cook, points 0, 1, -1, 2, -2, infinity): for a 6-sample input ``d``
# and a 5-tap filter ``g``, the correlation ``y[i] = sum_k g[k] d[i + k]`` (i = 0, 1) is
# ``A^T ((G g) * (B^T d))``. A^T and G from the points (G's rows divided by
# prod_{l != j} (p_j - p_l)); B^T solved from that identity (tests/test_export.py checks it).
WINOGRAD_F2_5 = (
    [[1, 1, 1, 1, 1, 0], [0, 1, -1, 2, -2, 1]],  # A^T (2, 6)
    [  # G (6, 5)
        [1 / 4, 0, 0, 0, 0],
        [-1 / 6, -1 / 6, -1 / 6, -1 / 6, -1 / 6],
        [-1 / 6, 1 / 6, -1 / 6, 1 / 6, -1 / 6],
        [1 / 24, 1 / 12, 1 / 6, 1 / 3, 2 / 3],
        [1 / 24, -1 / 12, 1 / 6, -1 / 3, 2 / 3],
        [0, 0, 0, 0, 1],
    ],
    [  # B^T (6, 6)
        [4, 0, -5, 0, 1, 0],
        [0, -4, -4, 1, 1, 0],
        [0, 4, -4, -1, 1, 0],
        [0, -2, -1, 2, 1, 0],
        [0, 2, -1, -2, 1, 0],
        [0, 4, 0, -5, 0, 1],
    ],
)


def fold_batch_norm(
    kernel: np.ndarray, bias: np.ndarray | None, bn: dict | None, epsilon: float = BN_EPSILON
) -> tuple[np.ndarray, np.ndarray]:
    """Flax HWIO kernel (+ bias, + eval-mode BatchNorm ``{scale, bias, mean, var}``) ->
    ONNX ``(W (Cout, Cin, kh, kw), b (Cout,))`` float32, computed in float64."""
    kernel = np.asarray(kernel, np.float64)
    cout = kernel.shape[-1]
    b = np.zeros(cout) if bias is None else np.asarray(bias, np.float64)
    w = kernel.transpose(3, 2, 0, 1)  # HWIO -> OIHW
    if bn is not None:
        s = np.asarray(bn["scale"], np.float64) / np.sqrt(
            np.asarray(bn["var"], np.float64) + epsilon
        )
        w = w * s[:, None, None, None]
        b = (b - np.asarray(bn["mean"], np.float64)) * s + np.asarray(bn["bias"], np.float64)
    return w.astype(np.float32), b.astype(np.float32)


class GraphBuilder:
    """Accumulates ONNX nodes, initializers, inputs and outputs; :meth:`model` builds the file."""

    def __init__(self, name: str, prefix: str = ""):
        self.name = name
        self.prefix = prefix  # of every generated name (a rewrite must not reuse a name)
        # Conv node output -> [Cin, H, W] of 5x5 convs that a float32 runtime may run as
        # Winograd F(2x2, 5x5) (gac_jax.deploy.export.winograd), stored in the model's metadata
        self.winograd_convs: dict[str, list[int]] = {}
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.inputs: list[onnx.ValueInfoProto] = []
        self.outputs: list[onnx.ValueInfoProto] = []
        self._count: dict[str, int] = {}
        self._named: set[str] = set()

    def fresh(self, prefix: str) -> str:
        n = self._count.get(prefix, 0)
        self._count[prefix] = n + 1
        return f"{self.prefix}{prefix}_{n}"

    def named(self, name: str | None) -> str | None:
        """``name`` (a layer's Flax path, e.g. ``backbone/layer1_0/conv1``) made unique, or
        None. Convolutions carry these names so that a quantizer's ignored scope (NNCF
        patterns, :mod:`gac_jax.deploy.int8`) can select layers by the model's own names."""
        if name is None:
            return None
        name = f"{self.prefix}{name}"
        if name in self._named:
            return self.fresh(name)
        self._named.add(name)
        return name

    # ------------------------------------------------------------------ graph interface
    def add_input(self, name: str, shape: list) -> str:
        self.inputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, shape))
        return name

    def add_output(self, tensor: str, name: str, shape: list) -> None:
        self.op("Identity", [tensor], name=name)
        self.outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, shape))

    def const(self, value, prefix: str = "const", dtype=np.float32) -> str:
        name = self.fresh(prefix)
        self.initializers.append(numpy_helper.from_array(np.asarray(value, dtype), name))
        return name

    def op(self, op_type: str, inputs: list[str], name: str | None = None, **attrs) -> str:
        out = name or self.fresh(op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=out, **attrs))
        return out

    def model(self, opset: int, doc: str = "") -> onnx.ModelProto:
        graph = helper.make_graph(
            self.nodes, self.name, self.inputs, self.outputs, self.initializers, doc_string=doc
        )
        model = helper.make_model(
            graph,
            opset_imports=[helper.make_opsetid("", opset)],
            producer_name="gac_jax.deploy.export",
        )
        model.ir_version = min(model.ir_version, 10)  # readable by current runtimes
        if self.winograd_convs:
            helper.set_model_props(model, {WINOGRAD_KEY: json.dumps(self.winograd_convs)})
        return model

    # ------------------------------------------------------------------ layers
    def conv(
        self,
        x: str,
        conv: dict,
        bn: dict | None = None,
        *,
        stride: int = 1,
        padding: int | None = None,
        relu: bool = False,
        scale: float | None = None,
        bias_add: float = 0.0,
        winograd_size: tuple[int, int] | None = None,
    ) -> str:
        """Flax conv params ``{'kernel', 'bias'?, 'name'?}`` (+ folded BN, output ``scale``,
        constant ``bias_add``) as one ONNX Conv (+ Relu) named ``name`` (:meth:`named`).
        ``padding`` defaults to ``(k - 1) // 2``. ``winograd_size``: the (H, W) of ``x``,
        marking a 5x5 stride-1 conv as a candidate for :meth:`conv5x5_winograd` at load time
        (float32 runtimes only)."""
        w, b = fold_batch_norm(conv["kernel"], conv.get("bias"), bn)
        if scale is not None:
            w, b = w * np.float32(scale), b * np.float32(scale)
        b = b + np.float32(bias_add)
        kh, kw = w.shape[2:]
        ph = (kh - 1) // 2 if padding is None else padding
        pw = (kw - 1) // 2 if padding is None else padding
        y = self.op(
            "Conv",
            [x, self.const(w, "W"), self.const(b, "B")],
            kernel_shape=[kh, kw],
            strides=[stride, stride],
            pads=[ph, pw, ph, pw],
            name=self.named(conv.get("name")),
        )
        if winograd_size is not None and (kh, kw, ph, pw, stride) == (5, 5, 2, 2, 1):
            self.winograd_convs[y] = [int(w.shape[1]), *map(int, winograd_size)]
        return self.op("Relu", [y]) if relu else y

    def conv5x5_winograd(
        self,
        x: str,
        channels: int,
        size: tuple[int, int],
        conv: dict,
        bn: dict | None = None,
        relu: bool = True,
    ) -> str:
        """A 5x5 stride-1 conv with zero padding 2 (+ folded BN, + ReLU) as Winograd F(2x2, 5x5):
        36 multiplications per 2x2 output tile instead of 100, i.e. 2.8x fewer FLOPs in the
        batched matrix product that replaces the convolution (the decoder's 5x5 convs are half
        of the depth U-Net's time in ONNX Runtime and OpenVINO).

        With the 6x6 input tile ``d`` at rows/cols ``2i-2 .. 2i+3`` and ``Y`` the 2x2 output:
        ``Y = A^T [sum_c (G w_oc G^T) * (B^T d_c B)] A`` (``WINOGRAD_F2_5``). In ONNX: pad,
        the input transform as a 1->36 stride-2 conv over every (batch, channel) plane, a
        (B, 36, C, T) x (36, Cout, C) MatMul over the T = th * tw tiles, the output transform
        as a (4, 36) MatMul, and a transpose back to NCHW. ``x`` is (B, channels, *size).
        Agrees with the direct conv to float32 rounding (the transforms' coefficients are
        small: interpolation points 0, +-1, +-2, infinity).
        """
        w, b = fold_batch_norm(conv["kernel"], conv.get("bias"), bn)
        cout, cin, kh, kw = w.shape
        if (kh, kw) != (5, 5) or cin != channels:
            raise ValueError(f"expected a 5x5 kernel with {channels} inputs, got {w.shape}")
        AT, G, BT = (np.asarray(m, np.float64) for m in WINOGRAD_F2_5)
        H, W = size
        th, tw = -(-H // 2), -(-W // 2)
        # U[a*6 + b, o, c] = (G w[o, c] G^T)[a, b]
        U = np.einsum("ak,ockl,bl->aboc", G, w.astype(np.float64), G).reshape(36, cout, cin)
        k_in = np.einsum("au,bv->abuv", BT, BT).reshape(36, 1, 6, 6)
        k_out = np.einsum("pa,qb->pqab", AT, AT).reshape(4, 36)
        pads = [0, 0, 2, 2, 0, 0, 2 + 2 * th - H, 2 + 2 * tw - W]
        d = self.op("Pad", [x, self.const(pads, "pads", np.int64)], mode="constant")
        d = self.reshape(d, [-1, 1, 2 * th + 4, 2 * tw + 4])  # (B*C, 1, Hp, Wp)
        v = self.op(
            "Conv", [d, self.const(k_in, "Wt")], kernel_shape=[6, 6], strides=[2, 2]
        )  # (B*C, 36, th, tw)
        v = self.op("Transpose", [self.reshape(v, [-1, cin, 36, th * tw])], perm=[0, 2, 1, 3])
        m = self.op("MatMul", [self.const(U, "U"), v])  # (B, 36, Cout, T)
        y = self.op("MatMul", [self.const(k_out, "At"), self.reshape(m, [-1, 36, cout * th * tw])])
        y = self.reshape(y, [-1, 2, 2, cout, th, tw])
        y = self.op("Transpose", [y], perm=[0, 3, 4, 1, 5, 2])
        y = self.reshape(y, [-1, cout, 2 * th, 2 * tw])
        if (2 * th, 2 * tw) != (H, W):
            y = self.op(
                "Slice",
                [
                    y,
                    self.const([0, 0], "st", np.int64),
                    self.const([H, W], "en", np.int64),
                    self.const([2, 3], "ax", np.int64),
                ],
            )
        y = self.op("Add", [y, self.const(b.reshape(1, -1, 1, 1), "B")])
        return self.op("Relu", [y]) if relu else y

    def max_pool(self, x: str) -> str:
        """3x3 stride-2 max-pool with 1 pixel of padding that never wins (the ResNet stem)."""
        return self.op("MaxPool", [x], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1])

    def gather_rows(self, x: str, index: np.ndarray, axis: int) -> str:
        return self.op("Gather", [x, self.const(index, "idx", np.int64)], axis=axis)

    def slice(self, x: str, start: int, end: int, axis: int) -> str:
        return self.op(
            "Slice",
            [
                x,
                self.const([start], "st", np.int64),
                self.const([end], "en", np.int64),
                self.const([axis], "ax", np.int64),
            ],
        )

    def reshape(self, x: str, shape: list[int]) -> str:
        return self.op("Reshape", [x, self.const(shape, "shape", np.int64)])
