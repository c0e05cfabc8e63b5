"""Load-time rewrite of the marked 5x5 convolutions of an exported model into Winograd form.

The exporter marks the 5x5 stride-1 convolutions it emits (the depth U-Net's decoder
``conv1``: about half of that network's time) in the model's metadata
(:data:`~gac_jax.deploy.export.graph.WINOGRAD_KEY`: ``{conv output: [Cin, H, W]}``); ``model.onnx``
itself keeps the direct convolutions. For float32 runs, :func:`apply_winograd` replaces each
marked conv with at least ``min_channels`` input channels and ``min_pixels`` pixels by
:meth:`~gac_jax.deploy.export.graph.GraphBuilder.conv5x5_winograd` (2.8x fewer multiplications in
a batched MatMul; equal to the direct conv to float32 rounding). Not for bf16: rounding the
transformed tiles to bfloat16 makes the result ~20x less accurate than a direct bf16 conv
(and OpenVINO's bf16 direct conv is faster anyway), nor for narrow convs or small maps
(128 channels at 88x304, 384 channels at 6x22: the transforms cost as much as the MatMul
saves or more, measured on a 2-core EPYC).
"""

from __future__ import annotations

import json

import numpy as np
import onnx
from onnx import numpy_helper

from gac_jax.deploy.export.graph import WINOGRAD_KEY, GraphBuilder

MIN_CHANNELS = 256
MIN_PIXELS = 1024  # H * W; the 384-channel 6x22 conv of configs/depth_default.py gains nothing


def marked_convs(model: onnx.ModelProto) -> dict[str, list[int]]:
    """``{conv output: [Cin, H, W]}`` recorded by the exporter ({} for an unmarked model)."""
    for prop in model.metadata_props:
        if prop.key == WINOGRAD_KEY:
            return json.loads(prop.value)
    return {}


def apply_winograd(
    model: onnx.ModelProto, min_channels: int = MIN_CHANNELS, min_pixels: int = MIN_PIXELS
) -> int:
    """Rewrites the marked convs with ``Cin >= min_channels`` and ``H * W >= min_pixels`` in
    place; returns how many."""
    marks = {
        k: v
        for k, v in marked_convs(model).items()
        if v[0] >= min_channels and v[1] * v[2] >= min_pixels
    }
    if not marks:
        return 0
    graph = model.graph
    weights = {t.name: t for t in graph.initializer}
    g = GraphBuilder("winograd", prefix="winograd__")
    nodes, used = [], set()
    for node in graph.node:
        out = node.output[0] if node.output else None
        if node.op_type != "Conv" or out not in marks:
            nodes.append(node)
            continue
        cin, H, W = marks[out]
        w = numpy_helper.to_array(weights[node.input[1]])  # (Cout, Cin, 5, 5)
        b = numpy_helper.to_array(weights[node.input[2]]) if len(node.input) > 2 else None
        conv = {"kernel": np.transpose(w, (2, 3, 1, 0))}  # OIHW -> HWIO
        if b is not None:
            conv["bias"] = b
        start = len(g.nodes)
        y = g.conv5x5_winograd(node.input[0], cin, (H, W), conv, relu=False)
        nodes.extend(g.nodes[start:])
        nodes.append(onnx.helper.make_node("Identity", [y], [out], name=out))
        used.update(node.input[1:])
    still_used = {i for n in nodes for i in n.input}
    keep = [t for t in graph.initializer if t.name not in used or t.name in still_used]
    del graph.initializer[:]
    graph.initializer.extend(keep + g.initializers)
    del graph.node[:]
    graph.node.extend(nodes)
    return len(marks)
