"""Deployment runtimes vs the jitted float32 path, per frame at batch 1 (CPU).

For the paper configs (configs/detect3d_kitti.py: ResNet-101 at 288x1280;
configs/depth_kitti.py: ResNet-34 U-Net at 352x1216) and the default configs, the network is
exported (:mod:`gac_jax.deploy.export`) and run as

* ``jax f32``: the jitted Flax model (the reference of every ratio); ``jax bf16`` with
  ``--jax-bf16`` (Flax compute dtype bfloat16),
* ``onnxruntime f32``, ``openvino f32`` and ``openvino bf16`` (where the CPU has native bf16),
* ``openvino int8``: the export quantized by NNCF as ``--precision int8`` does (detector:
  calibrated on ``--int8-frames`` of the real KITTI frames through the eval transform; depth:
  on random images, timing only), and per ``--keep-float REGEX[,REGEX]`` the mixed network
  with those layers in float32 (``openvino int8 f32[...]``),

with the calls interleaved (every round runs each path once, so a shared machine's load hits
them alike). Detector: the *full path* of one real KITTI frame, image file -> KITTI objects
(read + test transform, network, the jitted decoding/filter/top-k, NMS + hill-climbing), and
the network call alone; depth net: the network call. Weights are random (timing only; score
threshold 0 and ``top_k`` 100, so 100 candidates go through NMS and hill-climbing: a crowded
frame; random weights would otherwise send a varying number, up to the configs' cap of 4096,
through hill-climbing, which dominates and differs between runtimes). Reported:
medians of wall and process-CPU ms, the wall ratio to ``jax f32`` and, per detector runtime,
the non-network part of the frame (full path minus network medians); plus the CPU model and
its AMX / AVX512_BF16 / int8 dot-product flags, and the 1-minute load average.

    python benchmarks/bench_runtimes.py [--configs paper,default] [--nets detect3d,depth]
        [--rounds 5] [--threads N] [--jax-bf16] [--no-int8] [--int8-frames N]
        [--keep-float REGEX[,REGEX]] [--only LABEL,...] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path
from random_weights import random_variables, timing_detector_config

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

KITTI = REPO.parent / "shared" / "data" / "kitti_samples" / "object"
CONFIGS = {
    ("detect3d", "paper"): "configs/detect3d_kitti.py",
    ("detect3d", "default"): "configs/detect3d_default.py",
    ("depth", "paper"): "configs/depth_kitti.py",
    ("depth", "default"): "configs/depth_default.py",
}


def quantized(task, config, onnx_path: Path, size, keep, args, tmp: Path) -> Path:
    """``onnx_path`` quantized by NNCF as ``--precision int8`` does (``keep``: layers kept in
    float32); the detector calibrated on real frames (eval transform), depth on noise."""
    import numpy as np

    from gac_jax.deploy.int8 import calibration_frames, quantize_model
    from gac_jax.deploy.telemetry import import_openvino
    from gac_jax.geometry import level_plane

    ov = import_openvino()

    if task == "detect3d":
        feeds, _ = calibration_frames(task, config, args.int8_frames, 0)
    else:
        rng = np.random.default_rng(1)
        P2 = np.array([[[721.5, 0, size[1] / 2, 45], [0, 721.5, size[0] / 2, 0], [0, 0, 1, 0]]])
        feeds = [
            {
                "images": rng.normal(size=(1, *size, 3)).astype(np.float32),
                "P2": P2.astype("f4"),
                "plane": level_plane()[None].astype("f4"),
            }
            for _ in range(args.int8_frames)
        ]
    t0 = time.perf_counter()
    model = quantize_model(onnx_path, feeds, keep)
    out = tmp / f"{onnx_path.stem}_int8_{len(keep)}_{abs(hash(keep))}.xml"
    ov.save_model(model, str(out), compress_to_fp16=False)
    print(
        f"  quantized ({len(feeds)} frames, float32 {keep or 'none'}): "
        f"{time.perf_counter() - t0:.0f} s",
        flush=True,
    )
    return out


def paths_for(task, name, args, tmp: Path):
    """``{label: callable}`` of the timed calls of one network/config (built and warmed up)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from gac_jax.builders import depth as depth_builders
    from gac_jax.builders import detect3d as det_builders
    from gac_jax.config import load_config
    from gac_jax.deploy.export.networks import depth_graph, detector_graph
    from gac_jax.deploy.runtimes import (
        DEPTH_OUTPUTS,
        DETECTOR_OUTPUTS,
        OnnxNetwork,
        RuntimeDetectionPredict,
        check_runtime,
    )
    from gac_jax.geometry import level_plane

    if task == "detect3d":
        config = timing_detector_config(str(REPO / CONFIGS[(task, name)]), KITTI)
    else:
        config = load_config(str(REPO / CONFIGS[(task, name)]))
    d = config.data
    if task == "detect3d":
        layout = det_builders.anchor_layout(config)
        model = det_builders.build_model(config, layout.anchors_per_cell)
        variables = random_variables(model, config, det_builders.init_variables)
        size, graph, outputs = (d.height, d.width), detector_graph, DETECTOR_OUTPUTS
    else:
        model = depth_builders.build_model(config, 2.5)
        variables = random_variables(model, config, depth_builders.init_variables)
        size, graph, outputs = (d.height, d.eval_width), depth_graph, DEPTH_OUTPUTS
    path = tmp / f"{task}_{name}.onnx"
    path.write_bytes(graph(model, variables, size, 17).SerializeToString())

    networks = {}
    combos = [("jax", "f32")] + ([("jax", "bf16")] if args.jax_bf16 else [])
    combos += [("onnxruntime", "f32"), ("openvino", "f32"), ("openvino", "bf16")]
    if not args.no_int8:
        combos += [("openvino", "int8")]
        combos += [("openvino", f"int8 f32[{keep}]") for keep in args.keep_float]
    if args.only:
        combos = [c for c in combos if c[0] == "jax" or f"{c[0]} {c[1]}" in args.only.split(",")]
    for runtime, precision in combos:
        try:
            check_runtime(runtime, precision.split()[0])
        except Exception as e:  # noqa: BLE001 - reported, not timed
            print(f"  skip {runtime} {precision}: {e}")
            continue
        if precision.startswith("int8"):
            keep = tuple(p for p in precision[len("int8 f32[") : -1].split(",") if p)
            networks[(runtime, precision)] = OnnxNetwork(
                quantized(task, config, path, size, keep, args, tmp),
                runtime,
                "int8",
                outputs=outputs,
                image_size=size,
                threads=args.threads,
                batch_size=1,
            )
        elif runtime == "jax":
            m = model.clone(dtype=jnp.bfloat16 if precision == "bf16" else jnp.float32)
            networks[(runtime, precision)] = m
        else:
            networks[(runtime, precision)] = OnnxNetwork(
                path,
                runtime,
                precision,
                outputs=outputs,
                image_size=size,
                threads=args.threads,
                batch_size=1,
            )

    if task == "depth":
        images = np.random.default_rng(0).normal(size=(1, *size, 3)).astype(np.float32)
        P2 = np.array([[[721.5, 0, size[1] / 2, 45], [0, 721.5, size[0] / 2, 0], [0, 0, 1, 0]]])
        P2 = P2.astype(np.float32)
        plane = level_plane()[None].astype(np.float32)
        calls = {}
        for key, net in networks.items():
            if key[0] == "jax":
                fn = jax.jit(lambda v, x, P, m=net: m.apply(v, x, P, train=False)["log_depth"])
                calls[key] = lambda fn=fn: jax.block_until_ready(fn(variables, images, P2))
            else:
                calls[key] = lambda net=net: net(images, P2, plane)
        return {(f"{k[0]} {k[1]}", "network"): c for k, c in calls.items()}

    # detector: full path image file -> KITTI objects, and the network alone
    from gac_jax.cli.evaluate_detector import postprocess_config
    from gac_jax.data.loader import collate
    from gac_jax.data.sources import open_object_source
    from gac_jax.detection.anchor_priors import make_detection_constants
    from gac_jax.detection.anchors import generate_anchors
    from gac_jax.detection.inference import make_predict_fn, postprocess
    from gac_jax.evaluation.detector_evaluator import InputArrays

    priors = det_builders.compute_priors(config, KITTI, layout, tmp / f"priors_{name}")
    constants = make_detection_constants(
        generate_anchors(layout), priors, det_builders.sign_axis(config)
    )
    source = open_object_source(KITTI, "labeled", use_right_image=False)
    transform = det_builders.eval_transform(config)
    classes, post = tuple(d.classes), postprocess_config(config)
    opts = {
        "top_k": config.eval.top_k,
        "filter_options": det_builders.filter_options(config),
        "use_ground_filter": config.anchors.filter,
    }

    def load_frame():
        return collate([InputArrays()(transform(source[0]))])

    calls = {}
    for key, net in networks.items():
        if key[0] == "jax":
            predict = make_predict_fn(net, constants, **opts)
            raw = jax.jit(lambda v, x, P, m=net: m.apply(v, x, P, train=False))
        else:
            predict = RuntimeDetectionPredict(net, constants, **opts)
            predict.compile(1, size)
            raw = None

        def full(predict=predict):
            batch = load_frame()
            cand = predict(variables, batch["image"], batch["P2"], batch["plane"])
            return postprocess(cand, batch, classes, post)

        batch = load_frame()
        if raw is not None:
            calls[(f"{key[0]} {key[1]}", "network")] = lambda raw=raw, b=batch: (
                jax.block_until_ready(raw(variables, b["image"], b["P2"]))
            )
        else:
            calls[(f"{key[0]} {key[1]}", "network")] = lambda net=net, b=batch: net(
                b["image"], b["P2"], b["plane"]
            )
        calls[(f"{key[0]} {key[1]}", "full path")] = full
    return calls


def main() -> None:
    import numpy as np

    from gac_jax.deploy.runtimes import cpu_flags

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--configs", default="paper,default")
    p.add_argument("--nets", default="detect3d,depth")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--threads", type=int, help="runtime threads (default: usable cores)")
    p.add_argument("--jax-bf16", action="store_true", help="also time the jitted bf16 model")
    p.add_argument("--no-int8", action="store_true", help="skip the int8 rows")
    p.add_argument("--int8-frames", type=int, default=13, help="calibration frames (int8)")
    p.add_argument(
        "--keep-float",
        action="append",
        default=[],
        metavar="REGEX[,REGEX]",
        help="an int8 row with these layers in float32 (repeatable)",
    )
    p.add_argument("--only", help="time only these non-jax rows, e.g. 'openvino int8'")
    p.add_argument("--json", type=Path)
    args = p.parse_args()

    info = describe_machine("jax", "onnxruntime", "openvino", "onnx")
    flags = cpu_flags()
    print(one_line(info))
    yes = {True: "yes", False: "no"}
    print(
        f"CPU {flags['cpu']}: AMX-BF16 {yes[flags['amx_bf16']]}, AMX-INT8 "
        f"{yes[flags['amx_int8']]}, AVX512_BF16 {yes[flags['avx512_bf16']]}, int8 dot products "
        f"(VNNI/AMX) {yes[flags['int8_dot']]}"
    )
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_runtimes_") as tmp:
        for task in args.nets.split(","):
            for name in args.configs.split(","):
                print(f"\n=== {task} {name} ({CONFIGS[(task, name)]}), batch 1 ===", flush=True)
                t0 = time.perf_counter()
                calls = paths_for(task, name, args, Path(tmp))
                for call in calls.values():  # warm-up (and compile) outside the timing
                    call()
                print(f"  set-up and warm-up {time.perf_counter() - t0:.0f} s", flush=True)
                wall = {k: [] for k in calls}
                cpu = {k: [] for k in calls}
                for _ in range(args.rounds):
                    for key, call in calls.items():
                        w0, c0 = time.perf_counter(), time.process_time()
                        call()
                        wall[key].append(1e3 * (time.perf_counter() - w0))
                        cpu[key].append(1e3 * (time.process_time() - c0))
                for what in ("full path", "network"):
                    base = wall.get(("jax f32", what))
                    for key in calls:
                        if key[1] != what:
                            continue
                        w, c = float(np.median(wall[key])), float(np.median(cpu[key]))
                        ratio = float(np.median(base)) / w if base else float("nan")
                        rows.append(
                            {
                                "net": task,
                                "config": name,
                                "path": what,
                                "runtime": key[0],
                                "wall_ms": w,
                                "cpu_ms": c,
                                "speedup_vs_jax_f32": ratio,
                            }
                        )
                        print(
                            f"  {what:9s} {key[0]:17s} wall {w:8.1f} ms  CPU {c:8.1f} ms  "
                            f"x{ratio:5.2f} vs jax f32",
                            flush=True,
                        )
                for label in sorted({k[0] for k in calls if k[1] == "full path"}):
                    host = float(np.median(wall[(label, "full path")])) - float(
                        np.median(wall[(label, "network")])
                    )
                    rows.append(
                        {
                            "net": task,
                            "config": name,
                            "path": "non-network",
                            "runtime": label,
                            "wall_ms": host,
                        }
                    )
                    print(f"  non-network part {label:17s} {host:8.1f} ms (full - network)")
    info["load_avg_1min_end"] = round(__import__("os").getloadavg()[0], 2)
    print(f"\nload average (1 min) at the end: {info['load_avg_1min_end']}")
    if args.json:
        args.json.write_text(
            json.dumps({"machine": info, "cpu_flags": flags, "rows": rows}, indent=2)
        )


if __name__ == "__main__":
    main()
