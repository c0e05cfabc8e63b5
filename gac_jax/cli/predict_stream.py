"""``python -m gac_jax.cli.predict --video/--camera/--sequence/--clip``: a stream through the
detector, written as an annotated video and per-frame results while it runs.

    python -m gac_jax.cli.predict --workdir W (--video FILE | --camera INDEX | --sequence DIR |
        --clip [N]) [--calib FILE] [--plane FILE] [--out DIR] [--out-video FILE] [--no-images]
        [--jsonl] [--realtime] [--fps F] [--max-frames N] [--report-every S]
        [--runtime R] [--precision P] [--batch-size B] [--threads T] [--score-threshold S]
        [--no-video] [--video-scale S] [--network-requests N]

A video or camera needs ``--calib FILE`` (KITTI calibration with a ``P2`` line, checked
against the frame size); a ``--sequence`` in the KITTI tracking layout
(``ROOT/training/image_02/SSSS/``) finds ``ROOT/training/calib/SSSS.txt`` and the per-frame
planes ``ROOT/training/planes/SSSS/<frame>.txt`` by itself; ``--clip N`` runs on generated
driving clip N (made into the cache on first use, no download). Without a plane the config's
level camera is used. Writes ``OUT/annotated.mp4`` (camera view with 3D boxes | bird's-eye
view, at the input's fps) and ``OUT/data/<frame>.txt`` (or ``OUT/detections.jsonl`` with
``--jsonl``) as frames finish; prints frames/s and latency every few seconds and at the end.
Ctrl-C stops reading and finishes the frames in flight (twice: drops them); the video stays
playable.

Throughput: ``--no-video`` writes the results only; ``--video-scale 0.5`` draws and encodes a
half-size annotated frame; the container sets the encoder (``.mp4``: MPEG-4 part 2; ``.avi``
/ ``.mkv``: Motion JPEG, about as costly per frame, larger files); ``--network-requests 2``
keeps two network calls in flight (OpenVINO: two streams sharing the ``--threads``). The
stream sizes its threads as one budget (:mod:`gac_jax.streams.thread_budget`), printed.
"""

from __future__ import annotations

import argparse
import functools
import os
import signal
import sys
from pathlib import Path

from gac_jax.data.files import KittiFormatError

STREAM_SOURCES = ("video", "camera", "sequence", "clip")
CLIP_SEQUENCES = 2  # sequences of the generated clip set (--clip 0, --clip 1)
CLIP_FRAMES = 60  # frames per sequence (6 s at 10 Hz; about 1 s per frame to generate)
EXIT_INTERRUPTED = 130
DEFAULT_FPS = 10.0  # a sequence's rate (KITTI records at 10 Hz), or a source's without one


def add_stream_arguments(parser: argparse.ArgumentParser) -> None:
    """The stream options of ``python -m gac_jax.cli.predict``."""
    group = parser.add_argument_group("streams (instead of IMAGE_OR_DIR)")
    group.add_argument("--video", metavar="FILE", help="a video file (fps from the file)")
    group.add_argument("--camera", metavar="INDEX", type=int, help="a camera (cv2 device index)")
    group.add_argument("--sequence", metavar="DIR", help="an image folder as an ordered sequence")
    group.add_argument(
        "--clip",
        metavar="N",
        type=int,
        nargs="?",
        const=0,
        help=f"generated driving clip N (0-{CLIP_SEQUENCES - 1}, default 0; {CLIP_FRAMES} "
        "frames made into the cache on first use)",
    )
    group.add_argument("--plane", metavar="FILE", help="ground plane of every frame")
    group.add_argument("--out-video", metavar="FILE", help="annotated video (.mp4/.avi/...)")
    group.add_argument("--jsonl", action="store_true", help="OUT/detections.jsonl, not data/")
    group.add_argument(
        "--realtime",
        action="store_true",
        help="keep only the newest frame when the detector falls behind (a file is paced "
        "to its fps, as a camera)",
    )
    group.add_argument("--fps", type=float, help="frame rate of a sequence (default 10)")
    group.add_argument("--max-frames", type=int, help="stop after this many frames")
    group.add_argument("--report-every", type=float, default=5.0, help="seconds per line")
    add_throughput_arguments(group)


def add_throughput_arguments(group) -> None:
    """What a stream spends its cores on: the video (none, or smaller) and the network's
    calls in flight."""
    group.add_argument(
        "--no-video", dest="no_images", action="store_true", help="results only (no video)"
    )
    group.add_argument(
        "--video-scale",
        type=float,
        default=1.0,
        metavar="S",
        help="annotated video at S times the input's size (0 < S <= 1; less to draw and encode)",
    )
    group.add_argument(
        "--network-requests",
        type=int,
        default=1,
        metavar="N",
        help="network calls in flight (openvino/onnxruntime; 2: the next frame's network runs "
        "while this one is finished)",
    )


def stream_kind(args: argparse.Namespace) -> str | None:
    """Which stream source the arguments ask for (None: image input)."""
    given = [k for k in STREAM_SOURCES if getattr(args, k) is not None]
    return given[0] if given else None


def check_stream_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    given = [f"--{k}" for k in STREAM_SOURCES if getattr(args, k) is not None]
    if args.input is not None and args.camera is not None:
        parser.error(
            "--camera INDEX opens a live camera; the P2/P3 choice of image input is "
            "--calib-camera 2|3"
        )
    if args.input is not None and given:
        parser.error(f"IMAGE_OR_DIR and {given[0]} are two inputs; give one")
    if len(given) > 1:
        parser.error(f"{' and '.join(given)} are several inputs; give one")
    if args.input is None and not given:
        parser.error("give IMAGE_OR_DIR or one of --video, --camera, --sequence, --clip")
    if args.out_video is not None and args.no_images:
        parser.error("--out-video and --no-images: give one (--no-images writes no video)")
    if not given:
        stream_only = ["plane", "out_video", "jsonl", "realtime", "fps", "max_frames"]
        used = [
            f"--{k.replace('_', '-')}" for k in stream_only if getattr(args, k) not in (None, False)
        ]
        used += [
            f"--{k}"
            for k, v in (
                ("video-scale", args.video_scale != 1.0),
                ("network-requests", args.network_requests != 1),
            )
            if v
        ]
        if used:
            parser.error(f"{used[0]} applies to --video/--camera/--sequence/--clip only")
        return
    if args.config is not None and args.checkpoint is None:
        parser.error(
            "--config: a stream runs the workdir's own config (or --checkpoint + --config)"
        )
    if args.fps is not None and not args.fps > 0:
        parser.error("--fps must be > 0")
    if args.max_frames is not None and args.max_frames < 1:
        parser.error("--max-frames must be >= 1")
    if args.clip is not None and args.clip < 0:
        parser.error("--clip N must be >= 0")
    if not 0 < args.video_scale <= 1:
        parser.error(f"--video-scale must be in (0, 1], got {args.video_scale:g}")
    if args.network_requests < 1:
        parser.error(f"--network-requests must be >= 1, got {args.network_requests}")
    if args.network_requests > 1 and args.runtime == "jax":
        parser.error("--network-requests applies to --runtime openvino/onnxruntime")


def clip_sequence(index: int) -> Path:
    """Folder of sequence ``index`` of the generated clip set (:data:`CLIP_SEQUENCES` x
    :data:`CLIP_FRAMES` frames in the cache, tracking layout), generated on first use."""
    from gac_jax.data.synthetic.clips import default_clip_dir, ensure_clips

    if not 0 <= index < CLIP_SEQUENCES:
        raise KittiFormatError(
            "--clip", f"{index}: the generated set has sequences 0 to {CLIP_SEQUENCES - 1}"
        )
    try:
        root = ensure_clips(None, CLIP_SEQUENCES, CLIP_FRAMES)
    except ValueError as e:
        where = default_clip_dir(CLIP_SEQUENCES, CLIP_FRAMES)
        raise KittiFormatError(where, str(e).removeprefix(f"{where}: ")) from None
    return Path(root) / "training" / "image_02" / f"{index:04d}"


def open_source(args: argparse.Namespace):
    """The frame source the arguments name (checks input and calibration; nothing loaded)."""
    from gac_jax.data.kitti import read_plane
    from gac_jax.streams import sources

    sources.quiet_video_backend()
    kind = stream_kind(args)
    plane = read_plane(args.plane) if args.plane else None
    if kind in ("video", "camera"):
        name = args.video if kind == "video" else f"camera {args.camera}"
        if args.calib is None:
            raise KittiFormatError(
                name, "no calibration: pass --calib FILE (a KITTI calibration with a P2 line)"
            )
        if not Path(args.calib).is_file():
            raise KittiFormatError(args.calib, "calibration file not found")
        P2 = sources.load_projection(args.calib, args.calib_camera)
        if kind == "video":
            source = sources.VideoSource(args.video, P2, args.calib, plane)
        else:
            source = sources.CameraSource(args.camera, P2, args.calib, plane)
        if args.fps is not None:
            source.fps = args.fps
    else:
        folder = clip_sequence(args.clip) if kind == "clip" else Path(args.sequence)
        if args.calib is not None and not Path(args.calib).is_file():
            raise KittiFormatError(args.calib, "calibration file not found (one per sequence)")
        source = sources.SequenceSource(
            folder, args.calib, plane, args.calib_camera, args.fps or DEFAULT_FPS
        )
    return source


def output_folder(args: argparse.Namespace, source) -> Path:
    if args.out:
        return Path(args.out)
    name = Path(source.name).stem if stream_kind(args) != "camera" else f"camera{args.camera}"
    return Path(args.workdir) / "predict" / (name or "stream")


def load_detector(args: argparse.Namespace):
    """The :class:`~gac_jax.api.Detector3D` of the workdir's checkpoint (``--step``), or of
    converted weights (``--checkpoint``, with ``--config`` or the workdir's config)."""
    from gac_jax.api import Detector3D
    from gac_jax.trained.run_config import load_run_config

    model = {
        "runtime": args.runtime,
        "precision": args.precision,
        "threads": args.threads if args.runtime != "jax" else None,
        "score_threshold": args.score_threshold,
        "batch_size": args.batch_size,
        "export_dir": args.export,
        "int8": getattr(args, "int8", None),
        "requests": getattr(args, "network_requests", 1),
    }
    if args.checkpoint is not None:
        config = args.config or load_run_config(args.workdir)
        return Detector3D.from_weights(args.checkpoint, config, workdir=args.workdir, **model)
    return Detector3D.from_workdir(args.workdir, step=args.step, **model)


class _CtrlC:
    """SIGINT during the stream: first stop reading, then drop the frames in flight."""

    def __init__(self, pipeline):
        self.pipeline = pipeline
        self.count = 0

    def __call__(self, signum, frame) -> None:
        self.count += 1
        if self.count == 1:
            self.pipeline.stop()
            print(
                "Ctrl-C: reading stopped; finishing the frames in flight (Ctrl-C again drops them)",
                flush=True,
            )
        else:
            self.pipeline.abort()
            print("Ctrl-C again: dropping the frames in flight", flush=True)


def summary_lines(report, written_to: list[str], detector, threads: int) -> list[str]:
    from gac_jax.streams.rates import format_rates

    lines = [
        f"{report.written} frames -> {', '.join(written_to)}: {format_rates(report.rates)} "
        f"({detector.runtime} {detector.precision}, batch {detector.batch_size}, "
        f"{threads} CPU threads)"
    ]
    if report.written:
        busy = ", ".join(f"{k} {v:.0f} ms" for k, v in report.stage_ms.items())
        lines.append(f"per frame, each stage (they overlap; the slowest sets the rate): {busy}")
    if report.dropped_live:
        lines.append(
            f"{report.dropped_live} of {report.delivered} delivered frames dropped (the "
            "detector was busy; --realtime keeps the newest)"
        )
    if report.interrupted:
        line = f"interrupted: reading stopped after {report.delivered} frames; "
        if report.dropped_in_flight:
            line += f"{report.dropped_in_flight} frames in flight dropped"
            line += f", {report.finished_after_stop} finished"
        else:
            line += f"{report.finished_after_stop} frames in flight finished"
        lines.append(line)
    return lines


def stream_thread_budget(args: argparse.Namespace):
    """The stream's :class:`~gac_jax.streams.thread_budget.ThreadBudget` (``--threads``,
    ``--network-requests``), its OpenCV/BLAS part applied; ``args.threads`` set to the
    network's threads."""
    from gac_jax.streams.thread_budget import apply_host_threads, plan_thread_budget

    budget = plan_thread_budget(args.threads, args.network_requests)
    apply_host_threads(budget)
    if args.runtime != "jax":
        args.threads = budget.network_threads
    return budget


def run_stream(args: argparse.Namespace, threads: int) -> int:
    """Runs the stream command; returns the exit code (errors raise, see ``predict.main``)."""
    from gac_jax.evaluation.detection_pictures import detection_picture
    from gac_jax.streams import outputs, sources
    from gac_jax.streams.pipeline import StreamPipeline

    workdir = Path(args.workdir)
    if not workdir.is_dir():
        raise KittiFormatError(workdir, "workdir not found")
    if args.out_video is not None:
        outputs.check_video_path(args.out_video)
    source = open_source(args)
    budget = stream_thread_budget(args)
    try:
        detector = load_detector(args)
        out = output_folder(args, source)
        h, w = source.size
        fps = f"{source.fps:g} frames/s" if source.fps else "fps unknown"
        count = f", {source.expected_frames} frames" if source.expected_frames else ""
        print(f"{detector.weights}: {source.name} ({w}x{h}, {fps}{count}) -> {out}", flush=True)
        print(detector.precision_line(), flush=True)
        print(budget.describe(detector.runtime), flush=True)
        print(f"warm-up (compile): {detector.warmup():.1f} s", flush=True)
        if args.realtime and not source.live:  # a recording replayed as a live camera
            source = sources.PacedSource(source, source.fps or DEFAULT_FPS)
        video = None
        if not args.no_images:
            video = outputs.AnnotatedVideo(args.out_video or out / "annotated.mp4", source.fps)
        if args.jsonl:
            results = outputs.JsonlResults(out / "detections.jsonl")
        else:
            results = outputs.KittiResults(out / "data")
            earlier = len(list(results.folder.glob("*.txt"))) if results.folder.is_dir() else 0
            if earlier:
                print(
                    f"note: {results.folder} already holds {earlier} result files; this run "
                    "overwrites those of its frames and leaves the others",
                    flush=True,
                )
        pipeline = StreamPipeline(
            source,
            detector,
            video,
            results,
            realtime=args.realtime,
            batch_size=1 if args.realtime else args.batch_size,
            max_frames=args.max_frames,
            report_every=args.report_every,
            log=lambda line: print(line, flush=True),
            draw=functools.partial(detection_picture, scale=args.video_scale),
            network_requests=budget.requests,
        )
        handler = _CtrlC(pipeline)
        previous = signal.signal(signal.SIGINT, handler)
        try:
            report = pipeline.run()
        finally:
            signal.signal(signal.SIGINT, previous)
            for output in (video, results):
                if output is not None:
                    output.close()
    finally:
        source.close()
    written_to = [os.fspath(video.path)] if video is not None and video.frames else []
    written_to.append(os.fspath(getattr(results, "path", None) or results.folder))
    for line in summary_lines(report, written_to, detector, threads):
        print(line, flush=True)
    if report.error is not None:
        raise report.error
    return EXIT_INTERRUPTED if report.interrupted else 0


if __name__ == "__main__":
    sys.exit("use python -m gac_jax.cli.predict --video/--camera/--sequence/--clip")
