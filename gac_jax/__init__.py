"""gac-jax: ground-aware monocular 3D object detection and depth (GAC, RA-L 2021) in JAX/Flax.

The inference API (:mod:`gac_jax.api`) is importable from here, loaded on first use so that
``import gac_jax`` stays cheap::

    from gac_jax import Detector3D, DepthPredictor, Detections, InputError, Tracker3D
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

_API = (
    "Detector3D",
    "DepthPredictor",
    "Detections",
    "DetectedObject",
    "InputError",
    "Tracker3D",
    "TrackedObjects",
)

__all__ = [
    "DepthPredictor",
    "DetectedObject",
    "Detections",
    "Detector3D",
    "InputError",
    "TrackedObjects",
    "Tracker3D",
]

if TYPE_CHECKING:
    from gac_jax.api import (
        DepthPredictor,
        DetectedObject,
        Detections,
        Detector3D,
        InputError,
        TrackedObjects,
        Tracker3D,
    )


def __getattr__(name: str) -> Any:
    if name in _API:
        return getattr(importlib.import_module("gac_jax.api"), name)
    raise AttributeError(f"module 'gac_jax' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_API])
