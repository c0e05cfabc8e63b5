"""Multiply-accumulates of an exported network, counted from its ONNX graph.

:func:`count_macs` adds up the MACs of the ``Conv``, ``ConvTranspose``, ``Gemm`` and
``MatMul`` nodes (the work a CPU's dot-product units do; element-wise ops, pooling and
normalisation are not counted), with every tensor's shape from ONNX shape inference:

* ``Conv``: ``N * C_out * prod(output spatial) * (C_in / group) * prod(kernel)``;
* ``ConvTranspose``: ``N * C_in * prod(input spatial) * (C_out / group) * prod(kernel)``;
* ``Gemm``: ``M * N * K``; ``MatMul``: ``prod(batch) * M * N * K`` (numpy broadcasting).

Used by ``benchmarks/bench_stream.py`` to set a network's achieved MAC/s against the CPU's
peak.
"""

from __future__ import annotations

import copy
import math
import os
from collections import defaultdict

COUNTED = ("Conv", "ConvTranspose", "Gemm", "MatMul")


def _shapes(model, batch: int) -> dict[str, tuple[int, ...]]:
    """Static shapes of every value of ``model`` after shape inference, the graph inputs'
    symbolic dimensions set to ``batch`` (values without a static shape: absent)."""
    import onnx

    model = copy.deepcopy(model)
    for value in model.graph.input:
        for d in value.type.tensor_type.shape.dim:
            if not d.HasField("dim_value"):
                d.dim_value = batch
    inferred = onnx.shape_inference.infer_shapes(model, data_prop=True)
    graph = inferred.graph
    shapes: dict[str, tuple[int, ...]] = {}
    for value in (*graph.input, *graph.value_info, *graph.output):
        dims = value.type.tensor_type.shape.dim
        if dims and all(d.HasField("dim_value") for d in dims):
            shapes[value.name] = tuple(int(d.dim_value) for d in dims)
    for init in graph.initializer:
        shapes[init.name] = tuple(int(d) for d in init.dims)
    for node in graph.node:  # weights held by Constant nodes
        if node.op_type == "Constant" and (value := _attribute(node, "value", None)) is not None:
            shapes[node.output[0]] = tuple(int(d) for d in value.dims)
    return shapes


def _attribute(node, name: str, default):
    import onnx

    for a in node.attribute:
        if a.name == name:
            return onnx.helper.get_attribute_value(a)
    return default


def node_macs(node, shapes: dict[str, tuple[int, ...]]) -> int:
    """MACs of one node (0 for a node type not counted).

    Raises:
      ValueError: a counted node whose input or output shape is not static, naming it.
    """
    if node.op_type not in COUNTED:
        return 0
    needed = [*node.input[:2], node.output[0]]
    missing = [n for n in needed if n not in shapes]
    if missing:
        raise ValueError(f"{node.op_type} node {node.name!r}: no static shape for {missing}")
    a, b, y = (shapes[n] for n in needed)  # b[1] is already per group
    if node.op_type == "Conv":  # weight (C_out, C_in/group, k...)
        return y[0] * y[1] * math.prod(y[2:]) * b[1] * math.prod(b[2:])
    if node.op_type == "ConvTranspose":  # weight (C_in, C_out/group, k...)
        return a[0] * a[1] * math.prod(a[2:]) * b[1] * math.prod(b[2:])
    if node.op_type == "Gemm":
        k = a[0] if _attribute(node, "transA", 0) else a[1]
        return y[0] * y[1] * k
    # MatMul: y (..., M, N), a (..., M, K); 1-D operands are promoted as numpy does
    k = a[-1]
    return math.prod(y) * k if len(y) else k


def count_macs(model, batch: int = 1) -> dict[str, int]:
    """MACs per counted op type of an ONNX model (a ``ModelProto`` or a file path) for one
    call with symbolic input dimensions set to ``batch``, and ``'total'``."""
    import onnx

    if isinstance(model, str | os.PathLike):
        model = onnx.load(os.fspath(model))
    shapes = _shapes(model, batch)
    out: dict[str, int] = defaultdict(int)
    for node in model.graph.node:
        macs = node_macs(node, shapes)
        if macs:
            out[node.op_type] += macs
    out["total"] = sum(out.values())
    return dict(out)
