"""``python -m gac_jax.cli.predict --video/--camera/--sequence/--clip``: a stream through the
detector, written as an annotated video and per-frame results while it runs.

    python -m gac_jax.cli.predict --workdir W (--video FILE | --camera INDEX | --sequence DIR |
        --clip [N]) [--calib FILE] [--plane FILE] [--out DIR] [--out-video FILE] [--no-images]
        [--jsonl] [--realtime] [--fps F] [--max-frames N] [--report-every S]
        [--runtime R] [--precision P] [--batch-size B] [--threads T] [--score-threshold S]
        [--track] [--poses FILE] [--mcap FILE [--mcap-profile foxglove|ros2]]
        [--no-video] [--video-scale S] [--codec h264|mjpeg] [--network-requests N]

A video or camera needs ``--calib FILE`` (a KITTI calibration of any format,
:mod:`gac_jax.data.kitti_calib`, checked against the frame size); a ``--sequence`` in the
KITTI tracking layout (``ROOT/training/image_02/SSSS/``) finds ``ROOT/training/calib/SSSS.txt``
and the per-frame planes ``ROOT/training/planes/SSSS/<frame>.txt`` by itself, one in the KITTI
raw layout (``DATE/DATE_drive_NNNN_sync/image_02/data``, its ``image_02`` or the drive folder)
the day's ``DATE/calib_cam_to_cam.txt`` and the frame times ``image_02/timestamps.txt``
(:mod:`gac_jax.streams.sources`); ``--clip N`` runs on generated
driving clip N (made into the cache on first use, no download). Without a plane the config's
level camera is used. Writes ``OUT/annotated.mp4`` (camera view with 3D boxes | bird's-eye
view, at the input's fps) and ``OUT/data/<frame>.txt`` (or ``OUT/detections.jsonl`` with
``--jsonl``) as frames finish; prints frames/s and latency every few seconds and at the end.
Ctrl-C, SIGTERM and SIGHUP stop reading and finish the frames in flight (twice: drop them);
the video stays playable; exit 130 / 143 / 129 (:mod:`gac_jax.streams.stop_signals`). The
outputs are checked before the model is loaded (:mod:`gac_jax.streams.output_plan`: a folder
with an earlier run's results needs ``--overwrite``); a failed write ends the run with one
line and exit 1, keeping the frames written so far (:mod:`gac_jax.streams.outputs`).
``--track``: objects over frames (:mod:`gac_jax.cli.predict_track`). ``--mcap FILE``: an MCAP
recording of the frames, calibration, boxes, ground plane and poses for Foxglove
(``--mcap-profile ros2``: ROS 2 messages; :mod:`gac_jax.streams.mcap_recording`).

Throughput: ``--no-video`` writes the results only; ``--video-scale 0.5`` draws and encodes a
half-size annotated frame; ``.mp4`` is H.264 (``--codec mjpeg``: Motion JPEG) in a fragmented
MP4 that stays playable after any stop, encoded on a thread of its own
(:mod:`gac_jax.streams.video_encoder`); ``.avi`` / ``.mkv``: OpenCV's Motion JPEG writer,
playable after a clean close; ``--network-requests 2`` keeps two network calls in flight
(OpenVINO: two streams sharing the ``--threads``). The stream sizes its threads as one budget
(:mod:`gac_jax.streams.thread_budget`), printed.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import sys
from pathlib import Path

from gac_jax.cli import predict_recording, predict_track
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti_raw import RawDrive

STREAM_SOURCES = ("video", "camera", "sequence", "clip")
CLIP_SEQUENCES = 2  # sequences of the generated clip set (--clip 0, --clip 1)
CLIP_FRAMES = 60  # frames per sequence (6 s at 10 Hz; about 1 s per frame to generate)
EXIT_INTERRUPTED = 130
EXIT_WRITE_FAILED = 1  # an output could not be written (a full disk, a permission)
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
    group.add_argument(
        "--report-every", type=float, default=5.0, help="seconds per progress line (0: none)"
    )
    group.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in the output folder (deleted first; an "
        "earlier video is replaced when the new one is complete)",
    )
    predict_track.add_tracking_arguments(group)
    predict_recording.add_recording_arguments(group)
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
        "--codec",
        metavar="C",
        help="video codec of an .mp4: h264 (default; browsers play it) or mjpeg (Motion JPEG; "
        ".avi / .mkv are Motion JPEG)",
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
    predict_track.check_tracking_arguments(parser, args)
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
    recording_problem = predict_recording.option_problem(args)
    if recording_problem is not None:
        print(f"error: {recording_problem}", file=sys.stderr)
        raise SystemExit(2)
    if not given:
        stream_only = ["plane", "out_video", "jsonl", "realtime", "fps", "max_frames", "overwrite"]
        stream_only += ["mcap"]
        used = [
            f"--{k.replace('_', '-')}" for k in stream_only if getattr(args, k) not in (None, False)
        ]
        used += [
            f"--{k}"
            for k, v in (
                ("video-scale", args.video_scale != 1.0),
                ("network-requests", args.network_requests != 1),
                ("codec", args.codec is not None),
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
    if args.network_requests > 1 and args.runtime in (None, "jax"):
        parser.error("--network-requests applies to --runtime openvino/onnxruntime")
    for problem in numeric_problems(args):  # one line, as the other input errors
        print(f"error: {problem}", file=sys.stderr)
        raise SystemExit(2)
    try:  # the outputs, in a fraction of a second: before JAX is even imported
        if not Path(args.workdir).is_dir():
            raise KittiFormatError(args.workdir, "workdir not found")
        plan_outputs(args, clear=False)
    except KittiFormatError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    from gac_jax.streams.stop_signals import record_early

    record_early()  # from here on a stop signal ends the start-up cleanly


def numeric_problems(args: argparse.Namespace) -> list[str]:
    """What is wrong with the numeric options of a stream (checked before anything opens)."""
    checks = [
        ("--camera", args.camera, lambda v: v >= 0, "must be a device index >= 0"),
        ("--clip", args.clip, lambda v: v >= 0, "N must be >= 0"),
        ("--fps", args.fps, lambda v: math.isfinite(v) and v > 0, "must be a number > 0"),
        ("--max-frames", args.max_frames, lambda v: v >= 1, "must be >= 1"),
        (
            "--report-every",
            args.report_every,
            lambda v: math.isfinite(v) and v >= 0,
            "must be seconds >= 0 (0: no progress lines)",
        ),
        ("--step", args.step, lambda v: v >= 0, "must be a checkpoint step >= 0"),
        ("--score-threshold", args.score_threshold, math.isfinite, "must be a finite number"),
        ("--video-scale", args.video_scale, lambda v: 0 < v <= 1, "must be in (0, 1]"),
        ("--network-requests", args.network_requests, lambda v: v >= 1, "must be >= 1"),
    ]
    return [
        f"{flag} {problem}, got {value:g}"
        for flag, value, valid, problem in checks
        if value is not None and not valid(value)
    ]


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


def open_source(args: argparse.Namespace, decode_threads: int | None = None):
    """The frame source the arguments name (checks input and calibration; nothing loaded);
    a video decodes with ``decode_threads`` (the stream's thread budget)."""
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
            source = sources.VideoSource(args.video, P2, args.calib, plane, decode_threads)
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


def output_folder(args: argparse.Namespace) -> Path:
    """``--out``, else ``W/predict/<input name>`` (``camera<N>``, clip ``000N``)."""
    if args.out:
        return Path(args.out)
    kind = stream_kind(args)
    if kind == "camera":
        name = f"camera{args.camera}"
    elif kind == "clip":
        name = f"{args.clip:04d}"  # the sequence folder of the generated set
    elif kind == "sequence" and (raw := RawDrive.locate(args.sequence, args.calib_camera)):
        name = raw.drive.name  # not the "data" folder of its frames
    else:
        name = Path(args.video if kind == "video" else args.sequence).stem
    return Path(args.workdir) / "predict" / (name or "stream")


def plan_outputs(args: argparse.Namespace, source=None, clear: bool = True):
    """The checked output paths (:func:`gac_jax.streams.output_plan.plan_outputs`; ``clear``:
    deletes an earlier run's results with ``--overwrite``) and, given the opened ``source``,
    the free space for a few seconds of video; before any model is loaded."""
    from gac_jax.streams import output_plan

    out = output_folder(args)
    video = None
    if not args.no_images:
        video = args.out_video or out / output_plan.VIDEO_NAME
    inputs = [p for p in (args.video, args.calib, args.plane) if p is not None]
    plan = output_plan.plan_outputs(
        out, video, args.jsonl, inputs, args.overwrite, clear, track=bool(args.track)
    )
    if args.mcap is not None:
        predict_recording.check_mcap_output(Path(args.mcap), inputs, args.overwrite, clear)
    if source is not None:
        h, w = source.size
        output_plan.check_free_space(plan, h * (w + h), source.fps)
    return plan


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
    if report.write_error is not None:
        lines.append(
            f"stopped: writing failed after {report.written} frames; those are kept "
            f"({report.dropped_in_flight} frames in flight dropped)"
        )
    elif report.interrupted:
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
    """Runs the stream command; returns the exit code (errors raise, see ``predict.main``):
    0 at the input's end, 1 when writing failed, 128 + N after stop signal N
    (:mod:`gac_jax.streams.stop_signals`)."""
    from gac_jax.streams.stop_signals import StartupInterrupted, StopSignals

    with StopSignals(log=lambda line: print(line, flush=True)) as signals:
        try:
            return _run_stream(args, threads, signals)
        except StartupInterrupted as e:
            print(f"interrupted: {e}; nothing was written", file=sys.stderr, flush=True)
            sys.stdout.flush()
            # JAX's threads may be mid-compile: leave without the interpreter's teardown
            os._exit(signals.exit_status or EXIT_INTERRUPTED)


def _run_stream(args: argparse.Namespace, threads: int, signals) -> int:
    import time

    from gac_jax.data.io_errors import error_line
    from gac_jax.evaluation.detection_pictures import detection_picture
    from gac_jax.streams import outputs, sources
    from gac_jax.streams.pipeline import StreamPipeline

    t_start = time.perf_counter()
    workdir = Path(args.workdir)
    if not workdir.is_dir():
        raise KittiFormatError(workdir, "workdir not found")
    if args.out_video is not None:
        outputs.check_video_path(args.out_video, args.codec)
    budget = stream_thread_budget(args)
    source = open_source(args, budget.host_threads)
    video = results = recorder = None
    try:
        plan = plan_outputs(args, source)
        for line in getattr(source, "found", ()):  # what a sequence's layout gave
            print(line, flush=True)
        log = functools.partial(print, flush=True)
        poses = predict_track.stream_poses(args, source, log) if args.track or args.mcap else None
        signals.check()
        t_load = time.perf_counter()
        detector = load_detector(args)
        load_s = time.perf_counter() - t_load
        signals.check()
        h, w = source.size
        fps = f"{source.fps:g} frames/s" if source.fps else "fps unknown"
        count = f", {source.expected_frames} frames" if source.expected_frames else ""
        print(
            f"{detector.weights}: {source.name} ({w}x{h}, {fps}{count}) -> {plan.folder}",
            flush=True,
        )
        print(detector.precision_line(), flush=True)
        print(budget.describe(detector.runtime), flush=True)
        warmup_s = detector.warmup()
        signals.check()
        print(
            f"start-up: {time.perf_counter() - t_start:.1f} s (model {load_s:.1f} s, "
            f"warm-up/compile {warmup_s:.1f} s; not counted in the rates)",
            flush=True,
        )
        if args.realtime and not source.live:  # a recording replayed as a live camera
            source = sources.PacedSource(source, source.fps or DEFAULT_FPS)
        if plan.video is not None:
            video = outputs.AnnotatedVideo(plan.video, source.fps, args.codec)
        if args.mcap is not None:
            recorder = predict_recording.open_recording(args, detector, source, poses)
        track = None
        if args.track:
            fps = source.fps or DEFAULT_FPS
            results, track = predict_track.tracking_outputs(
                args, source, plan, detector, poses, fps
            )
        elif plan.jsonl:
            results = outputs.JsonlResults(plan.results)
        else:
            results = outputs.KittiResults(plan.results)
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
            track=track,
            draw=functools.partial(detection_picture, scale=args.video_scale),
            network_requests=budget.requests,
            recorder=recorder,
        )
        signals.check()
        signals.pipeline = pipeline
        try:
            report = pipeline.run()
        finally:
            complete = pipeline.write_error is None
            kept, close_error = outputs.close_outputs(video, [results, recorder], complete)
            kept = [os.fspath(where) for where in kept]
    except BaseException:
        for output in (video, results, recorder):  # start-up failed: nothing of this run is kept
            if output is not None and getattr(output, "partial", None) is not None:
                with contextlib.suppress(OSError):
                    output.close(False)
        raise
    finally:
        source.close()
    for line in summary_lines(report, kept or ["nothing"], detector, threads):
        print(line, flush=True)
    failure = report.write_error or close_error
    if failure is not None:
        text = error_line(failure) if isinstance(failure, OSError) else str(failure)
        kept_line = f"; kept: {', '.join(kept)}" if kept else ""
        print(f"error: {text}{kept_line}", file=sys.stderr, flush=True)
        return EXIT_WRITE_FAILED
    if report.error is not None:
        raise report.error
    if signals.signum is not None:
        return signals.exit_status
    return EXIT_INTERRUPTED if report.interrupted else 0


if __name__ == "__main__":
    sys.exit("use python -m gac_jax.cli.predict --video/--camera/--sequence/--clip")
