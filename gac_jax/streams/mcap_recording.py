"""An MCAP recording of detections or tracks, for Foxglove and ROS 2 (``--mcap FILE``, or
:class:`McapRecording` in a loop of :class:`~gac_jax.api.Detector3D` /
:class:`~gac_jax.api.Tracker3D` results).

Written with the ``mcap`` library: protobuf messages of ``foxglove-schemas-protobuf``
(profile ``foxglove``) or CDR messages (profile ``ros2``, what rosbag2's MCAP storage plugin
reads and ``ros2 bag play`` replays) of the definitions in :mod:`~gac_jax.streams.ros2_msgdefs`,
serialised by ``mcap-ros2-support`` (no serialiser of our own). One message per frame on each
topic (:data:`TOPICS`), stamped with the frame's time:

===================  ==============================  ======================================
what                 ``foxglove``                    ``ros2``
===================  ==============================  ======================================
the frame (JPEG)     ``foxglove.CompressedImage``    ``sensor_msgs/msg/CompressedImage``
calibration (P2)     ``foxglove.CameraCalibration``  ``sensor_msgs/msg/CameraInfo``
3D boxes             ``foxglove.SceneUpdate``        ``foxglove_msgs/msg/SceneUpdate`` and
                                                     ``vision_msgs/msg/Detection3DArray``
ground plane         ``foxglove.SceneUpdate``        ``foxglove_msgs/msg/SceneUpdate``
world <- camera      ``foxglove.FrameTransforms``    ``tf2_msgs/msg/TFMessage``
detections as JSON   JSON (``jsonschema``)           ``std_msgs/msg/String``
===================  ==============================  ======================================

The frame is a JPEG (quality :data:`JPEG_QUALITY` by default), or the bytes of the JPEG file
it was read from (a sequence of JPEGs: nothing to encode). A box is a cube entity in the
``camera`` frame (centre, yaw and size of the KITTI box; colour per track id, or per class
without tracking), with a text label (id, class, score, speed) and metadata (id, class,
score, velocity: over the ground with poses, else relative to the camera). Each scene update
first deletes the previous frame's entities. Transforms (frame ``world`` <- ``camera``) are
written only for frames with a pose.

The file is chunked (:data:`CHUNK_BYTES`): a chunk goes to disk whole once it is full, and
:meth:`McapRecording.close` writes the last chunk and the summary (index) at the end or after
a stop signal. Every write is checked: after a failed write (a full disk) the file is cut
back to its last whole record, kept as ``<name>.incomplete.mcap`` and raises an ``OSError``
naming it; a killed writer leaves its hidden ``.<name>.partial.mcap``. Either holds every
chunk written before: the ``mcap`` stream readers read them in order up to the cut (the file
has no summary; a frame's messages may go on in the chunk that was cut), and the ``mcap`` CLI's
``mcap recover`` writes a file with a summary.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.files import KittiFormatError
from gac_jax.streams import recording_scene as scene
from gac_jax.streams.checked_file import CheckedFile
from gac_jax.streams.outputs import _keep, _plain, partial_path
from gac_jax.streams.recording_messages import foxglove_messages, protobuf_class, ros2_messages
from gac_jax.streams.ros2_msgdefs import msgdef

PROFILES = ("foxglove", "ros2")
CHUNK_BYTES = 1 << 20
JPEG_QUALITY = 80  # 90: a fifth more CPU, half again the bytes (benchmarks/bench_mcap.py)
TOPICS = {
    "foxglove": {
        "image": ("/camera/image", "foxglove.CompressedImage"),
        "calibration": ("/camera/calibration", "foxglove.CameraCalibration"),
        "scene": ("/detections/scene", "foxglove.SceneUpdate"),
        "plane": ("/ground_plane", "foxglove.SceneUpdate"),
        "tf": ("/tf", "foxglove.FrameTransforms"),
        "json": ("/detections/json", "gac_jax.Detections"),
    },
    "ros2": {
        "image": ("/camera/image/compressed", "sensor_msgs/msg/CompressedImage"),
        "calibration": ("/camera/camera_info", "sensor_msgs/msg/CameraInfo"),
        "detections": ("/detections", "vision_msgs/msg/Detection3DArray"),
        "scene": ("/detections/scene", "foxglove_msgs/msg/SceneUpdate"),
        "plane": ("/ground_plane", "foxglove_msgs/msg/SceneUpdate"),
        "tf": ("/tf", "tf2_msgs/msg/TFMessage"),
        "json": ("/detections/json", "std_msgs/msg/String"),
    },
}
JSON_SCHEMA = {
    "type": "object",
    "title": "gac_jax.Detections",
    "description": "A frame's detections or tracks: to_dict() of Detections / TrackedObjects",
    "properties": {
        "frame": {"type": "string"},
        "timestamp": {"type": "number", "description": "seconds"},
        "objects": {"type": "array", "items": {"type": "object"}},
    },
}


def encode_jpeg(image: np.ndarray, quality: int = JPEG_QUALITY) -> bytes:
    """JPEG bytes of an (H, W, 3) uint8 RGB image (OpenCV's libjpeg-turbo, 4:2:0)."""
    ok, jpeg = cv2.imencode(
        ".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    if not ok:
        raise ValueError(f"cannot encode a {image.shape[1]}x{image.shape[0]} frame as JPEG")
    return jpeg.tobytes()


def check_mcap_path(path: str | os.PathLike, profile: str = "foxglove") -> Path:
    """``path`` as the recording's file, or :class:`KittiFormatError` naming the problem."""
    path = Path(path)
    if profile not in PROFILES:
        raise KittiFormatError(
            "--mcap-profile", f"unknown profile {profile!r} (use one of {', '.join(PROFILES)})"
        )
    if path.is_dir():
        raise KittiFormatError(path, "is a folder; --mcap needs a file name (e.g. run.mcap)")
    if path.suffix.lower() != ".mcap":
        raise KittiFormatError(path, "an MCAP recording's name ends in .mcap")
    return path


class McapRecording:
    """Writes frames, their calibration and their boxes into an MCAP file (module doc).

    Args:
      path: the ``.mcap`` file (replaced only when this one is complete).
      profile: ``foxglove`` (protobuf) or ``ros2`` (CDR).
      default_plane: (4,) ground plane of frames given none (e.g. the detector's level
        camera ``(0, -1, 0, camera_height)``), or None: no plane message for them.
      chunk_size: bytes of a chunk (the unit a killed writer's file is readable to).
      jpeg_quality: of the frames' JPEG (1-100; a JPEG file's bytes are stored as they are).

    ``write`` raises an ``OSError`` naming the file when it cannot be written; the chunks
    written before stay readable. Use as a context manager, or call :meth:`close`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        profile: str = "foxglove",
        default_plane=None,
        chunk_size: int = CHUNK_BYTES,
        jpeg_quality: int = JPEG_QUALITY,
    ):
        from mcap.writer import CompressionType, Writer

        self.path = check_mcap_path(path, profile).absolute()
        self.profile = profile
        self.jpeg_quality = int(jpeg_quality)
        self.default_plane = None if default_plane is None else np.asarray(default_plane)
        self.partial = partial_path(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.frames = 0
        self.kept: Path | None = None
        self.cpu_s = 0.0  # CPU seconds spent in write()
        # of them: the JPEG; the entities, JSON and messages; serialisation and the chunk
        self.cpu_parts = {"image": 0.0, "messages": 0.0, "write": 0.0}
        self._closed = False
        self._file = CheckedFile(self.partial, self.path, mark_writes=True)
        self._channels: dict[str, int] = {}  # channel ids
        self._encoders: dict[str, object] = {}  # ros2: mcap-ros2-support's CDR encoder per key
        try:
            self._writer = Writer(self._file, chunk_size, CompressionType.NONE)
            self._writer.start(profile="ros2" if profile == "ros2" else "", library="gac_jax")
        except OSError:
            self.close(False)
            raise

    # ------------------------------------------------------------------ channels

    def _channel(self, key: str) -> int:
        if key in self._channels:
            return self._channels[key]
        topic, schema = TOPICS[self.profile][key]
        if self.profile == "ros2":  # rosbag2's encodings: the definitions, CDR messages
            from mcap_ros2._dynamic import serialize_dynamic

            text = msgdef(schema)
            self._encoders[key] = serialize_dynamic(schema, text)[schema]
            schema_id = self._writer.register_schema(schema, "ros2msg", text.encode())
            channel = self._writer.register_channel(topic, "cdr", schema_id)
        elif key == "json":
            data = json.dumps(JSON_SCHEMA).encode()
            schema_id = self._writer.register_schema(schema, "jsonschema", data)
            channel = self._writer.register_channel(topic, "json", schema_id)
        else:
            from mcap_protobuf.schema import register_schema

            schema_id = register_schema(self._writer, protobuf_class(schema))
            channel = self._writer.register_channel(topic, "protobuf", schema_id)
        self._channels[key] = channel
        return channel

    def _add(self, key: str, message, ns: int) -> None:
        channel = self._channel(key)
        if self.profile == "ros2":
            data = self._encoders[key](message)
        else:
            data = message.encode() if key == "json" else message.SerializeToString()
        self._writer.add_message(
            channel, log_time=ns, data=data, publish_time=ns, sequence=self.frames
        )

    # ------------------------------------------------------------------ frames

    def write(
        self,
        image: np.ndarray,
        P2,
        detections,
        *,
        timestamp: float,
        pose=None,
        plane=None,
        frame_id: str | None = None,
        record: dict | None = None,
        jpeg: bytes | None = None,
    ) -> None:
        """Writes one frame.

        Args:
          image: (H, W, 3) uint8 RGB frame (stored as JPEG of ``jpeg_quality``).
          P2: (3, 4) its projection.
          detections: :class:`~gac_jax.api.Detections` or
            :class:`~gac_jax.tracking.TrackedObjects` (boxes in the camera frame).
          timestamp: the frame's time in seconds (the messages' stamps).
          pose: (3, 4) camera -> world of the frame, or None (no transform; velocities then
            are relative to the camera).
          plane: (4,) ground plane (camera frame), or None: ``default_plane``.
          frame_id: the frame's name in the JSON (default: its number).
          record: the JSON record (default ``detections.to_dict()``).
          jpeg: the bytes of the JPEG file ``image`` was read from
            (:attr:`~gac_jax.streams.sources.Frame.jpeg`): stored as they are instead.
        """
        t0 = time.thread_time()
        ns = round(float(timestamp) * 1e9)
        h, w = image.shape[:2]
        data = encode_jpeg(image, self.jpeg_quality) if jpeg is None else jpeg
        t1 = time.thread_time()
        objects = detections.to_kitti_objects()
        ids = getattr(detections, "ids", None)
        velocities = getattr(detections, "velocities", None)
        entities = scene.box_entities(objects, ids, velocities, over_ground=pose is not None)
        plane = self.default_plane if plane is None else plane
        record = detections.to_dict() if record is None else record
        text = json.dumps(
            {"frame": frame_id or str(self.frames), "timestamp": float(timestamp), **record},
            default=_plain,
        )
        build = ros2_messages if self.profile == "ros2" else foxglove_messages
        messages = build(ns, data, (h, w), P2, entities, pose, plane, text)
        t2 = time.thread_time()
        try:
            for key, message in messages:
                self._add(key, message, ns)
        except OSError as e:
            failure = OSError(e.errno or errno.EIO, e.strerror or "write failed", str(self.path))
            raise self._file.error or failure from None
        self.frames += 1
        t3 = time.thread_time()
        for part, seconds in zip(self.cpu_parts, (t1 - t0, t2 - t1, t3 - t2), strict=True):
            self.cpu_parts[part] += seconds
        self.cpu_s += t3 - t0

    def close(self, complete: bool = True) -> Path | None:
        """Writes the last chunk and the summary, closes and renames the file into place
        (``complete``; else to ``<name>.incomplete.mcap``). Returns where it is (None: no
        frame was written). Raises an ``OSError`` naming the file when it cannot be
        finished (the chunks before stay). Idempotent."""
        if self._closed:
            return self.kept
        self._closed = True
        failed_before = self._file.error is not None  # raised by write() already
        if not failed_before:
            with contextlib.suppress(OSError):  # kept as the file's error
                self._writer.finish()
        self._file.close()  # a failed flush to disk is kept as its error too
        error = None if failed_before else self._file.error
        complete = complete and self._file.error is None
        self.kept = _keep(self.partial, self.path, complete, self.frames)
        if error is not None:
            raise error
        return self.kept

    def __enter__(self) -> McapRecording:
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close(complete=exc_type is None)


class McapResults:
    """The stream's recorder: each written frame (its image, P2, plane, pose and detections
    or tracks) into a :class:`McapRecording`.

    Args:
      recording: the :class:`McapRecording`.
      fps: the stream's frames per second (frame times ``index / fps``).
      realtime: frame times are the wall-clock moments the frames were read.
      poses: (N, 3, 4) camera -> world by frame index, or None.
    """

    def __init__(self, recording: McapRecording, fps: float, realtime: bool = False, poses=None):
        self.recording, self.fps, self.realtime = recording, fps, realtime
        self.poses = None if poses is None else np.asarray(poses, np.float64)
        self._epoch = time.time() - time.perf_counter()  # perf_counter -> wall clock

    @property
    def frames(self) -> int:
        return self.recording.frames

    @property
    def kept(self) -> Path | None:
        return self.recording.kept

    @property
    def partial(self) -> Path:
        return self.recording.partial

    def write_frame(self, frame, detections, record: dict | None) -> None:
        timestamp = self._epoch + frame.t_read if self.realtime else frame.index / self.fps
        pose = None
        if self.poses is not None and frame.index < len(self.poses):
            pose = self.poses[frame.index]
        self.recording.write(
            frame.image,
            frame.P2,
            detections,
            timestamp=timestamp,
            pose=pose,
            plane=frame.plane,
            frame_id=frame.frame_id,
            record=record or None,
            jpeg=getattr(frame, "jpeg", None),
        )

    def close(self, complete: bool = True) -> Path | None:
        return self.recording.close(complete)
