"""The CPU's achievable multiply-accumulate rate through OpenVINO, measured per precision.

    python benchmarks/bench_peak.py [--precisions f32,bf16,int8] [--rounds 7] [--seconds 1]
        [--channels 1024] [--size 16] [--layers 4] [--kernel 3] [--threads N] [--json OUT]

The peak graph: ``--layers`` convolutions of ``--kernel`` x ``--kernel`` (stride 1, same
padding) from ``--channels`` to as many channels on a ``--size`` x ``--size`` map, each
followed by a ReLU (fused into it), one image. Its MACs leave no doubt: ``layers * size^2 *
channels^2 * kernel^2`` (9.66 GMAC by default; :func:`gac_jax.deploy.graph_macs.count_macs` of
the graph equals this hand count, tests/test_bench_peak.py), and OpenVINO runs each
convolution as the direct kernel its runtime graph names (``brgconv_avx512_I8``, ...): a
Winograd primitive, which multiplies less, is refused. It is compiled as ``bench_stream.py``'s
networks are (:func:`gac_jax.deploy.runtimes.openvino_config`: ``f32``, ``bf16`` inference
precision; ``int8``: the NNCF-quantized graph of :func:`gac_jax.deploy.int8.quantize_model`,
its other ops in float32; one call in flight on every core).

Why 3x3 convolutions by default: on a 2-core AMD EPYC (Zen 4) they ran faster per core than
1x1 convolutions (``--kernel 1``: 1024 channels on 32x32 the fastest 1x1 shape tried) and
large MatMuls, and a peak of 1x1 convolutions was beaten by the paper detector's own, mostly
3x3, convolutions on a loaded machine; among the 3x3 shapes tried (256-1024 channels, 16x16
to 64x64) this one was the fastest, within 5 %.

Per round: calls one after another for ``--seconds``; MAC/s over the wall clock (every core,
whatever clock they boost to) and MACs per busy core-second (the process's CPU time: on a
machine shared with other jobs the wall-clock rate is what the load leaves, the per-core rate
much less so). The load average is printed before each round; the figures are the medians
over ``--rounds`` (and the spread). :func:`measure_peak` is what ``bench_stream.py`` runs for
its "share of the peak".
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PRECISIONS = ("f32", "bf16", "int8")
DEFAULT_SHAPE = {"channels": 1024, "size": 16, "layers": 4, "kernel": 3}


def hand_count(channels: int, size: int, layers: int, kernel: int = 1) -> int:
    """MACs of the peak graph: each layer, every output pixel and channel, sums ``channels *
    kernel^2`` products."""
    return layers * size * size * channels * channels * kernel * kernel


def peak_graph(channels: int, size: int, layers: int, kernel: int = 1, seed: int = 0):
    """The peak graph as an ONNX ``ModelProto`` (input ``x`` (1, channels, size, size))."""
    from onnx import TensorProto, helper, numpy_helper

    rng = np.random.default_rng(seed)
    nodes, weights, x = [], [], "x"
    for i in range(layers):  # He-scaled weights: activations keep their size through the chain
        shape = (channels, channels, kernel, kernel)
        w = rng.normal(0, np.sqrt(2.0 / channels / kernel**2), shape).astype(np.float32)
        weights.append(numpy_helper.from_array(w, f"w{i}"))
        pads = [kernel // 2] * 4
        nodes.append(
            helper.make_node("Conv", [x, f"w{i}"], [f"conv{i}"], name=f"conv{i}", pads=pads)
        )
        nodes.append(helper.make_node("Relu", [f"conv{i}"], [f"relu{i}"], name=f"relu{i}"))
        x = f"relu{i}"
    shape = [1, channels, size, size]
    graph = helper.make_graph(
        nodes,
        "peak",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info(x, TensorProto.FLOAT, shape)],
        weights,
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])


def executed_primitives(compiled) -> dict[str, int]:
    """``{primitive: count}`` of the convolutions of an OpenVINO compiled model, from its
    runtime graph (``brgconv_avx512_1x1_I8``, ...; Winograd shows as ``*wino*``)."""
    out: dict[str, int] = {}
    for op in compiled.get_runtime_model().get_ordered_ops():
        info = op.get_rt_info()
        if "layerType" in info and info["layerType"].astype(str) == "Convolution":
            name = info["primitiveType"].astype(str) if "primitiveType" in info else "?"
            out[name] = out.get(name, 0) + 1
    return out


def _compile(model, precision: str, threads: int, work: Path):
    from gac_jax.deploy.runtimes import openvino_config
    from gac_jax.deploy.telemetry import import_openvino

    ov = import_openvino()
    path = work / "peak.onnx"
    path.write_bytes(model.SerializeToString())
    x = model.graph.input[0].type.tensor_type.shape.dim
    feed = {"x": np.random.default_rng(1).random([d.dim_value for d in x], np.float32)}
    if precision == "int8":
        from gac_jax.deploy.int8 import quantize_model

        network = quantize_model(path, [feed] * 4)
    else:
        network = ov.Core().read_model(str(path))
    compiled = ov.Core().compile_model(network, "CPU", openvino_config(precision, threads))
    return compiled, feed


def measure_peak(
    precision: str,
    threads: int | None = None,
    rounds: int = 7,
    seconds: float = 1.0,
    shape: dict | None = None,
    log=print,
) -> dict:
    """Runs the peak graph at ``precision`` (module docstring). Returns ``{precision, macs,
    primitives, wall_macs_per_s, core_macs_per_s: {median, min, max, rounds}, loads,
    threads}`` (rates in MACs per second; ``core``: per busy core-second)."""
    shape = {**DEFAULT_SHAPE, **(shape or {})}
    threads = threads or len(os.sched_getaffinity(0))
    macs = hand_count(**shape)
    with tempfile.TemporaryDirectory(prefix="bench_peak_") as tmp:
        compiled, feed = _compile(peak_graph(**shape), precision, threads, Path(tmp))
    primitives = executed_primitives(compiled)
    if any("wino" in p.lower() for p in primitives):
        raise ValueError(
            f"OpenVINO runs the peak graph's convolutions as {primitives}: Winograd multiplies "
            "less than the graph counts; choose another --kernel or shape"
        )
    request = compiled.create_infer_request()
    request.infer(feed)  # warm-up
    wall, core, loads = [], [], []
    for _ in range(rounds):
        loads.append(round(os.getloadavg()[0], 2))
        calls, t0, c0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - t0 < seconds or calls < 2:
            request.infer(feed)
            calls += 1
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        wall.append(calls * macs / dt)
        core.append(calls * macs / dc)
        log(
            f"    {precision} round: {calls} calls, {wall[-1] / 1e9:.1f} GMAC/s, "
            f"{core[-1] / 1e9:.1f} GMAC per busy core-second (load {loads[-1]})"
        )

    def stats(values):
        return {
            "median": float(np.median(values)),
            "min": float(min(values)),
            "max": float(max(values)),
            "rounds": values,
        }

    return {
        "precision": precision,
        "shape": shape,
        "macs": macs,
        "threads": threads,
        "primitives": primitives,
        "wall_macs_per_s": stats(wall),
        "core_macs_per_s": stats(core),
        "loads": loads,
    }


def measure_peaks(precisions, threads: int, rounds: int, seconds: float) -> dict:
    """:func:`measure_peak` of each of ``precisions`` that OpenVINO runs here, printed as it
    goes: ``{precision: result}``."""
    from gac_jax.deploy.runtimes import check_runtime

    peaks = {}
    print(f"measured peak (benchmarks/bench_peak.py, {rounds} rounds):", flush=True)
    for precision in (p for p in PRECISIONS if p in precisions):
        try:
            check_runtime("openvino", precision)
        except Exception as e:  # noqa: BLE001 - reported, not measured
            print(f"  no {precision} peak: {e}", flush=True)
            continue
        peaks[precision] = measure_peak(precision, threads, rounds, seconds, log=lambda _: None)
        print("  " + describe(peaks[precision]), flush=True)
    return peaks


def describe(peak: dict) -> str:
    """One line: a precision's measured peak."""
    w, c = peak["wall_macs_per_s"], peak["core_macs_per_s"]
    prims = ", ".join(f"{n} x{k}" for n, k in peak["primitives"].items())
    return (
        f"{peak['precision']}: {w['median'] / 1e9:.1f} GMAC/s on {peak['threads']} threads "
        f"(rounds {w['min'] / 1e9:.1f}-{w['max'] / 1e9:.1f}), {c['median'] / 1e9:.1f} GMAC per "
        f"busy core-second ({c['min'] / 1e9:.1f}-{c['max'] / 1e9:.1f}); load "
        f"{min(peak['loads'])}-{max(peak['loads'])}; convolutions run as {prims}"
    )


def main(argv=None) -> int:
    from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

    from gac_jax.data.files import atomic_write

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--precisions", default=",".join(PRECISIONS))
    p.add_argument("--rounds", type=int, default=7)
    p.add_argument("--seconds", type=float, default=1.0, help="per round")
    p.add_argument("--channels", type=int, default=DEFAULT_SHAPE["channels"])
    p.add_argument("--size", type=int, default=DEFAULT_SHAPE["size"])
    p.add_argument("--layers", type=int, default=DEFAULT_SHAPE["layers"])
    p.add_argument("--kernel", type=int, default=DEFAULT_SHAPE["kernel"], help="1 or 3")
    p.add_argument("--threads", type=int, help="default: every usable core")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    from gac_jax.deploy.runtimes import check_runtime

    info = describe_machine("openvino", "nncf")
    print(one_line(info))
    shape = {"channels": args.channels, "size": args.size, "layers": args.layers}
    shape["kernel"] = args.kernel
    k = args.kernel
    print(
        f"peak graph: {args.layers} x {k}x{k} conv {args.channels}->{args.channels} on "
        f"{args.size}x{args.size}: {hand_count(**shape) / 1e9:.3f} GMAC per call"
    )
    peaks = {}
    for precision in args.precisions.split(","):
        try:
            check_runtime("openvino", precision)
        except Exception as e:  # noqa: BLE001 - reported, not measured
            print(f"  skip {precision}: {e}")
            continue
        peaks[precision] = measure_peak(precision, args.threads, args.rounds, args.seconds, shape)
        print("  " + describe(peaks[precision]), flush=True)
    if "int8" in peaks and "f32" in peaks:
        ratio = {k: peaks[k]["core_macs_per_s"]["median"] for k in peaks}
        print(
            "  per busy core-second, relative to f32: "
            + ", ".join(f"{k} {v / ratio['f32']:.2f}x" for k, v in ratio.items())
        )
    if args.json:
        with atomic_write(args.json) as f:
            json.dump({"machine": info, "peaks": peaks}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
