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
view, each frame at its own time) and ``OUT/data/<frame>.txt`` (or ``OUT/detections.jsonl`` with
``--jsonl``) as frames finish; prints frames/s and latency every few seconds and at the end.
Ctrl-C, SIGTERM and SIGHUP stop reading and finish the frames in flight (twice: drop them);
the video stays playable; exit 130 / 143 / 129 (:mod:`gac_jax.streams.stop_signals`).
Everything that can refuse the run is checked before JAX loads
(:mod:`gac_jax.cli.stream_start`: numbers, input, calibration, outputs, free space, the output
folder's lock, an earlier run's results, which need ``--overwrite``). A damaged frame is
skipped with a warning (:mod:`gac_jax.streams.damaged_frames`); a failed write ends the run
with one line and exit 1, keeping the frames written so far (:mod:`gac_jax.streams.outputs`);
what the command prints never stops it (:mod:`gac_jax.cli.console`).
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
import os
import sys

from gac_jax.cli import predict_recording, predict_track
from gac_jax.cli.stream_start import (
    CLIP_FRAMES,
    CLIP_SEQUENCES,
    DEFAULT_FPS,
    StreamStart,
)

STREAM_SOURCES = ("video", "camera", "sequence", "clip")
EXIT_INTERRUPTED = 130
EXIT_WRITE_FAILED = 1  # an output could not be written (a full disk, a permission)


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
    group.add_argument(
        "--fps",
        type=float,
        help="frame rate of a sequence (default 10); for a video or camera the rate its "
        "frames without a timestamp are taken to have and, with --realtime, the pace "
        "(0.1 to 1000)",
    )
    group.add_argument("--max-frames", type=int, help="stop after this many frames")
    group.add_argument(
        "--report-every", type=float, default=5.0, help="seconds per progress line (0: none)"
    )
    group.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the results of an earlier run in the output folder (moved aside, deleted "
        "once this run has written a frame, given back if it ends before; an earlier video is "
        "replaced when the new one is complete)",
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
        help="annotated video at S times the input's size (0.05 to 4; below 1: less to draw "
        "and encode)",
    )
    group.add_argument(
        "--network-requests",
        type=int,
        default=1,
        metavar="N",
        help="network calls in flight, 1 to 16 (openvino/onnxruntime; 2: the next frame's "
        "network runs while this one is finished)",
    )
    group.add_argument(
        "--codec",
        metavar="C",
        help="video codec of an .mp4: h264 (default; browsers play it) or mjpeg (Motion JPEG; "
        ".avi / .mkv are Motion JPEG)",
    )


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
        parser.error(recording_problem)
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


def summary_lines(report, written_to: list[str], detector, threads: int, source=None) -> list[str]:
    """The lines after a stream (``source``: its damaged frames are told)."""
    from gac_jax.streams.rates import format_rates

    lines = [
        f"{report.written} frames -> {', '.join(written_to)}: {format_rates(report.rates)} "
        f"({detector.runtime} {detector.precision}, batch {detector.batch_size}, "
        f"{threads} CPU threads)"
    ]
    if report.written:
        busy = ", ".join(f"{k} {v:.0f} ms" for k, v in report.stage_ms.items())
        lines.append(f"per frame, each stage (they overlap; the slowest sets the rate): {busy}")
    damaged = getattr(source, "damaged", None)
    if damaged is not None and damaged.summary():
        lines.append(damaged.summary())
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


def apply_thread_budget(args: argparse.Namespace, budget) -> None:
    """The OpenCV/BLAS part of the stream's :class:`~gac_jax.streams.thread_budget.ThreadBudget`
    applied; ``args.threads`` set to the network's threads."""
    from gac_jax.streams.thread_budget import apply_host_threads

    apply_host_threads(budget)
    if args.runtime != "jax":
        args.threads = budget.network_threads


def say(line: str) -> None:
    print(line, flush=True)


def run_stream(args: argparse.Namespace, threads: int, start: StreamStart) -> int:
    """Runs the stream command on what :func:`gac_jax.cli.stream_start.start_stream` opened
    and claimed; returns the exit code (errors raise, see ``predict.main``): 0 at the input's
    end, 1 when writing failed, 128 + N after stop signal N
    (:mod:`gac_jax.streams.stop_signals`). The outputs' locks are given back at the end."""
    from gac_jax.streams import output_lock, stop_signals

    stop_signals.at_exit(output_lock.release_all)
    try:
        with stop_signals.StopSignals(log=say) as signals:
            try:
                return _run_stream(args, threads, start, signals)
            except stop_signals.StartupInterrupted as e:
                print(f"interrupted: {e}; nothing was written", file=sys.stderr, flush=True)
                sys.stdout.flush()
                # JAX's threads may be mid-compile: leave without the interpreter's teardown
                stop_signals.exit_now(signals.exit_status or EXIT_INTERRUPTED)
    finally:
        output_lock.release_all()
        stop_signals.forget_at_exit()


def _open_outputs(args, start: StreamStart, source, detector):
    """``(video, results, tracking stage, MCAP recorder)`` writers of the stream."""
    from gac_jax.streams import outputs

    plan, video, track = start.plan, None, None
    if plan.video is not None:
        video = outputs.AnnotatedVideo(plan.video, source.fps, args.codec)
    if args.track:
        fps = source.fps or DEFAULT_FPS
        results, track = predict_track.tracking_outputs(
            args, source, plan, detector, start.poses, fps
        )
    elif plan.jsonl:
        results = outputs.JsonlResults(plan.results)
    else:
        results = outputs.KittiResults(plan.results)
    recorder = None
    if args.mcap is not None:
        recorder = predict_recording.open_recording(args, detector, source, start.poses)
    return video, results, track, recorder


def _run_stream(args: argparse.Namespace, threads: int, start: StreamStart, signals) -> int:
    import time

    from gac_jax.data.io_errors import error_line
    from gac_jax.drawing.detection_pictures import detection_picture
    from gac_jax.streams import earlier_results, outputs, sources, stop_signals
    from gac_jax.streams.pipeline import StreamPipeline

    t_start = time.perf_counter()
    source, plan, budget = start.source, start.plan, start.budget
    for line in start.notes:
        say(line)
    apply_thread_budget(args, budget)
    video = results = recorder = aside = None
    try:
        signals.check()
        t_load = time.perf_counter()
        detector = load_detector(args)
        load_s = time.perf_counter() - t_load
        signals.check()
        h, w = source.size
        fps = f"{source.fps:g} frames/s" if source.fps else "fps unknown"
        count = f", {source.expected_frames} frames" if source.expected_frames else ""
        say(f"{detector.weights}: {source.name} ({w}x{h}, {fps}{count}) -> {plan.folder}")
        say(detector.threshold_source)
        say(detector.precision_line())
        say(budget.describe(detector.runtime))
        warmup_s = detector.warmup()
        signals.check()
        say(
            f"start-up: {time.perf_counter() - t_start:.1f} s (model {load_s:.1f} s, "
            f"warm-up/compile {warmup_s:.1f} s; not counted in the rates)"
        )
        if args.realtime and not source.live:  # a recording replayed as a live camera
            source = sources.PacedSource(source, source.fps or DEFAULT_FPS)
        if args.overwrite:  # deleted once the first frame is written, else given back
            aside = earlier_results.set_aside(plan)
            stop_signals.at_exit(aside.restore)
        video, results, track, recorder = _open_outputs(args, start, source, detector)
        pipeline = StreamPipeline(
            source,
            detector,
            video,
            results,
            realtime=args.realtime,
            batch_size=1 if args.realtime else args.batch_size,
            max_frames=args.max_frames,
            report_every=args.report_every,
            log=say,
            track=track,
            draw=functools.partial(detection_picture, scale=args.video_scale),
            network_requests=budget.requests,
            on_first_frame=None if aside is None else aside.discard,
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
        if aside is not None:
            aside.restore()
        raise
    finally:
        source.close()
    if aside is not None and report.written == 0:
        aside.restore()  # not one frame replaced them
    for line in summary_lines(report, kept or ["nothing"], detector, threads, source):
        say(line)
    cut_short = args.max_frames is not None and report.delivered >= args.max_frames
    if track is not None and not (report.interrupted or report.error or cut_short):
        unused = track.unused_poses(report.delivered + report.damaged)
        if unused:
            print(unused, file=sys.stderr, flush=True)
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
