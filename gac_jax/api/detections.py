"""The detector's result for one image: :class:`Detections`, N objects as read-only arrays.

Frames: ``boxes_2d`` are xyxy in the pixels of the image given to ``predict`` (u right, v
down); ``locations`` are the bottom-face centres ``(x, y, z)`` in that image's camera frame
(x right, y down, z forward, metres); ``rotation_y`` is the yaw about the camera's y axis and
``alpha`` the observation angle (KITTI's conventions, radians). Objects come best first.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np

from gac_jax.data.kitti import KittiObjects, format_label


@dataclasses.dataclass(frozen=True)
class DetectedObject:
    """One detected object (see :class:`Detections` for the frames)."""

    name: str
    score: float
    box_2d: tuple[float, float, float, float]
    dimensions: tuple[float, float, float]  # h, w, l (metres)
    location: tuple[float, float, float]  # x, y, z bottom centre (camera frame, metres)
    rotation_y: float
    alpha: float


_SHAPES = {
    "names": (),
    "scores": (),
    "boxes_2d": (4,),
    "dimensions": (3,),
    "locations": (3,),
    "rotation_y": (),
    "alpha": (),
}


def _frozen(value: Any, dtype, shape: tuple[int, ...], field: str, n: int) -> np.ndarray:
    arr = np.array(value, dtype=dtype).reshape((n, *shape)) if n else np.zeros((0, *shape), dtype)
    if arr.shape != (n, *shape):
        raise ValueError(f"{field}: expected shape {(n, *shape)}, got {arr.shape}")
    arr.flags.writeable = False
    return arr


@dataclasses.dataclass(frozen=True, eq=False)
class Detections:
    """N detected objects of one image (immutable: the arrays are read-only copies).

    Attributes:
      names: (N,) class names (``'Car'``, ...).
      scores: (N,) confidences, best first.
      boxes_2d: (N, 4) xyxy in the original image's pixels.
      dimensions: (N, 3) ``(h, w, l)`` metres.
      locations: (N, 3) bottom-face centre ``(x, y, z)``, camera frame, metres.
      rotation_y: (N,) yaw about the camera y axis (radians).
      alpha: (N,) observation angle (radians).

    ``len(d)``, ``d[i]`` and ``for obj in d`` give :class:`DetectedObject` records;
    :meth:`to_kitti_lines` the KITTI result lines (score last) that ``evaluate.py`` writes,
    :meth:`to_kitti_objects` the project's :class:`~gac_jax.data.kitti.KittiObjects` (for
    :mod:`gac_jax.drawing.boxes`), :meth:`to_dict` plain JSON-ready values.
    """

    names: np.ndarray
    scores: np.ndarray
    boxes_2d: np.ndarray
    dimensions: np.ndarray
    locations: np.ndarray
    rotation_y: np.ndarray
    alpha: np.ndarray

    def __post_init__(self):
        n = len(np.asarray(self.names).reshape(-1))
        for field, shape in _SHAPES.items():
            dtype = "<U16" if field == "names" else np.float64
            object.__setattr__(self, field, _frozen(getattr(self, field), dtype, shape, field, n))

    @classmethod
    def from_kitti_objects(cls, objects: KittiObjects) -> Detections:
        """The detections of a post-processed :class:`KittiObjects` (scores set)."""
        return cls(
            names=objects.type,
            scores=objects.score,
            boxes_2d=objects.bbox,
            dimensions=objects.dimensions,
            locations=objects.location,
            rotation_y=objects.rotation_y,
            alpha=objects.alpha,
        )

    @classmethod
    def empty(cls) -> Detections:
        return cls.from_kitti_objects(KittiObjects.empty())

    def __len__(self) -> int:
        return int(self.names.shape[0])

    def __getitem__(self, i: int) -> DetectedObject:
        return DetectedObject(
            name=str(self.names[i]),
            score=float(self.scores[i]),
            box_2d=tuple(float(v) for v in self.boxes_2d[i]),
            dimensions=tuple(float(v) for v in self.dimensions[i]),
            location=tuple(float(v) for v in self.locations[i]),
            rotation_y=float(self.rotation_y[i]),
            alpha=float(self.alpha[i]),
        )

    def __iter__(self) -> Iterator[DetectedObject]:
        return (self[i] for i in range(len(self)))

    def __repr__(self) -> str:
        counts: dict[str, int] = {}
        for name in self.names.tolist():
            counts[name] = counts.get(name, 0) + 1
        shown = ", ".join(f"{k}: {v}" for k, v in counts.items())
        return f"Detections({len(self)} objects{'; ' + shown if shown else ''})"

    def to_kitti_objects(self) -> KittiObjects:
        """As :class:`KittiObjects` (truncation and occlusion unknown: -1, as in result files)."""
        return KittiObjects.predictions(
            type=self.names,
            alpha=self.alpha,
            bbox=self.boxes_2d,
            dimensions=self.dimensions,
            location=self.locations,
            rotation_y=self.rotation_y,
            score=self.scores,
        )

    def to_kitti_lines(self) -> list[str]:
        """The KITTI result lines (score last, no newline) ``evaluate.py`` writes per frame."""
        return format_label(self.to_kitti_objects(), with_score=True).splitlines()

    def to_dict(self) -> dict[str, list]:
        """``{'objects': [{'name', 'score', 'box_2d', 'dimensions', 'location', 'rotation_y',
        'alpha'}, ...]}`` with plain Python values (``json.dumps`` ready)."""
        return {"objects": [dataclasses.asdict(obj) for obj in self]}
