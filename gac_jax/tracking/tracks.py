"""What goes into a tracker (:class:`DetectionArrays`) and what comes out (:class:`TrackedObjects`).

Frames: boxes ``xyxy`` in image pixels (u right, v down); locations are bottom-face centres in
the camera frame of the frame given (x right, y down, z forward, metres); ``rotation_y`` the
yaw about the camera's y axis and ``alpha`` the observation angle (KITTI's conventions).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np

from gac_jax.data.kitti import KittiObjects, format_label
from gac_jax.geometry import alpha_from_rotation_y


@dataclasses.dataclass(frozen=True)
class DetectionArrays:
    """N detections of one frame as plain arrays (float64; names ``<U16``)."""

    names: np.ndarray  # (N,)
    scores: np.ndarray  # (N,)
    boxes_2d: np.ndarray  # (N, 4)
    dimensions: np.ndarray  # (N, 3) h, w, l
    locations: np.ndarray  # (N, 3)
    rotation_y: np.ndarray  # (N,)

    @classmethod
    def of(cls, detections: Any) -> DetectionArrays:
        """From :class:`gac_jax.api.Detections` (``boxes_2d``, ``locations``, ...) or
        :class:`~gac_jax.data.kitti.KittiObjects` (``bbox``, ``location``, ...).

        Raises:
          TypeError: neither; ValueError: inconsistent lengths or non-finite values.
        """
        if isinstance(detections, KittiObjects):
            fields = (
                detections.type,
                detections.score,
                detections.bbox,
                detections.dimensions,
                detections.location,
                detections.rotation_y,
            )
        elif all(hasattr(detections, k) for k in ("names", "boxes_2d", "locations")):
            d = detections
            fields = (d.names, d.scores, d.boxes_2d, d.dimensions, d.locations, d.rotation_y)
        else:
            raise TypeError(f"expected Detections or KittiObjects, got {type(detections).__name__}")
        names = np.asarray(fields[0]).astype("<U16").reshape(-1)
        n = len(names)
        arrays = [np.asarray(f, np.float64) for f in fields[1:]]
        shapes = ((n,), (n, 4), (n, 3), (n, 3), (n,))
        for name, arr, shape in zip(
            ("scores", "boxes_2d", "dimensions", "locations", "rotation_y"),
            arrays,
            shapes,
            strict=True,
        ):
            if arr.shape != shape:
                raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
            if name != "scores" and not np.all(np.isfinite(arr)):
                raise ValueError(f"{name}: non-finite value")
        scores = np.where(np.isnan(arrays[0]), 1.0, arrays[0])  # ground truth: score 1
        return cls(names, scores, *arrays[1:])

    def __len__(self) -> int:
        return len(self.names)

    def select(self, index: np.ndarray) -> DetectionArrays:
        return DetectionArrays(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))


_FIELDS = {  # name -> (dtype, shape after N)
    "ids": (np.int64, ()),
    "names": ("<U16", ()),
    "scores": (np.float64, ()),
    "boxes_2d": (np.float64, (4,)),
    "dimensions": (np.float64, (3,)),
    "locations": (np.float64, (3,)),
    "rotation_y": (np.float64, ()),
    "velocities": (np.float64, (3,)),
    "velocity_covariances": (np.float64, (3, 3)),
    "ages": (np.int64, ()),
    "hits": (np.int64, ()),
}


@dataclasses.dataclass(frozen=True)
class TrackedObject:
    """One tracked object (see :class:`TrackedObjects`)."""

    track_id: int
    name: str
    score: float
    box_2d: tuple[float, float, float, float]
    dimensions: tuple[float, float, float]
    location: tuple[float, float, float]
    rotation_y: float
    alpha: float
    velocity: tuple[float, float, float]
    speed: float
    age: int
    hits: int


@dataclasses.dataclass(frozen=True, eq=False)
class TrackedObjects:
    """The tracks reported for one frame (immutable: read-only arrays).

    Attributes:
      ids: (N,) track ids (int, unique within a stream, from 0).
      names: (N,) class names; scores: (N,) the last matched detection's score.
      boxes_2d: (N, 4) xyxy pixels (the last matched detection's box).
      dimensions: (N, 3) ``(h, w, l)`` metres, smoothed.
      locations: (N, 3) bottom-face centre in this frame's camera frame, smoothed (on the
        frame's ground plane when one was given).
      rotation_y: (N,) smoothed yaw (radians); alpha: (N,) the matching observation angle.
      velocities: (N, 3) m/s in this frame's camera axes: over the ground when poses were
        given (tracking in the world frame), relative to the camera otherwise; NaN for a
        tracker that estimates none (the 2D baseline).
      velocity_covariances: (N, 3, 3) of ``velocities`` ((m/s)^2).
      ages: (N,) frames since the track began (0 in its first frame); hits: (N,) detections
        matched to it.
      trails: N arrays (K, 3): the track's last positions, oldest first, in this frame's
        camera frame.
    """

    ids: np.ndarray
    names: np.ndarray
    scores: np.ndarray
    boxes_2d: np.ndarray
    dimensions: np.ndarray
    locations: np.ndarray
    rotation_y: np.ndarray
    velocities: np.ndarray
    velocity_covariances: np.ndarray
    ages: np.ndarray
    hits: np.ndarray
    trails: tuple = ()

    def __post_init__(self):
        n = len(np.asarray(self.ids).reshape(-1))
        for field, (dtype, shape) in _FIELDS.items():
            value = getattr(self, field)
            arr = (
                np.array(value, dtype=dtype).reshape((n, *shape))
                if n
                else np.zeros((0, *shape), dtype)
            )
            arr.flags.writeable = False
            object.__setattr__(self, field, arr)
        trails = tuple(np.array(t, np.float64).reshape(-1, 3) for t in self.trails)
        if len(trails) != n:
            raise ValueError(f"trails: expected {n}, got {len(trails)}")
        for t in trails:
            t.flags.writeable = False
        object.__setattr__(self, "trails", trails)

    @classmethod
    def empty(cls) -> TrackedObjects:
        return cls(**{k: [] for k in _FIELDS})

    @classmethod
    def of_detections(cls, det: DetectionArrays, index, ids, ages, hits) -> TrackedObjects:
        """Tracks that carry detections ``det[index]`` unchanged (no velocity: NaN)."""
        index = np.asarray(index, np.int64)
        n = len(index)
        return cls(
            ids=ids,
            names=det.names[index],
            scores=det.scores[index],
            boxes_2d=det.boxes_2d[index],
            dimensions=det.dimensions[index],
            locations=det.locations[index],
            rotation_y=det.rotation_y[index],
            velocities=np.full((n, 3), np.nan),
            velocity_covariances=np.full((n, 3, 3), np.nan),
            ages=ages,
            hits=hits,
            trails=tuple(det.locations[i : i + 1] for i in index),
        )

    @property
    def alpha(self) -> np.ndarray:
        return alpha_from_rotation_y(self.rotation_y, self.locations)

    @property
    def speeds(self) -> np.ndarray:
        """(N,) m/s (NaN where no velocity is estimated)."""
        return np.linalg.norm(self.velocities, axis=1)

    def __len__(self) -> int:
        return int(self.ids.shape[0])

    def __getitem__(self, i: int) -> TrackedObject:
        return self._object(i, self.alpha, self.speeds)

    def __iter__(self) -> Iterator[TrackedObject]:
        alpha, speeds = self.alpha, self.speeds  # once for all tracks, not once per track
        return (self._object(i, alpha, speeds) for i in range(len(self)))

    def _object(self, i: int, alpha: np.ndarray, speeds: np.ndarray) -> TrackedObject:
        return TrackedObject(
            track_id=int(self.ids[i]),
            name=str(self.names[i]),
            score=float(self.scores[i]),
            box_2d=tuple(float(v) for v in self.boxes_2d[i]),
            dimensions=tuple(float(v) for v in self.dimensions[i]),
            location=tuple(float(v) for v in self.locations[i]),
            rotation_y=float(self.rotation_y[i]),
            alpha=float(alpha[i]),
            velocity=tuple(float(v) for v in self.velocities[i]),
            speed=float(speeds[i]),
            age=int(self.ages[i]),
            hits=int(self.hits[i]),
        )

    def __repr__(self) -> str:
        return f"TrackedObjects({len(self)} tracks; ids {self.ids.tolist()})"

    def to_kitti_objects(self) -> KittiObjects:
        """As :class:`KittiObjects` (no ids; for the detection pictures and result files)."""
        return KittiObjects.predictions(
            type=self.names,
            alpha=self.alpha,
            bbox=self.boxes_2d,
            dimensions=self.dimensions,
            location=self.locations,
            rotation_y=self.rotation_y,
            score=self.scores,
        )

    def to_kitti_tracking_lines(self, frame: int) -> list[str]:
        """KITTI tracking result lines of frame ``frame`` (no newline): ``frame id type -1 -1
        alpha x1 y1 x2 y2 h w l x y z ry score``."""
        return kitti_tracking_lines(frame, self.ids, self.to_kitti_objects())

    def to_dict(self) -> dict[str, list]:
        """``{'objects': [{'track_id', 'name', 'score', 'box_2d', 'dimensions', 'location',
        'rotation_y', 'alpha', 'velocity', 'speed', 'age', 'hits'}, ...]}`` (JSON ready;
        NaN velocities become None)."""
        out = []
        for obj in self:
            record = dataclasses.asdict(obj)
            if not np.isfinite(obj.speed):
                record["velocity"], record["speed"] = None, None
            out.append(record)
        return {"objects": out}


def kitti_tracking_lines(frame: int, ids: np.ndarray, objects: KittiObjects) -> list[str]:
    """KITTI tracking result lines (no newline) of ``objects`` with track ``ids`` in ``frame``:
    truncation and occlusion unknown (``-1 -1``), the score last."""
    lines = []
    text = format_label(objects, with_score=True).splitlines()
    for line, track in zip(text, np.asarray(ids).tolist(), strict=True):
        name, _, _, rest = line.split(" ", 3)
        lines.append(f"{int(frame)} {int(track)} {name} -1 -1 {rest}")
    return lines
