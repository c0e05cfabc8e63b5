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
per frame) or, for a sequence in the KITTI tracking layout (``--clip`` too), its
``poses/SSSS.txt``. They are checked against the frames actually read (a video's header does not
know its frame count for sure): the first frame without a pose stops the stream with one line
naming the file (a sequence, whose images are counted, is checked before the model loads);
poses left over at the end are a warning.
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
        help="with --track: ego poses, one line per frame (KITTI odometry: camera -> first "
        "frame); a tracking-layout sequence's poses/SSSS.txt is found by itself",
    )


def check_tracking_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if args.poses is not None and not args.track:
        parser.error("--poses goes with --track")
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


def stream_poses(args: argparse.Namespace, source):
    """``(path, (N, 3, 4) poses)`` of the stream's frames, or None; too few for a sequence's
    images is refused here, a video's are checked as its frames come."""
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.tracking import read_pose_file

    path = args.poses
    if path is None and getattr(source, "images", None):
        located = KittiTrackingLayout.locate(Path(source.images[0]).parent)
        if located is not None and located[0].poses(located[1]).is_file():
            path = located[0].poses(located[1])
    if path is None:
        return None
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
