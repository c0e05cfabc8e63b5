"""A frame's messages in a recording's two profiles (:mod:`gac_jax.streams.mcap_recording`):
protobuf messages of ``foxglove-schemas-protobuf`` (``foxglove``) and ROS 2 message
dictionaries that mcap-ros2-support serialises (``ros2``), built from the plain values of
:mod:`gac_jax.streams.recording_scene`.
"""

from __future__ import annotations

import importlib

from gac_jax.streams import recording_scene as scene

CAMERA_FRAME, WORLD_FRAME = "camera", "world"


def protobuf_class(name: str):
    """The protobuf class of a Foxglove schema name (``foxglove.SceneUpdate``)."""
    short = name.split(".")[-1]
    module = importlib.import_module(f"foxglove_schemas_protobuf.{short}_pb2")
    return getattr(module, short)


def box_entity(entity: dict, stamp) -> dict:
    """A scene entity of one box (:func:`~gac_jax.streams.recording_scene.box_entities`): its
    cube, a billboard label in its colour and its metadata, in the camera frame."""
    label = {**entity["label"], "billboard": True, "font_size": 14.0, "scale_invariant": True}
    return {
        "timestamp": stamp,
        "frame_id": CAMERA_FRAME,
        "id": entity["id"],
        "cubes": [entity["cube"]],
        "texts": [{**label, "color": entity["color"]}],
        "metadata": [{"key": k, "value": v} for k, v in entity["metadata"]],
    }


def _stamp(ns: int) -> dict:
    return {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}


def foxglove_messages(ns, jpeg, size, P2, entities, pose, plane, text):
    """``(channel key, protobuf message)`` of one frame, profile ``foxglove``."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from google.protobuf.timestamp_pb2 import Timestamp

    stamp = Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)
    calib = scene.calibration(P2)
    out = [
        (
            "image",
            CompressedImage(timestamp=stamp, frame_id=CAMERA_FRAME, data=jpeg, format="jpeg"),
        ),
        (
            "calibration",
            CameraCalibration(
                timestamp=stamp,
                frame_id=CAMERA_FRAME,
                width=size[1],
                height=size[0],
                distortion_model="",
                D=[],
                K=calib["K"],
                R=calib["R"],
                P=calib["P"],
            ),
        ),
    ]
    deletion = [{"timestamp": stamp, "type": 1}]  # ALL: the previous frame's boxes go
    boxes = [box_entity(e, stamp) for e in entities]
    out.append(("scene", SceneUpdate(deletions=deletion, entities=boxes)))
    if plane is not None:
        ground = {
            "timestamp": stamp,
            "frame_id": CAMERA_FRAME,
            "id": "ground",
            "cubes": [scene.plane_patch(plane)],
        }
        out.append(("plane", SceneUpdate(entities=[ground])))
    if pose is not None:
        t, q = scene.camera_transform(pose)
        transform = {
            "timestamp": stamp,
            "parent_frame_id": WORLD_FRAME,
            "child_frame_id": CAMERA_FRAME,
            "translation": dict(zip("xyz", t, strict=True)),
            "rotation": dict(zip("xyzw", q, strict=True)),
        }
        out.append(("tf", FrameTransforms(transforms=[transform])))
    out.append(("json", text))
    return out


def ros2_messages(ns, jpeg, size, P2, entities, pose, plane, text):
    """``(channel key, message dict)`` of one frame, profile ``ros2``."""
    stamp = _stamp(ns)
    header = {"stamp": stamp, "frame_id": CAMERA_FRAME}
    calib = scene.calibration(P2)
    out = [
        ("image", {"header": header, "format": "jpeg", "data": jpeg}),
        (
            "calibration",
            {
                "header": header,
                "height": size[0],
                "width": size[1],
                "distortion_model": "plumb_bob",
                "d": [0.0] * 5,
                "k": calib["K"],
                "r": calib["R"],
                "p": calib["P"],
                "binning_x": 0,
                "binning_y": 0,
                "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
            },
        ),
        (
            "detections",
            {
                "header": header,
                "detections": [
                    {
                        "header": header,
                        "results": [
                            {
                                "hypothesis": {"class_id": e["name"], "score": e["score"]},
                                "pose": {"pose": e["cube"]["pose"], "covariance": [0.0] * 36},
                            }
                        ],
                        "bbox": {"center": e["cube"]["pose"], "size": e["cube"]["size"]},
                        "id": "" if e["track_id"] is None else str(e["track_id"]),
                    }
                    for e in entities
                ],
            },
        ),
    ]
    empty = {
        "arrows": [],
        "spheres": [],
        "cylinders": [],
        "lines": [],
        "triangles": [],
        "models": [],
    }
    forever = {"sec": 0, "nanosec": 0}
    boxes = [
        {**box_entity(e, stamp), "lifetime": forever, "frame_locked": False, **empty}
        for e in entities
    ]
    deletion = [{"timestamp": stamp, "type": 1, "id": ""}]
    out.append(("scene", {"deletions": deletion, "entities": boxes}))
    if plane is not None:
        ground = {
            "timestamp": stamp,
            "frame_id": CAMERA_FRAME,
            "id": "ground",
            "lifetime": forever,
            "frame_locked": False,
            "metadata": [],
            "cubes": [scene.plane_patch(plane)],
            "texts": [],
            **empty,
        }
        out.append(("plane", {"deletions": [], "entities": [ground]}))
    if pose is not None:
        t, q = scene.camera_transform(pose)
        transform = {
            "header": {"stamp": stamp, "frame_id": WORLD_FRAME},
            "child_frame_id": CAMERA_FRAME,
            "transform": {
                "translation": dict(zip("xyz", t, strict=True)),
                "rotation": dict(zip("xyzw", q, strict=True)),
            },
        }
        out.append(("tf", {"transforms": [transform]}))
    out.append(("json", {"data": text}))
    return out
