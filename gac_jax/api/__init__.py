"""The inference API: trained models as Python objects, RGB arrays in, typed results out.

    from gac_jax import Detector3D, DepthPredictor

    det = Detector3D.from_workdir("runs/detect3d_default")      # or runtime="openvino", ...
    detections = det.predict(image, P2)   # image (H, W, 3) uint8 RGB, P2 (3, 4); plane=None
    print(detections.to_kitti_lines())

    tracker = Tracker3D(det.config)       # objects over time: ids, smoothed boxes, velocities
    tracks = tracker.update(detections, pose=pose, timestamp=t)   # pose (3, 4) or None

Bad input raises :class:`InputError` (a ``ValueError``) naming the argument.
"""

from gac_jax.api.depth import DepthPredictor, PreparedDepthImage
from gac_jax.api.detections import DetectedObject, Detections
from gac_jax.api.detector import Detector3D, PreparedImage
from gac_jax.api.inputs import PLANE_NORM_TOLERANCE, InputError
from gac_jax.api.tracker import Tracker3D
from gac_jax.tracking.tracks import TrackedObject, TrackedObjects

__all__ = [
    "PLANE_NORM_TOLERANCE",
    "DepthPredictor",
    "DetectedObject",
    "Detections",
    "Detector3D",
    "InputError",
    "PreparedDepthImage",
    "PreparedImage",
    "TrackedObject",
    "TrackedObjects",
    "Tracker3D",
]
