"""ROS 2 message definitions of a ``--mcap-profile ros2`` recording, as rosbag2 stores them
in an MCAP schema (``ros2msg`` encoding): the message's own fields, then each type it uses
after a ``===`` line and ``MSG: package/Type``. The fields are those of ROS 2's
``sensor_msgs``, ``std_msgs``, ``geometry_msgs``, ``builtin_interfaces``, ``tf2_msgs``,
``vision_msgs`` (4.x) and Foxglove's ``foxglove_msgs`` (3.x); :func:`msgdef` assembles one.
mcap-ros2-support serialises the messages (CDR) from these definitions.
"""

from __future__ import annotations

SEPARATOR = "=" * 80

FIELDS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "builtin_interfaces/Duration": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "std_msgs/String": "string data",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\nTransform transform"
    ),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "sensor_msgs/CompressedImage": "std_msgs/Header header\nstring format\nuint8[] data",
    "sensor_msgs/RegionOfInterest": (
        "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify"
    ),
    "sensor_msgs/CameraInfo": (
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nRegionOfInterest roi"
    ),
    "vision_msgs/ObjectHypothesis": "string class_id\nfloat64 score",
    "vision_msgs/ObjectHypothesisWithPose": (
        "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose"
    ),
    "vision_msgs/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size",
    "vision_msgs/Detection3D": (
        "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id"
    ),
    "vision_msgs/Detection3DArray": "std_msgs/Header header\nDetection3D[] detections",
    "foxglove_msgs/Color": "float64 r\nfloat64 g\nfloat64 b\nfloat64 a",
    "foxglove_msgs/KeyValuePair": "string key\nstring value",
    "foxglove_msgs/CubePrimitive": (
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 size\nfoxglove_msgs/Color color"
    ),
    "foxglove_msgs/TextPrimitive": (
        "geometry_msgs/Pose pose\nbool billboard\nfloat64 font_size\nbool scale_invariant\n"
        "foxglove_msgs/Color color\nstring text"
    ),
    "foxglove_msgs/ArrowPrimitive": (
        "geometry_msgs/Pose pose\nfloat64 shaft_length\nfloat64 shaft_diameter\n"
        "float64 head_length\nfloat64 head_diameter\nfoxglove_msgs/Color color"
    ),
    "foxglove_msgs/SpherePrimitive": (
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 size\nfoxglove_msgs/Color color"
    ),
    "foxglove_msgs/CylinderPrimitive": (
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 size\nfloat64 bottom_scale\n"
        "float64 top_scale\nfoxglove_msgs/Color color"
    ),
    "foxglove_msgs/LinePrimitive": (
        "uint8 LINE_STRIP=0\nuint8 LINE_LOOP=1\nuint8 LINE_LIST=2\nuint8 type\n"
        "geometry_msgs/Pose pose\nfloat64 thickness\nbool scale_invariant\n"
        "geometry_msgs/Point[] points\nfoxglove_msgs/Color color\nfoxglove_msgs/Color[] colors\n"
        "uint32[] indices"
    ),
    "foxglove_msgs/TriangleListPrimitive": (
        "geometry_msgs/Pose pose\ngeometry_msgs/Point[] points\nfoxglove_msgs/Color color\n"
        "foxglove_msgs/Color[] colors\nuint32[] indices"
    ),
    "foxglove_msgs/ModelPrimitive": (
        "geometry_msgs/Pose pose\ngeometry_msgs/Vector3 scale\nfoxglove_msgs/Color color\n"
        "bool override_color\nstring url\nstring media_type\nuint8[] data"
    ),
    "foxglove_msgs/SceneEntityDeletion": (
        "uint8 MATCHING_ID=0\nuint8 ALL=1\nbuiltin_interfaces/Time timestamp\nuint8 type\nstring id"
    ),
    "foxglove_msgs/SceneEntity": (
        "builtin_interfaces/Time timestamp\nstring frame_id\nstring id\n"
        "builtin_interfaces/Duration lifetime\nbool frame_locked\n"
        "foxglove_msgs/KeyValuePair[] metadata\nfoxglove_msgs/ArrowPrimitive[] arrows\n"
        "foxglove_msgs/CubePrimitive[] cubes\nfoxglove_msgs/SpherePrimitive[] spheres\n"
        "foxglove_msgs/CylinderPrimitive[] cylinders\nfoxglove_msgs/LinePrimitive[] lines\n"
        "foxglove_msgs/TriangleListPrimitive[] triangles\nfoxglove_msgs/TextPrimitive[] texts\n"
        "foxglove_msgs/ModelPrimitive[] models"
    ),
    "foxglove_msgs/SceneUpdate": (
        "foxglove_msgs/SceneEntityDeletion[] deletions\nfoxglove_msgs/SceneEntity[] entities"
    ),
}
PRIMITIVES = {
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32",
    "uint32", "int64", "uint64", "string", "wstring",
}  # fmt: skip


def _uses(name: str) -> list[str]:
    """The message types ``name``'s fields use, as ``package/Type``."""
    package = name.split("/")[0]
    out = []
    for line in FIELDS[name].splitlines():
        kind = line.split()[0].split("[")[0]
        if kind in PRIMITIVES or "=" in line.split()[1]:
            continue
        out.append(kind if "/" in kind else f"{package}/{kind}")
    return out


def msgdef(name: str) -> str:
    """The definition of ``name`` (``package/msg/Type`` or ``package/Type``) with every type
    it uses, depth first, each once."""
    name = name.replace("/msg/", "/")
    order: list[str] = []

    def visit(kind: str) -> None:
        for used in _uses(kind):
            if used not in order and used != name:
                order.append(used)
                visit(used)

    visit(name)
    parts = [FIELDS[name]] + [f"{SEPARATOR}\nMSG: {kind}\n{FIELDS[kind]}" for kind in order]
    return "\n".join(parts) + "\n"
