"""``--track`` of the stream command (:mod:`gac_jax.cli.predict_stream`): objects over time.

    python -m gac_jax.cli.predict --workdir W (--video F | --camera I | --sequence D | --clip [N])
        --track [--poses FILE] [--jsonl] [--realtime] ...

Each frame's detections go through :class:`gac_jax.api.Tracker3D` (the workdir config's
``track`` section) before drawing and writing: the annotated video shows track ids, trails
and velocity arrows on the camera and bird's-eye views, and the results are
``OUT/tracking/SSSS.txt`` (KITTI tracking result format, one line per object per frame;
``SSSS`` the sequence's folder name in the KITTI tracking layout, else ``0000``) or, with
``--jsonl``, ``OUT/tracks.jsonl`` (one JSON object per frame). Ego poses (tracks in the world
frame, velocities over the ground) come from ``--poses FILE`` (KITTI odometry format, one line
per frame) or else, found by themselves and said in a printed line: a KITTI tracking layout
sequence's (``--clip`` too) ``poses/SSSS.txt``, else its ``oxts/SSSS.txt``; a KITTI raw
drive's ``oxts/data/<frame>.txt``. OXTS packets become camera poses as the KITTI devkit makes
them (:mod:`gac_jax.data.kitti_oxts`), through the sequence's calibration. They are checked
against the frames actually read (a video's header does not know its frame count for sure):
the first frame without a pose stops the stream with one line naming the file (a sequence,
whose images are counted, is checked before the model loads); poses left over at the end are
a warning.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from gac_jax.data.files import KittiFormatError

DEFAULT_SEQUENCE = "0000"


def add_tracking_arguments(group) -> None:
    group.add_argument(
        "--track",
        action="store_true",
        help="track objects over frames: ids, trails and velocities drawn; results in "
        "OUT/tracking/SSSS.txt (KITTI tracking format) or OUT/tracks.jsonl (--jsonl)",
    )
    group.add_argument(
        "--poses",
        metavar="FILE",
        help="with --track or --mcap: ego poses, one line per frame (KITTI odometry: camera -> "
        "first frame); a tracking-layout sequence's poses/SSSS.txt or oxts/SSSS.txt and a KITTI "
        "raw drive's oxts/ are found by themselves",
    )


def check_tracking_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.poses is not None and not (args.track or args.mcap):
        parser.error("--poses goes with --track or --mcap")
    if args.track and args.input is not None:
        parser.error("--track applies to --video/--camera/--sequence/--clip only")
    if args.poses is not None and args.camera is not None:
        parser.error("--poses: a live camera's frames have no pose file (track without it)")


def sequence_name(source) -> str:
    """``SSSS`` of a source in the KITTI tracking layout, else :data:`DEFAULT_SEQUENCE`."""
    from gac_jax.data.kitti_tracking import KittiTrackingLayout

    folder = getattr(getattr(source, "source", source), "images", None)  # a paced one's too
    if folder:
        located = KittiTrackingLayout.locate(Path(folder[0]).parent)
        if located is not None:
            return located[1]
    return DEFAULT_SEQUENCE


def layout_poses(source) -> tuple | None:
    """``((N, 3, 4) poses, the file they came from, a line saying so)`` of a sequence source's
    frames found by its layout (module docstring), or None."""
    from gac_jax.data.kitti_oxts import camera_poses, read_oxts
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.tracking import read_pose_file

    images = getattr(source, "images", None)
    if not images:
        return None
    located = KittiTrackingLayout.locate(Path(images[0]).parent)
    if located is not None:
        layout, sequence = located
        if layout.poses(sequence).is_file():
            path = layout.poses(sequence)
            return read_pose_file(path, source.expected_frames), path, f"poses: {path}"
        if layout.oxts(sequence).is_file():
            path = layout.oxts(sequence)
            packets = read_oxts(path)
            if not all(p.stem.isdigit() for p in images):
                raise KittiFormatError(path, "frame names are not frame numbers: no line is theirs")
            frames = [int(p.stem) for p in images]
            if max(frames) >= len(packets):
                raise KittiFormatError(
                    path, f"{len(packets)} OXTS packets for frames up to {max(frames)}"
                )
            return camera_poses(packets[frames], source.calibration), path, oxts_line(path)
    raw = getattr(getattr(source, "files", None), "raw", None)
    if raw is not None and raw.oxts_dir.is_dir():
        poses = raw.poses([p.stem for p in images], source.calibration)
        return poses, raw.oxts_dir, oxts_line(raw.oxts_dir)
    return None


def oxts_line(path) -> str:
    return f"poses: {path} (OXTS -> camera poses as the KITTI devkit: IMU -> velodyne -> camera)"


def stream_poses(args: argparse.Namespace, source, log=print):
    """``(path, (N, 3, 4) poses)`` of the stream's frames, or None: ``--poses``, else those the
    sequence's layout holds (:func:`layout_poses`; ``log`` gets a line saying which). Too few
    for a sequence's images is refused here, a video's are checked as its frames come."""
    from gac_jax.tracking import read_pose_file

    path = args.poses
    if path is None:
        found = layout_poses(getattr(source, "source", source))
        if found is None:
            return None
        log(found[2])
        return os.fspath(found[1]), found[0]
    if not Path(path).is_file():
        raise KittiFormatError(path, "poses file not found")
    poses = read_pose_file(path)
    images = getattr(getattr(source, "source", source), "images", None)  # counted, not guessed
    if images is not None and len(poses) < len(images):
        raise KittiFormatError(
            path, f"{len(poses)} poses for {len(images)} frames (one line of 12 numbers per frame)"
        )
    return os.fspath(path), poses


def tracking_outputs(args: argparse.Namespace, source, plan, detector, poses, fps: float):
    """``(results writer, tracking stage)`` of ``--track`` (``plan``: the stream's checked
    :class:`~gac_jax.streams.output_plan.OutputPlan`: ``tracks.jsonl`` or ``tracking/``;
    ``poses``: :func:`stream_poses`)."""
    from gac_jax.api.tracker import Tracker3D
    from gac_jax.streams.outputs import JsonlResults
    from gac_jax.streams.tracking import KittiTrackingResults, TrackingStage

    tracker = Tracker3D(detector.config)
    if plan.jsonl:
        results = JsonlResults(plan.results)
    else:
        results = KittiTrackingResults(plan.results, sequence_name(source))
    scale = getattr(args, "video_scale", 1.0)
    name, poses = poses if poses is not None else ("poses", None)
    return results, TrackingStage(tracker, fps, args.realtime, poses, scale, name)
