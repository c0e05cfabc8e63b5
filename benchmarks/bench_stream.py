"""The stream path end to end: video file in -> annotated video + result files out (CPU).

For the default detector (configs/detect3d_default.py: ResNet-18/2 at 160x720) and the paper
detector (configs/detect3d_kitti.py: ResNet-101 at 288x1280), per runtime and precision that
runs on this machine (jax f32/bf16, onnxruntime f32, openvino f32/bf16/int8), a KITTI-size
(1242x375) MPEG-4 video of the vendored real KITTI frames (tests/data/kitti) goes through the
stream pipeline of ``python -m gac_jax.cli.predict --video``
(:class:`gac_jax.streams.pipeline.StreamPipeline`): decode, test transform, network,
decoding + NMS + hill-climbing, drawing the 3D boxes and the bird's-eye view, MPEG-4
encoding of the annotated frame and the KITTI result file, the five stages overlapping on
threads. Weights are random (timing only; score threshold 0 and ``top_k`` 100 as in
bench_runtimes.py: 100 candidates per frame through NMS and hill-climbing, a crowded frame).

Reported per row: sustained frames/s (frames written / wall time from the first frame's read
to the last frame's write; the median over ``--rounds``), per-frame latency (decode start
to written; median and p95 over the frames of every round) and the milliseconds each stage
works per frame (stages overlap: the slowest one sets the rate) and the process CPU time per
frame (all threads: what the stream costs the machine, less sensitive to other load than the
wall-clock figures), plus the machine and its load. Export, int8 calibration and the first
(compiling) frame are outside the timing.

    python benchmarks/bench_stream.py [--configs default,paper] [--frames 120]
        [--paper-frames 20] [--rounds 2] [--only 'jax f32,openvino int8'] [--batch-size 1]
        [--threads N] [--workdir W] [--live FPS] [--json OUT] [--requests 1,2]
        [--no-video] [--video-scale S] [--container mp4|avi] [--net-frames N] [--profile]
        [--peak-rounds 5] [--peak-seconds 1] [--track] [--codec h264|mjpeg]
        [--mcap [--mcap-profile ros2]]

Core accounting per row: each stage's CPU time per frame (its thread's), the XLA threads'
(decoding; the jax runtime's network), the rest (the ONNX Runtime / OpenVINO inference
threads and the video encoder's own threads: process CPU minus the stage and XLA threads),
the video encoder's thread (H.264 by default, ``--codec mjpeg`` as the CLI's; its own line),
the total core-ms per frame against wall x cores, and the stream's rate as a fraction of the
network-alone rate measured in the same run (``infer`` on ``--net-frames`` prepared frames one
after another, before each round; the median over rounds: one measurement of a few frames
varied by 10-15 % between runs on a 2-core VM), and the bound the host stages set: when the
network alone keeps every core busy (N core-ms per frame), a stream whose host stages take H
core-ms per frame reaches at most N / (N + H) of the network-alone rate.
Per config a summary: the network's MACs (counted from the exported ONNX graph,
:mod:`gac_jax.deploy.graph_macs`), its MAC rate alone (over the wall clock, and per busy
core-second, which a shared machine's load leaves alone) and their shares of this machine's
*measured* peak for that precision (``benchmarks/bench_peak.py``, run first for each OpenVINO
precision of the run: ``--peak-rounds`` of ``--peak-seconds``, medians; jax and ONNX Runtime
rows against OpenVINO's float32 peak). Every OpenVINO row prints the primitive each
convolution ran as (the compiled model's runtime graph): a Winograd convolution, which
multiplies less than the graph counts, would show there, and a share above 100 % says why on
its line. ``--profile``: OpenVINO's per-layer counters per layer type and executed precision.
The stream runs with the CLI's thread budget (:mod:`gac_jax.streams.thread_budget`);
``--requests 1,2`` times each ONNX Runtime / OpenVINO row with that many network calls in
flight (``--network-requests``); ``--no-video``, ``--video-scale S`` and ``--container avi``
(OpenCV's Motion JPEG instead of the MP4), ``--codec`` and ``--mcap`` (an MCAP recording of
every frame, its core-ms per frame printed: the time inside the recorder's ``write``) as the
CLI's options.

``--workdir W`` adds rows of a trained detector (W's checkpoint and config: its score
threshold, so the post-processing sees what that detector keeps; copy a run folder first,
the runtimes export into it). ``--live FPS`` adds one pass per row paced as a camera at FPS
(``--realtime``: the newest frame kept): the frames dropped and the latency of a live stream.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_peak import measure_peaks
from core_accounting import ThreadCpu, cpu_info, exported_onnx, mac_summary, primitives, profile
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path
from random_weights import random_variables, timing_detector_config
from stream_row import print_row

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

KITTI = REPO / "tests" / "data" / "kitti" / "object"  # the vendored real frames (split labeled)
CONFIGS = {
    "default": "configs/detect3d_default.py",
    "paper": "configs/detect3d_kitti.py",
    "tiny": "configs/detect3d_default.py:tiny",  # a check of the script, not a result
}
FRAME_SIZE = (375, 1242)  # KITTI's


def make_video(path: Path, frames: int) -> tuple[Path, Path]:
    """An MPEG-4 video of the KITTI sample frames (cropped/resized to 1242x375, cycled) and
    the calibration of its first frame."""
    import cv2

    from gac_jax.data.files import read_image

    images = sorted((KITTI / "training" / "image_2").glob("*.png"))
    h, w = FRAME_SIZE
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (w, h))
    for i in range(frames):
        image = read_image(images[i % len(images)])[:h, :w]
        if image.shape[:2] != (h, w):
            image = cv2.resize(image, (w, h), interpolation=cv2.INTER_LINEAR)
        writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    writer.release()
    return path, KITTI / "training" / "calib" / f"{images[0].stem}.txt"


def random_detector(name: str, tmp: Path):
    """A :class:`LoadedDetector` of config ``name`` with random weights (priors from the
    KITTI samples)."""
    from gac_jax.builders import detect3d as builders
    from gac_jax.detection.anchor_priors import make_detection_constants
    from gac_jax.detection.anchors import generate_anchors
    from gac_jax.trained.detector import LoadedDetector

    config = timing_detector_config(str(REPO / CONFIGS[name]), KITTI)
    layout = builders.anchor_layout(config)
    model = builders.build_model(config, layout.anchors_per_cell)
    variables = random_variables(model, config, builders.init_variables)
    priors = builders.compute_priors(config, KITTI, layout, tmp / f"priors_{name}")
    constants = make_detection_constants(
        generate_anchors(layout), priors, builders.sign_axis(config)
    )
    return LoadedDetector(config, model, constants, variables, "random weights", f"random_{name}")


def run_stream(
    detector,
    video: Path,
    calib: Path,
    out: Path,
    args,
    live_fps: float | None = None,
) -> dict:
    """One pass of the stream pipeline over ``video`` (``live_fps``: paced as a camera at that
    rate, newest frame kept, as ``--realtime``); returns its rates, latencies and CPU times."""
    import functools

    from gac_jax.drawing.detection_pictures import detection_picture
    from gac_jax.streams import outputs, sources
    from gac_jax.streams.pipeline import StreamPipeline

    P2 = sources.load_projection(calib)
    source = sources.VideoSource(video, P2, str(calib), decode_threads=args.decode_threads)
    annotated = recorder = None
    if not args.no_video:
        codec = args.codec if args.container == "mp4" else None
        annotated = outputs.AnnotatedVideo(out / f"annotated.{args.container}", source.fps, codec)
    if args.mcap:
        from gac_jax.streams.mcap_recording import McapRecording, McapResults

        recording = McapRecording(out / "run.mcap", args.mcap_profile, (0.0, -1.0, 0.0, 1.65))
        recorder = McapResults(recording, source.fps or 10.0)
    results, track = outputs.KittiResults(out / "data"), None
    if args.track:  # as predict --track: tracks drawn and written as KITTI tracking lines
        from gac_jax.api.tracker import Tracker3D
        from gac_jax.streams.tracking import KittiTrackingResults, TrackingStage

        results = KittiTrackingResults(out / "tracking", "0000")
        fps = source.fps or 10.0
        tracker = Tracker3D(detector.config)
        track = TrackingStage(tracker, fps, bool(live_fps), None, args.video_scale)
    if live_fps:
        source = sources.PacedSource(source, live_fps)
    pipeline = StreamPipeline(
        source,
        detector,
        annotated,
        results,
        batch_size=1 if live_fps else args.batch_size,
        realtime=bool(live_fps),
        report_every=0,
        draw=functools.partial(detection_picture, scale=args.video_scale),
        network_requests=detector.requests,
        track=track,
        recorder=recorder,
    )
    threads = ThreadCpu()
    threads.start()
    cpu0, t0 = time.process_time(), time.perf_counter()
    try:
        report = pipeline.run()
        other = threads.stop()  # before the encoder's threads end with the writer
        cpu_s, wall_s = time.process_time() - cpu0, time.perf_counter() - t0
    finally:
        for output in (annotated, recorder):
            if output is not None:
                output.close()
        source.close()
    if report.error is not None:
        raise report.error
    n = max(report.written, 1)
    stage_cpu = pipeline.stage_ms(cpu=True)
    xla_ms = 1e3 * other["xla_s"] / n
    encoder_ms = 1e3 * annotated.encoder_cpu_s / n if annotated is not None else 0.0
    return {
        "fps": report.rates["fps"],
        "latencies": pipeline.rates.latencies().tolist(),
        "frames": report.written,
        "delivered": report.delivered,
        "dropped": report.dropped_live,
        "stage_ms": report.stage_ms,
        "stage_cpu_ms": stage_cpu,
        "xla_cpu_ms": xla_ms,
        "encoder_cpu_ms": encoder_ms,
        "mcap_cpu_ms": 1e3 * recorder.recording.cpu_s / n if recorder is not None else 0.0,
        # runtime inference threads + the rest of the process
        "other_cpu_ms": 1e3 * cpu_s / n - sum(stage_cpu.values()) - xla_ms - encoder_ms,
        "cpu_ms_per_frame": 1e3 * cpu_s / n,
        "wall_core_ms_per_frame": 1e3 * wall_s * cpu_info()["cores"] / n,
    }


def network_alone(detector, video: Path, calib: Path, frames: int) -> dict:
    """The stream's network stage alone (``infer`` of one prepared frame after another, the
    decoding included) and, for an exported network, its bare call: median ms per frame (with
    calls in flight: the rate, :func:`calls_in_flight`)."""
    import numpy as np

    from gac_jax.streams import sources

    source = sources.VideoSource(video, sources.load_projection(calib), str(calib))
    try:
        prepared = []
        while len(prepared) < frames and (frame := source.read()) is not None:
            prepared.append(detector.prepare(frame.image, frame.P2, frame.plane))
    finally:
        source.close()
    network = getattr(detector._predict, "network", None)
    if detector.requests > 1:  # the rate with that many calls in flight
        return calls_in_flight(detector, network, prepared)
    infer, bare, cpu = [], [], []
    for p in prepared:
        t0, c0 = time.perf_counter(), time.process_time()
        detector.infer([p])
        infer.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if network is not None:
            t0 = time.perf_counter()
            network(p.image[None], p.P2[None], p.plane[None])
            bare.append(time.perf_counter() - t0)
    out = {"infer_ms": 1e3 * float(np.median(infer)), "infer_cpu_ms": 1e3 * float(np.median(cpu))}
    if bare:
        out["network_ms"] = 1e3 * float(np.median(bare))
    return out


def with_dtype(loaded, runtime: str, precision: str):
    """``loaded`` with the compute dtype of ``runtime``/``precision`` (jax bf16: bfloat16)."""
    import dataclasses

    import jax.numpy as jnp

    if (runtime, precision) != ("jax", "bf16"):
        return loaded
    return dataclasses.replace(loaded, model=loaded.model.clone(dtype=jnp.bfloat16))


def measure(detector, video: Path, calib: Path, out: Path, args) -> dict:
    """``args.rounds`` passes of the stream over ``video``: medians of frames/s, stage times
    and CPU per frame; latency median and p95 over every round's frames."""
    import numpy as np

    from gac_jax.streams.rates import percentile_ms

    t0 = time.perf_counter()
    results, alone = [], []
    for r in range(args.rounds):  # the network alone before each round: the same conditions
        alone.append(network_alone(detector, video, calib, args.net_frames))
        results.append(run_stream(detector, video, calib, out / str(r), args))
    latencies = [x for r in results for x in r["latencies"]]

    def median_of(key):
        return {k: float(np.median([r[key][k] for r in results])) for k in results[0][key]}

    row = {
        "rounds": args.rounds,
        "fps_median": float(np.median([r["fps"] for r in results])),
        "fps_rounds": [r["fps"] for r in results],
        "latency_median_ms": percentile_ms(latencies, 50),
        "latency_p95_ms": percentile_ms(latencies, 95),
        "stage_ms": median_of("stage_ms"),
        "stage_cpu_ms": median_of("stage_cpu_ms"),
        "cpu_ms_per_frame": float(np.median([r["cpu_ms_per_frame"] for r in results])),
        **{
            k: float(np.median([r[k] for r in results]))
            for k in (
                "xla_cpu_ms",
                "encoder_cpu_ms",
                "mcap_cpu_ms",
                "other_cpu_ms",
                "wall_core_ms_per_frame",
            )
        },
        "frames_written": [r["frames"] for r in results],
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    if args.live:  # one pass paced as a camera: what a live stream keeps and its latency
        live = run_stream(detector, video, calib, out / "live", args, args.live)
        row["live"] = {
            "fps": args.live,
            "delivered": live["delivered"],
            "dropped": live["dropped"],
            "latency_median_ms": percentile_ms(live["latencies"], 50),
            "latency_p95_ms": percentile_ms(live["latencies"], 95),
        }
    row.update({k: float(np.median([a[k] for a in alone])) for k in alone[0]})
    row["infer_ms_rounds"] = [a["infer_ms"] for a in alone]
    row["stream_over_network"] = row["fps_median"] * row["infer_ms"] / 1e3
    # on a machine shared with other work: the share of the process's CPU the network takes
    row["network_cpu_share"] = row["infer_cpu_ms"] / row["cpu_ms_per_frame"]
    row["wall_s"] = time.perf_counter() - t0
    return row


def calls_in_flight(detector, network, prepared: list) -> dict:
    """ms per frame of ``infer_async`` (and the bare network's ``start``) with
    ``detector.requests`` calls in flight over ``prepared``."""
    import collections

    def rate(start) -> tuple[float, float]:
        pending = collections.deque()
        t0, c0 = time.perf_counter(), time.process_time()
        for p in prepared:
            if len(pending) == detector.requests:
                pending.popleft().result()
            pending.append(start(p))
        while pending:
            pending.popleft().result()
        n = len(prepared)
        return 1e3 * (time.perf_counter() - t0) / n, 1e3 * (time.process_time() - c0) / n

    infer_ms, cpu_ms = rate(lambda p: detector.infer_async([p]))
    out = {"infer_ms": infer_ms, "infer_cpu_ms": cpu_ms}
    if network is not None:
        out["network_ms"] = rate(lambda p: network.start(p.image[None], p.P2[None], p.plane[None]))[
            0
        ]
    return out


def main() -> None:
    from gac_jax.api.detector import Detector3D
    from gac_jax.deploy.graph_macs import count_macs
    from gac_jax.deploy.runtimes import RUNTIME_PRECISIONS, check_runtime, cpu_flags
    from gac_jax.streams import sources
    from gac_jax.streams.thread_budget import apply_host_threads, plan_thread_budget

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--configs", default="default,paper")
    p.add_argument("--frames", type=int, default=120, help="video frames (default detector)")
    p.add_argument("--paper-frames", type=int, default=20, help="video frames (paper detector)")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--only", help="rows to run, e.g. 'jax f32,openvino int8' (default: all)")
    p.add_argument("--batch-size", type=int, default=1)
    p.add_argument("--threads", type=int, help="ONNX Runtime / OpenVINO threads")
    p.add_argument(
        "--workdir", help="also a trained detector's run folder (its weights and config)"
    )
    p.add_argument(
        "--live", type=float, metavar="FPS", help="also one pass paced as a camera at FPS"
    )
    p.add_argument("--json", type=Path)
    p.add_argument("--requests", default="1,2", help="network calls in flight, per row")
    p.add_argument("--no-video", action="store_true", help="results only")
    p.add_argument("--track", action="store_true", help="as predict --track (the 3D tracker)")
    p.add_argument("--video-scale", type=float, default=1.0)
    p.add_argument("--container", default="mp4", choices=("mp4", "avi"))
    p.add_argument("--codec", default="h264", choices=("h264", "mjpeg"), help="of the mp4")
    p.add_argument("--mcap", action="store_true", help="also an MCAP recording of every frame")
    p.add_argument("--mcap-profile", default="foxglove", choices=("foxglove", "ros2"))
    p.add_argument(
        "--decode-threads",
        type=int,
        default=1,
        help="FFmpeg decoder threads (default 1, the stream's budget; 0: FFmpeg's choice)",
    )
    p.add_argument(
        "--net-frames", type=int, default=30, help="frames of the network alone, per round"
    )
    p.add_argument("--profile", action="store_true", help="OpenVINO per-layer counters")
    p.add_argument("--peak-rounds", type=int, default=5, help="rounds of the peak graph")
    p.add_argument("--peak-seconds", type=float, default=1.0, help="per peak round")
    args = p.parse_args()
    args.decode_threads = args.decode_threads or None

    sources.quiet_video_backend()
    budget = plan_thread_budget(args.threads)
    apply_host_threads(budget)
    info = describe_machine("jax", "onnxruntime", "openvino", "cv2")
    flags = cpu_flags()
    print(one_line(info))
    print(
        f"CPU flags: AMX-BF16 {flags['amx_bf16']}, AMX-INT8 {flags['amx_int8']}, "
        f"AVX512_BF16 {flags['avx512_bf16']}, int8 dot products {flags['int8_dot']}"
    )
    video_kind = "no video" if args.no_video else f"{args.container} video x{args.video_scale:g}"
    video_kind += f" ({args.codec})" if args.container == "mp4" and not args.no_video else ""
    video_kind += f", MCAP ({args.mcap_profile})" if args.mcap else ""
    video_kind += ", tracking" if args.track else ""
    print(f"{budget.describe('openvino')}; output: {video_kind}")
    combos = [c for c in RUNTIME_PRECISIONS if not args.only or " ".join(c) in args.only.split(",")]
    requests = [int(r) for r in args.requests.split(",") if r]
    names = [n for n in args.configs.split(",") if n]
    if args.workdir is not None:
        names.append("trained")
    # the peak of each OpenVINO precision of the run (float32 for the jax and ONNX Runtime rows)
    wanted = {precision if runtime == "openvino" else "f32" for runtime, precision in combos}
    peaks = measure_peaks(wanted, budget.network_threads, args.peak_rounds, args.peak_seconds)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_stream_") as tmp:
        tmp = Path(tmp)
        for name in names:
            n = args.paper_frames if name == "paper" else args.frames
            video, calib = make_video(tmp / f"input_{n}.mp4", n)
            what = f"{args.workdir}, its config" if name == "trained" else CONFIGS[name]
            print(f"\n=== {name} detector ({what}), {n}-frame 1242x375 MPEG-4 video ===")
            loaded = random_detector(name, tmp) if name != "trained" else None
            macs = None
            for runtime, precision in combos:
                try:
                    check_runtime(runtime, precision)
                except Exception as e:  # noqa: BLE001 - reported, not timed
                    print(f"  skip {runtime} {precision}: {e}", flush=True)
                    continue
                for r in requests if runtime != "jax" else [1]:
                    label = f"{runtime} {precision}" + (f" {r} requests" if r > 1 else "")
                    t0 = time.perf_counter()
                    model = {
                        "runtime": runtime,
                        "precision": precision,
                        "threads": budget.network_threads if runtime != "jax" else None,
                        "batch_size": args.batch_size,
                        "requests": r,
                    }
                    if loaded is None:
                        detector = Detector3D.from_workdir(args.workdir, **model)
                    else:
                        loaded_dtype = with_dtype(loaded, runtime, precision)
                        detector = Detector3D(loaded_dtype, tmp / f"workdir_{name}", **model)
                    detector.warmup()
                    row = {"config": name, "runtime": runtime, "precision": precision}
                    row.update({"requests": r, "label": label, "frames": n})
                    out = tmp / f"out_{name}_{label}"
                    row.update(measure(detector, video, calib, out, args))
                    row["setup_s"] = time.perf_counter() - t0 - row.pop("wall_s")
                    if (prims := primitives(detector)) is not None:
                        row["primitives"] = prims
                    rows.append(row)
                    print_row(label, row)
                    if macs is None and (onnx := exported_onnx(detector)) is not None:
                        macs = count_macs(onnx)
                    if args.profile and runtime == "openvino" and r == 1:
                        profile(detector, row, budget.network_threads)
                    del detector
            best = max((r for r in rows if r["config"] == name), key=lambda r: r["fps_median"])
            print(
                f"  fastest: {best['label']} {best['fps_median']:.1f} frames/s end to end "
                f"({best['stream_over_network']:.0%} of its network alone)"
            )
            mac_summary(rows, name, macs, peaks)
    info["load_avg_1min_end"] = round(os.getloadavg()[0], 2)
    print(f"\nload average (1 min) at the end: {info['load_avg_1min_end']}")
    if args.json:
        result = {"machine": info, "cpu_flags": flags, "peaks": peaks, "rows": rows}
        args.json.write_text(json.dumps(result, default=str))


if __name__ == "__main__":
    main()
