"""``--mcap`` and ``--codec`` of the stream command (:mod:`gac_jax.cli.predict_stream`): what
a stream records besides its results.

    python -m gac_jax.cli.predict --workdir W (--video F | --camera I | --sequence D | --clip [N])
        [--mcap FILE [--mcap-profile foxglove|ros2]] [--poses FILE] [--codec h264|mjpeg] ...

``--mcap FILE``: an MCAP recording of every written frame (JPEG), its calibration, the 3D boxes
(tracks with ``--track``), the ground plane and, with poses (``--poses``, or a tracking-layout
sequence's own), the camera's transforms (:mod:`gac_jax.streams.mcap_recording`); profile
``foxglove`` (protobuf, the default) or ``ros2`` (CDR messages rosbag2 replays). ``--codec``:
the annotated ``.mp4``'s codec, ``h264`` (default) or ``mjpeg``. Bad values are one line and
exit 2 before anything is loaded.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gac_jax.data.files import KittiFormatError


def add_recording_arguments(group) -> None:
    group.add_argument(
        "--mcap",
        metavar="FILE",
        help="also an MCAP recording (frames, calibration, 3D boxes, ground plane, poses) for "
        "Foxglove / ROS 2",
    )
    group.add_argument(
        "--mcap-profile",
        metavar="PROFILE",
        help="with --mcap: foxglove (protobuf, the default) or ros2 (CDR messages rosbag2 plays)",
    )


def option_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with ``--codec``, ``--mcap`` and ``--mcap-profile`` (one line), or None."""
    from gac_jax.streams import mcap_recording, outputs, video_encoder

    if args.codec is not None and args.codec not in video_encoder.CODECS:
        return (
            f"--codec: unknown codec {args.codec!r} (use one of {', '.join(video_encoder.CODECS)})"
        )
    if args.mcap_profile is not None and args.mcap is None:
        return "--mcap-profile goes with --mcap FILE (the recording it sets the messages of)"
    try:
        if args.out_video is not None and not Path(args.out_video).is_dir():
            outputs.check_video_path(args.out_video, args.codec)  # a folder: the plan says
        if args.mcap is not None:
            mcap_recording.check_mcap_path(args.mcap, args.mcap_profile or "foxglove")
    except KittiFormatError as e:
        return str(e)
    return None


def check_mcap_output(path: Path, inputs: list, overwrite: bool, clear: bool) -> None:
    """``--mcap FILE``: not an input; an earlier recording there (or what a failed or killed
    one left) needs ``--overwrite`` (the leftovers are then deleted when ``clear``; an earlier
    recording is replaced when the new one is complete)."""
    from gac_jax.streams.outputs import incomplete_path, partial_path

    path = path.absolute()
    for source in inputs:
        if Path(source).absolute() == path:
            raise KittiFormatError(path, "is an input; choose another --mcap")
    earlier = [p for p in (path, incomplete_path(path), partial_path(path)) if p.is_file()]
    if earlier and not overwrite:
        raise KittiFormatError(
            path, "holds an earlier recording; pass --overwrite to replace it, or choose another"
        )
    for leftover in earlier[1:] if clear else []:
        leftover.unlink(missing_ok=True)
    if earlier and earlier[0] != path and clear:
        earlier[0].unlink(missing_ok=True)


def open_recording(args: argparse.Namespace, detector, source, poses, default_fps: float = 10.0):
    """The ``--mcap`` recorder of the stream (frames without a plane get the detector's
    level camera; ``poses``: ``(path, (N, 3, 4) poses)`` of
    :func:`~gac_jax.cli.predict_track.stream_poses`, or None)."""
    from gac_jax.streams.mcap_recording import McapRecording, McapResults

    height = float(detector.config.model.gac.camera_height)
    recording = McapRecording(
        args.mcap, args.mcap_profile or "foxglove", default_plane=(0.0, -1.0, 0.0, height)
    )
    return McapResults(
        recording, source.fps or default_fps, args.realtime, None if poses is None else poses[1]
    )
