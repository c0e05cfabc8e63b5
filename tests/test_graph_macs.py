"""MACs of an ONNX graph: a hand-built tiny graph with every counted op, counted by hand."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.deploy.graph_macs import count_macs

onnx = pytest.importorskip("onnx")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402


def weight(name, *shape):
    return numpy_helper.from_array(np.zeros(shape, np.float32), name)


def test_macs_of_a_tiny_graph_counted_by_hand():
    """x (1, 3, 10, 12) -> Conv 3x3 stride 2 pad 1 to 8 channels (5 x 6 out) -> grouped 1x1
    Conv (2 groups, 8 -> 8) -> ConvTranspose 2x2 stride 2 (8 -> 4, 10 x 12 out) -> Relu ->
    reshape (1, 480) -> Gemm (transB, 480 -> 16); and a batched MatMul (2, 5, 6) @ (6, 7)."""
    nodes = [
        helper.make_node(
            "Conv", ["x", "w1"], ["c1"], kernel_shape=[3, 3], strides=[2, 2], pads=[1, 1, 1, 1]
        ),
        helper.make_node("Conv", ["c1", "w2"], ["c2"], kernel_shape=[1, 1], group=2),
        helper.make_node(
            "ConvTranspose", ["c2", "w3"], ["c3"], kernel_shape=[2, 2], strides=[2, 2]
        ),
        helper.make_node("Relu", ["c3"], ["r"]),
        helper.make_node("Reshape", ["r", "shape"], ["flat"]),
        helper.make_node("Gemm", ["flat", "w4"], ["g"], transB=1),
        helper.make_node("MatMul", ["m", "w5"], ["mm"]),
    ]
    inits = [
        weight("w1", 8, 3, 3, 3),
        weight("w2", 8, 4, 1, 1),
        weight("w3", 8, 4, 2, 2),
        numpy_helper.from_array(np.array([1, 480], np.int64), "shape"),
        weight("w4", 16, 480),
        weight("w5", 6, 7),
    ]
    graph = helper.make_graph(
        nodes,
        "tiny",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 10, 12]),
            helper.make_tensor_value_info("m", TensorProto.FLOAT, [2, 5, 6]),
        ],
        [
            helper.make_tensor_value_info("g", TensorProto.FLOAT, None),
            helper.make_tensor_value_info("mm", TensorProto.FLOAT, None),
        ],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    macs = count_macs(model)
    conv = 8 * 5 * 6 * 3 * 9 + 8 * 5 * 6 * 4  # 3x3 stride 2; grouped 1x1 (4 inputs per output)
    transposed = 8 * 5 * 6 * 4 * 4  # every input pixel feeds 4 channels x 2x2 outputs
    assert macs == {
        "Conv": conv,
        "ConvTranspose": transposed,
        "Gemm": 16 * 480,
        "MatMul": 2 * 5 * 7 * 6,
        "total": conv + transposed + 16 * 480 + 2 * 5 * 7 * 6,
    }
