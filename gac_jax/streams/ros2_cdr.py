"""CDR bytes of the ROS 2 messages of a ``--mcap-profile ros2`` recording: the message
dictionaries of :func:`gac_jax.streams.recording_messages.ros2_messages`, laid out as their
definitions in :mod:`gac_jax.streams.ros2_msgdefs` say.

Little-endian CDR as ROS 2 writes it (and mcap-ros2-support, whose bytes these equal: tested):
a 4-byte encapsulation header ``00 01 00 00``; every primitive aligned to its own size,
counted from the end of that header; a string as a uint32 length (with its NUL), its UTF-8
bytes and a NUL; a sequence as a uint32 count and its items; a fixed-size array as its items
alone. Written here, with the fixed runs of float64 (poses, sizes, colours) packed at once,
because mcap-ros2-support's general serialiser walks every field of every box in Python
(``benchmarks/bench_mcap.py`` times both profiles).
"""

from __future__ import annotations

import struct

HEADER = b"\x00\x01\x00\x00"  # CDR_LE, no options
_U32 = struct.Struct("<I")
_TIME = struct.Struct("<iI")  # builtin_interfaces/Time and Duration: int32 sec, uint32 nanosec
_F64: dict[int, struct.Struct] = {}  # n -> the struct of n float64
UNUSED_PRIMITIVES = ("arrows", "spheres", "cylinders", "lines", "triangles", "models")


class CdrBuffer:
    """A CDR message being written (``data``: the bytes so far, header included)."""

    __slots__ = ("data",)

    def __init__(self):
        self.data = bytearray(HEADER)

    def align(self, size: int) -> None:
        pad = -(len(self.data) - 4) % size
        if pad:
            self.data += bytes(pad)

    def uint8(self, value: int) -> None:
        self.data.append(int(value))

    def boolean(self, value) -> None:
        self.data.append(1 if value else 0)

    def uint32(self, value: int) -> None:
        self.align(4)
        self.data += _U32.pack(value)

    def time(self, value: dict) -> None:
        self.align(4)
        self.data += _TIME.pack(value["sec"], value["nanosec"])

    def string(self, text: str) -> None:
        raw = text.encode()
        self.align(4)
        self.data += _U32.pack(len(raw) + 1)
        self.data += raw
        self.data.append(0)

    def float64s(self, values) -> None:
        """A run of float64 (no count: fixed-size fields or arrays)."""
        n = len(values)
        if n:
            packer = _F64.get(n) or _F64.setdefault(n, struct.Struct(f"<{n}d"))
            self.align(8)
            self.data += packer.pack(*values)

    def header(self, header: dict) -> None:
        self.time(header["stamp"])
        self.string(header["frame_id"])


def _xyz(v: dict) -> list[float]:
    return [v["x"], v["y"], v["z"]]


def _xyzw(q: dict) -> list[float]:
    return [q["x"], q["y"], q["z"], q["w"]]


def _pose(pose: dict) -> list[float]:
    return _xyz(pose["position"]) + _xyzw(pose["orientation"])


def _rgba(c: dict) -> list[float]:
    return [c["r"], c["g"], c["b"], c["a"]]


def _entity(out: CdrBuffer, entity: dict) -> None:
    """``foxglove_msgs/SceneEntity`` with metadata, cubes and texts (the other primitives
    must be empty)."""
    out.time(entity["timestamp"])
    out.string(entity["frame_id"])
    out.string(entity["id"])
    out.time(entity["lifetime"])
    out.boolean(entity["frame_locked"])
    out.uint32(len(entity["metadata"]))
    for pair in entity["metadata"]:
        out.string(pair["key"])
        out.string(pair["value"])
    if any(entity[name] for name in UNUSED_PRIMITIVES):
        raise ValueError(f"scene entity {entity['id']!r}: only cubes and texts are written")
    out.uint32(0)  # arrows
    out.uint32(len(entity["cubes"]))
    for cube in entity["cubes"]:
        out.float64s(_pose(cube["pose"]) + _xyz(cube["size"]) + _rgba(cube["color"]))
    for _ in range(4):  # spheres, cylinders, lines, triangles
        out.uint32(0)
    out.uint32(len(entity["texts"]))
    for text in entity["texts"]:
        out.float64s(_pose(text["pose"]))
        out.boolean(text["billboard"])
        out.float64s([text["font_size"]])
        out.boolean(text["scale_invariant"])
        out.float64s(_rgba(text["color"]))
        out.string(text["text"])
    out.uint32(0)  # models


def scene_update(out: CdrBuffer, msg: dict) -> None:
    """``foxglove_msgs/msg/SceneUpdate``."""
    out.uint32(len(msg["deletions"]))
    for deletion in msg["deletions"]:
        out.time(deletion["timestamp"])
        out.uint8(deletion["type"])
        out.string(deletion["id"])
    out.uint32(len(msg["entities"]))
    for entity in msg["entities"]:
        _entity(out, entity)


def detection_array(out: CdrBuffer, msg: dict) -> None:
    """``vision_msgs/msg/Detection3DArray``."""
    out.header(msg["header"])
    out.uint32(len(msg["detections"]))
    for detection in msg["detections"]:
        out.header(detection["header"])
        out.uint32(len(detection["results"]))
        for result in detection["results"]:
            out.string(result["hypothesis"]["class_id"])
            pose = result["pose"]
            out.float64s([result["hypothesis"]["score"], *_pose(pose["pose"])])
            covariance = list(pose["covariance"])
            if len(covariance) != 36:
                raise ValueError("a pose covariance has 36 values")
            out.float64s(covariance)
        bbox = detection["bbox"]
        out.float64s(_pose(bbox["center"]) + _xyz(bbox["size"]))
        out.string(detection["id"])


def camera_info(out: CdrBuffer, msg: dict) -> None:
    """``sensor_msgs/msg/CameraInfo``."""
    out.header(msg["header"])
    out.uint32(msg["height"])
    out.uint32(msg["width"])
    out.string(msg["distortion_model"])
    out.uint32(len(msg["d"]))
    for values in (msg["d"], msg["k"], msg["r"], msg["p"]):
        out.float64s(list(values))
    out.uint32(msg["binning_x"])
    out.uint32(msg["binning_y"])
    roi = msg["roi"]
    for key in ("x_offset", "y_offset", "height", "width"):
        out.uint32(roi[key])
    out.boolean(roi["do_rectify"])


def tf_message(out: CdrBuffer, msg: dict) -> None:
    """``tf2_msgs/msg/TFMessage``."""
    out.uint32(len(msg["transforms"]))
    for transform in msg["transforms"]:
        out.header(transform["header"])
        out.string(transform["child_frame_id"])
        t = transform["transform"]
        out.float64s(_xyz(t["translation"]) + _xyzw(t["rotation"]))


def compressed_image(out: CdrBuffer, msg: dict) -> None:
    """``sensor_msgs/msg/CompressedImage``."""
    out.header(msg["header"])
    out.string(msg["format"])
    out.uint32(len(msg["data"]))
    out.data += msg["data"]


def string(out: CdrBuffer, msg: dict) -> None:
    """``std_msgs/msg/String``."""
    out.string(msg["data"])


ENCODERS = {
    "foxglove_msgs/msg/SceneUpdate": scene_update,
    "vision_msgs/msg/Detection3DArray": detection_array,
    "sensor_msgs/msg/CameraInfo": camera_info,
    "tf2_msgs/msg/TFMessage": tf_message,
    "sensor_msgs/msg/CompressedImage": compressed_image,
    "std_msgs/msg/String": string,
}


def encode(schema: str, msg: dict) -> bytearray:
    """The CDR bytes of ``msg``, a message of ``schema`` (a key of :data:`ENCODERS`)."""
    out = CdrBuffer()
    ENCODERS[schema](out, msg)
    return out.data  # not copied again: an image's bytes are large
