"""The ``ros2`` recording read as a rosbag2 bag by an implementation of its own: ``rosbags``
(its MCAP storage reader, ``.msg`` parser, type system and CDR deserialiser; nothing of
``mcap`` or ``mcap-ros2-support``). The bare ``.mcap`` opens as a bag; the definitions stored
in the file parse, and those of the standard packages equal ROS 2 Humble's and Jazzy's; every
message deserialises with them and serialises back to the same bytes; the numbers are the
ones written (image bytes, K and P, boxes, transforms, stamps and log times)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags (the dev extra) reads rosbag2 bags")

from test_mcap_recordings import Tracks, frame_objects, poses, yaw_of  # noqa: E402
from test_stream_recordings import FPS, SIZE, pictures  # noqa: E402

from gac_jax.data.kitti import KittiObjects  # noqa: E402
from gac_jax.streams.mcap_recording import TOPICS, McapRecording, encode_jpeg  # noqa: E402
from gac_jax.streams.recording_scene import quaternion_matrix  # noqa: E402

P2 = np.array([[700.0, 0, 80, 45.0], [0, 700.0, 37, 0.2], [0, 0, 1, 0.003]])
T0 = 1_733_500_000.25  # a wall-clock start (--realtime): stamps with seconds and nanoseconds


def read_bag(path: Path) -> tuple[dict[str, list[tuple[int, object]]], dict]:
    """``({topic: [(log time ns, message), ...]}, summary)`` of a bare rosbag2 MCAP file, the
    messages deserialised by rosbags from the definitions stored in the file, each checked to
    serialise back to its bytes; the summary as rosbags reads it: ``types``, ``counts`` (per
    topic), ``messages``, ``start`` and ``end`` (ns, the end one past the last message)."""
    from rosbags.interfaces import MessageDefinitionFormat
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.EMPTY)
    out: dict[str, list[tuple[int, object]]] = {}
    with Reader(path) as reader:
        for connection in reader.connections:
            assert connection.msgdef.format == MessageDefinitionFormat.MSG, connection
            assert connection.ext.serialization_format == "cdr", connection
            store.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        for connection, ns, raw in reader.messages():
            message = store.deserialize_cdr(raw, connection.msgtype)
            assert bytes(store.serialize_cdr(message, connection.msgtype)) == bytes(raw)
            out.setdefault(connection.topic, []).append((ns, message))
        summary = {
            "types": {c.topic: c.msgtype for c in reader.connections},
            "counts": {c.topic: c.msgcount for c in reader.connections},
            "messages": reader.message_count,
            "start": reader.start_time,
            "end": reader.end_time,
        }
    return out, summary


def plain(message):
    """A message of rosbags (dataclasses, numpy arrays) or mcap-ros2-support (namespaces,
    lists, bytes) as dictionaries, lists and numbers, to compare the two."""
    if dataclasses.is_dataclass(message):  # rosbags lists the constants (upper case) too
        names = [f.name for f in dataclasses.fields(message) if f.name.islower()]
        return {name: plain(getattr(message, name)) for name in names if name != "__msgtype__"}
    if hasattr(message, "__slots__"):
        return {name: plain(getattr(message, name)) for name in message.__slots__}
    if isinstance(message, np.ndarray):
        return message.tolist()
    if isinstance(message, bytes | list | tuple):
        return [plain(v) for v in message]
    return message


class NoBoxes(Tracks):
    """A frame without tracks (empty sequences in the messages)."""

    def __init__(self, i: int):
        self.objects = frame_objects(i).select(np.zeros(0, np.int64))
        self.ids, self.velocities = np.zeros(0, np.int64), np.zeros((0, 3))


def test_the_definitions_are_those_of_ros2_humble_and_jazzy():
    """Each topic's definition as the file stores it (the type and every type it uses,
    :func:`~gac_jax.streams.ros2_msgdefs.msgdef`) registers in rosbags' stores
    of Humble and Jazzy, which refuse a type they hold with other fields: ``sensor_msgs``,
    ``std_msgs``, ``geometry_msgs``, ``builtin_interfaces``, ``tf2_msgs`` as ROS 2 has them
    (``vision_msgs`` and ``foxglove_msgs`` are not in the stores)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from gac_jax.streams.ros2_msgdefs import msgdef

    standard = {"sensor_msgs", "std_msgs", "geometry_msgs", "builtin_interfaces", "tf2_msgs"}
    for distro in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY):
        store, used = get_typestore(distro), set()
        held = {name for name in store.fielddefs if name.split("/")[0] in standard}
        for _, kind in TOPICS["ros2"].values():
            types = get_types_from_msg(msgdef(kind), kind)
            store.register(types)  # TypesysError: a type the distro holds with other fields
            used |= set(types)
        # every standard type was compared; the distro holds none of the others
        assert {name.split("/")[0] for name in used - held} == {"vision_msgs", "foxglove_msgs"}


def test_a_ros2_recording_reads_as_a_rosbag2_bag(tmp_path):
    """Five frames at wall-clock times (the third without boxes, the fourth without a pose):
    rosbags opens the bare file (its topics, types, counts and time span), and every message
    reads back to what was written."""
    n = 5
    times = [T0 + i / FPS for i in range(n)]
    ns = [round(t * 1e9) for t in times]
    pose, rgb = poses(n), pictures(n)
    has_pose = [i != 3 for i in range(n)]
    frames = [NoBoxes(i) if i == 2 else Tracks(i) for i in range(n)]
    path = tmp_path / "run.mcap"
    with McapRecording(path, "ros2", default_plane=(0, -1, 0, 1.65)) as recording:
        for i in range(n):
            at = pose[i] if has_pose[i] else None
            recording.write(rgb[i], P2, frames[i], timestamp=times[i], pose=at, frame_id=f"{i:06d}")
    bag, summary = read_bag(path)

    assert summary["types"] == dict(TOPICS["ros2"].values())
    counts = summary["counts"]
    assert counts == {topic: n - (topic == "/tf") for topic in summary["types"]}
    assert summary["messages"] == sum(counts.values()) == sum(len(m) for m in bag.values())
    assert (summary["start"], summary["end"]) == (ns[0], ns[-1] + 1)
    for topic, messages in bag.items():  # log times: the frames' times
        want = [t for t, p in zip(ns, has_pose, strict=True) if p] if topic == "/tf" else ns
        assert [t for t, _ in messages] == want, topic

    for i in range(n):
        stamp = ns[i]
        image = bag["/camera/image/compressed"][i][1]
        assert image.format == "jpeg" and image.header.frame_id == "camera"
        assert bytes(image.data) == encode_jpeg(rgb[i])
        info = bag["/camera/camera_info"][i][1]
        assert (info.height, info.width, info.distortion_model) == (*SIZE, "plumb_bob")
        np.testing.assert_array_equal(info.k, P2[:, :3].ravel())
        np.testing.assert_array_equal(info.p, P2.ravel())
        np.testing.assert_array_equal(info.r, np.eye(3).ravel())
        np.testing.assert_array_equal(info.d, np.zeros(5))
        detections = bag["/detections"][i][1]
        scene = bag["/detections/scene"][i][1]
        json_record = json.loads(bag["/detections/json"][i][1].data)
        assert json_record["frame"] == f"{i:06d}" and json_record["timestamp"] == times[i]
        stamps = [
            image.header.stamp,
            info.header.stamp,
            detections.header.stamp,
            scene.deletions[0].timestamp,
            bag["/ground_plane"][i][1].entities[0].timestamp,
        ]
        stamps += [d.header.stamp for d in detections.detections]
        stamps += [e.timestamp for e in scene.entities]
        assert {s.sec * 1_000_000_000 + s.nanosec for s in stamps} == {stamp}
        assert all(0 <= s.nanosec < 1_000_000_000 for s in stamps)
        check_boxes(frames[i].to_kitti_objects(), detections, scene)
        ground = bag["/ground_plane"][i][1].entities[0]
        assert ground.frame_id == "camera"
        assert ground.cubes[0].pose.position.y == pytest.approx(1.65)
    for t, message in bag["/tf"]:
        i = ns.index(t)
        (transform,) = message.transforms
        assert transform.header.frame_id == "world" and transform.child_frame_id == "camera"
        assert transform.header.stamp.sec * 1_000_000_000 + transform.header.stamp.nanosec == t
        translation, rotation = transform.transform.translation, transform.transform.rotation
        xyz = [translation.x, translation.y, translation.z]
        np.testing.assert_array_equal(xyz, pose[i][:, 3])
        q = [rotation.x, rotation.y, rotation.z, rotation.w]
        np.testing.assert_allclose(quaternion_matrix(q), pose[i][:, :3], atol=1e-12)


def check_boxes(want: KittiObjects, detections, scene) -> None:
    """The Detection3DArray's and the SceneUpdate's boxes: the KITTI boxes' centres, sizes
    (l, h, w), yaw, class, score and track id."""
    assert len(detections.detections) == len(scene.entities) == len(want)
    assert scene.deletions[0].type == 1  # ALL: the previous frame's boxes go
    boxes = zip(detections.detections, scene.entities, strict=True)
    for k, (detection, entity) in enumerate(boxes):
        h, w, l = want.dimensions[k]
        centre = want.location[k] - [0, h / 2, 0]
        (result,) = detection.results
        cube = entity.cubes[0]
        bbox = detection.bbox
        for box_pose, size in ((bbox.center, bbox.size), (result.pose.pose, bbox.size),
                               (cube.pose, cube.size)):  # fmt: skip
            p = box_pose.position
            np.testing.assert_allclose([p.x, p.y, p.z], centre, rtol=0, atol=1e-12)
            np.testing.assert_allclose([size.x, size.y, size.z], [l, h, w], rtol=0, atol=1e-12)
            assert yaw_of(box_pose.orientation) == pytest.approx(want.rotation_y[k], abs=1e-12)
        assert result.hypothesis.class_id == want.type[k]
        assert result.hypothesis.score == pytest.approx(want.score[k], abs=1e-7)
        assert detection.id == ["3", "7"][k] and entity.id == f"track {detection.id}"
        assert detection.header.frame_id == entity.frame_id == "camera"
