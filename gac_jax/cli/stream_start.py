"""What a stream command does before JAX loads: everything that can refuse the run.

In a fraction of a second, with one line and exit 2 for anything wrong (``error: <file or
option>: <problem>``, never a usage dump or a traceback), :func:`start_stream`:

1. range-checks every numeric option (:func:`numeric_problems`);
2. opens the input (a video's first frame is decoded, a camera's first frame taken, a
   sequence's first image read) and checks the calibration against it;
3. resolves and checks the outputs and the free space they need
   (:mod:`gac_jax.streams.output_plan`), reads the pose file (``--track``);
4. claims the outputs: folders created and locked for this stream, what a killed
   ``--overwrite`` run moved aside given back, an earlier run's results refused unless
   ``--overwrite``.

Only then do the model, JAX and the runtimes load (:func:`gac_jax.cli.predict_stream.run_stream`).
From step 4 on a stop signal is recorded and ends the start-up cleanly; before it, nothing
has been written, and a signal ends the command at once with one line
(:func:`gac_jax.streams.stop_signals.exit_during_start`).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
from pathlib import Path

from gac_jax.cli import predict_recording, predict_track
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti_raw import RawDrive
from gac_jax.streams.sources import MAX_CAMERA

CLIP_SEQUENCES = 2  # sequences of the generated clip set (--clip 0, --clip 1)
CLIP_FRAMES = 60  # frames per sequence (6 s at 10 Hz; about 1 s per frame to generate)
DEFAULT_FPS = 10.0  # a sequence's rate (KITTI records at 10 Hz), or a source's without one
FPS_RANGE = (0.1, 1000.0)
VIDEO_SCALE_RANGE = (0.05, 4.0)
MAX_NETWORK_REQUESTS = 16


@dataclasses.dataclass
class StreamStart:
    """What :func:`start_stream` opened and checked: the ``source``, the output ``plan``
    (:class:`~gac_jax.streams.output_plan.OutputPlan`), the ``poses`` (``(file, (N, 3, 4))``
    or None), the thread ``budget`` and the ``notes`` to print."""

    source: object
    plan: object
    poses: tuple | None
    budget: object
    notes: list[str]


def _between(lo: float, hi: float):
    return lambda v: math.isfinite(v) and lo <= v <= hi


def numeric_problems(args: argparse.Namespace) -> list[str]:
    """What is wrong with the numeric options (checked before anything opens)."""
    checks = [
        ("--batch-size", "batch_size", lambda v: v >= 1, "must be >= 1"),
        ("--threads", "threads", lambda v: v >= 1, "must be >= 1"),
        ("--step", "step", lambda v: v >= 0, "must be a checkpoint step >= 0"),
        ("--score-threshold", "score_threshold", math.isfinite, "must be a finite number"),
        (
            "--camera",
            "camera",
            _between(0, MAX_CAMERA),
            f"must be a device index 0 to {MAX_CAMERA}",
        ),
        ("--clip", "clip", lambda v: v >= 0, "N must be >= 0"),
        ("--fps", "fps", _between(*FPS_RANGE), "must be 0.1 to 1000 frames/s"),
        ("--max-frames", "max_frames", lambda v: v >= 1, "must be >= 1"),
        (
            "--report-every",
            "report_every",
            lambda v: math.isfinite(v) and v >= 0,
            "must be seconds >= 0 (0: no progress lines)",
        ),
        ("--video-scale", "video_scale", _between(*VIDEO_SCALE_RANGE), "must be 0.05 to 4"),
        (
            "--network-requests",
            "network_requests",
            _between(1, MAX_NETWORK_REQUESTS),
            f"must be 1 to {MAX_NETWORK_REQUESTS}",
        ),
    ]
    problems = []
    for flag, name, valid, problem in checks:
        value = getattr(args, name, None)
        if value is not None and not valid(value):
            shown = f"{value:g}" if isinstance(value, float) else str(value)
            problems.append(f"{flag} {problem}, got {shown}")
    return problems


def refuse(text: str) -> None:
    """One ``error:`` line, exit 2."""
    print(f"error: {text}", file=sys.stderr, flush=True)
    raise SystemExit(2)


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


def stream_kind(args: argparse.Namespace) -> str | None:
    """Which stream source the arguments ask for (None: image input)."""
    given = [k for k in ("video", "camera", "sequence", "clip") if getattr(args, k) is not None]
    return given[0] if given else None


def open_source(args: argparse.Namespace, decode_threads: int | None = None):
    """The frame source the arguments name (checks input and calibration; nothing loaded);
    a video decodes with ``decode_threads`` (the stream's thread budget)."""
    from gac_jax.data.kitti import read_plane
    from gac_jax.streams import sources
    from gac_jax.streams.input_files import check_input_file

    sources.quiet_video_backend()
    kind = stream_kind(args)
    plane = read_plane(args.plane) if args.plane else None
    if args.calib is not None:
        check_input_file(args.calib, "calibration")
    if kind in ("video", "camera"):
        name = args.video if kind == "video" else f"camera {args.camera}"
        if args.calib is None:
            raise KittiFormatError(
                name, "no calibration: pass --calib FILE (a KITTI calibration with a P2 line)"
            )
        P2 = sources.load_projection(args.calib, args.calib_camera)
        if kind == "video":
            source = sources.VideoSource(args.video, P2, args.calib, plane, decode_threads)
        else:
            source = sources.CameraSource(args.camera, P2, args.calib, plane)
        if args.fps is not None:
            source.fps = args.fps
        return source
    folder = clip_sequence(args.clip) if kind == "clip" else Path(args.sequence)
    return sources.SequenceSource(
        folder, args.calib, plane, args.calib_camera, args.fps or DEFAULT_FPS
    )


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


def plan_outputs(args: argparse.Namespace, source):
    """The checked output paths (:func:`gac_jax.streams.output_plan.plan_outputs`) and the
    free space for them (the annotated picture of ``source``'s frames at ``--video-scale``)."""
    from gac_jax.streams import output_plan

    out = output_folder(args)
    video = None
    if not args.no_images:
        video = args.out_video or out / output_plan.VIDEO_NAME
    inputs = [p for p in (args.video, args.calib, args.plane) if p is not None]
    plan = output_plan.plan_outputs(out, video, args.jsonl, inputs, track=bool(args.track))
    if args.mcap is not None:  # (an earlier recording is replaced only by a complete one)
        predict_recording.check_mcap_output(Path(args.mcap), inputs, args.overwrite, False)
    h, w = (round(n * args.video_scale) for n in source.size)
    output_plan.check_free_space(plan, h * (w + h), source.fps)
    return plan


def start_stream(args: argparse.Namespace) -> StreamStart:
    """Steps 2 to 4 of the module doc.

    Raises:
      KittiFormatError: a bad input, calibration, pose file or output (one line).
      OutputBusyError: another stream writes to an output.
      OSError: an output folder or its lock cannot be made (naming it).
    """
    from gac_jax.streams import output_plan
    from gac_jax.streams.stop_signals import forget_early, record_early
    from gac_jax.streams.thread_budget import plan_thread_budget

    source = None
    try:
        if not Path(args.workdir).is_dir():
            raise KittiFormatError(args.workdir, "workdir not found")
        budget = plan_thread_budget(args.threads, args.network_requests)
        source = open_source(args, budget.host_threads)
        plan = plan_outputs(args, source)
        for line in getattr(source, "found", ()):  # what a sequence's layout gave
            print(line, flush=True)
        log = functools.partial(print, flush=True)
        poses = predict_track.stream_poses(args, source, log) if args.track or args.mcap else None
        record_early()  # from here on a stop signal ends the start-up cleanly
        notes = output_plan.claim_outputs(plan, args.overwrite)
    except BaseException:
        forget_early()
        if source is not None:
            source.close()
        raise
    return StreamStart(source, plan, poses, budget, notes)
