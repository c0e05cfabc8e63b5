"""A small NCHW ONNX graph builder over ``onnx.helper``: the ops the GAC networks need.

Every method appends nodes (and float32 initializers) to one graph and returns the name of
its output tensor. Convolutions take Flax kernels (``(kh, kw, Cin, Cout)``, HWIO) and an
optional eval-mode BatchNorm, which is folded into the kernel and bias::

    y = BN(conv(x, W) + b) = conv(x, W * s) + (b - mean) * s + beta,  s = gamma / sqrt(var + eps)

so the exported graph has no BatchNorm node. Tensors are NCHW (ONNX's native layout), so the
graph needs no transposes between layers.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

BN_EPSILON = 1e-5  # every BatchNorm of the project (PyTorch's default)


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

    def __init__(self, name: str):
        self.name = name
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.inputs: list[onnx.ValueInfoProto] = []
        self.outputs: list[onnx.ValueInfoProto] = []
        self._count: dict[str, int] = {}

    def fresh(self, prefix: str) -> str:
        n = self._count.get(prefix, 0)
        self._count[prefix] = n + 1
        return f"{prefix}_{n}"

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
            graph, opset_imports=[helper.make_opsetid("", opset)], producer_name="gac_jax.export"
        )
        model.ir_version = min(model.ir_version, 10)  # readable by current runtimes
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
    ) -> str:
        """Flax conv params ``{'kernel', 'bias'?}`` (+ folded BN, output ``scale``, constant
        ``bias_add``) as one ONNX Conv (+ Relu). ``padding`` defaults to ``(k - 1) // 2``."""
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
        )
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
