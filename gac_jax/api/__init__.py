"""The inference API: trained models as Python objects, RGB arrays in, typed results out.

    from gac_jax import Detector3D, DepthPredictor

    det = Detector3D.from_workdir("runs/detect3d_default")      # or runtime="openvino", ...
    detections = det.predict(image, P2)   # image (H, W, 3) uint8 RGB, P2 (3, 4); plane=None
    print(detections.to_kitti_lines())

    tracker = Tracker3D(det.config)       # objects over time: ids, smoothed boxes, velocities
    tracks = tracker.update(detections, pose=pose, timestamp=t)   # pose (3, 4) or None

Bad input raises :class:`InputError` (a ``ValueError``) naming the argument.

The names load on first use, so that the input checks (:mod:`gac_jax.api.inputs`, numpy only)
import without JAX: a stream command checks its input and calibration before JAX starts.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_WHERE = {
    "DepthPredictor": "gac_jax.api.depth",
    "PreparedDepthImage": "gac_jax.api.depth",
    "DetectedObject": "gac_jax.api.detections",
    "Detections": "gac_jax.api.detections",
    "Detector3D": "gac_jax.api.detector",
    "PreparedImage": "gac_jax.api.detector",
    "PLANE_NORM_TOLERANCE": "gac_jax.api.inputs",
    "InputError": "gac_jax.api.inputs",
    "Tracker3D": "gac_jax.api.tracker",
    "TrackedObject": "gac_jax.tracking.tracks",
    "TrackedObjects": "gac_jax.tracking.tracks",
}

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

if TYPE_CHECKING:
    from gac_jax.api.depth import DepthPredictor, PreparedDepthImage
    from gac_jax.api.detections import DetectedObject, Detections
    from gac_jax.api.detector import Detector3D, PreparedImage
    from gac_jax.api.inputs import PLANE_NORM_TOLERANCE, InputError
    from gac_jax.api.tracker import Tracker3D
    from gac_jax.tracking.tracks import TrackedObject, TrackedObjects


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        return getattr(importlib.import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'gac_jax.api' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_WHERE])
