"""The tracker's parameters (:class:`TrackerParams`) and their place in a config (``track``).

Every detector config carries a ``track`` section (:func:`track_config`); a run folder trained
before the section existed gets the defaults. Units: metres, seconds, radians.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import ml_collections


@dataclasses.dataclass(frozen=True)
class TrackerParams:
    """Parameters of :class:`~gac_jax.tracking.tracker.Tracker` (and of the 2D baseline).

    Attributes:
      min_hits: detections a track needs before it is reported (birth).
      max_misses: frames in a row without a detection before a reported track ends (death);
        a track not yet reported ends at its first miss.
      min_score: detections scoring below this are not tracked.
      frame_rate: frames per second assumed between updates without timestamps.
      accel_std: process noise: white acceleration (m/s^2) of the constant-velocity model.
      yaw_rate_std: process noise of the heading (rad/s).
      depth_std, depth_std_per_m: a detection's error along its viewing ray: ``depth_std +
        depth_std_per_m * distance`` (monocular depth error grows with distance).
      lateral_std, lateral_std_per_m: its error across the ray, alike.
      yaw_std: a detection's heading error (rad).
      initial_speed_std: velocity uncertainty of a new track (m/s).
      gate_chi2: association gate on the squared Mahalanobis distance of the centres
        (3 degrees of freedom; 16.27 keeps 99.9 % of true matches).
      iou_weight: first stage: weight of ``1 - IoU`` (detection's 2D box with the track's
        last one) beside ``d2 / gate_chi2`` in the assignment cost.
      min_iou_2d: second stage: a track and a detection left over by the 3D stage are
        matched on their 2D boxes when the IoU is at least this.
      size_window: the box size is the running mean of up to this many detections.
      trail_length: positions kept per track for drawing its trail.
    """

    min_hits: int = 3
    max_misses: int = 4
    min_score: float = 0.0
    frame_rate: float = 10.0
    accel_std: float = 2.0
    yaw_rate_std: float = 0.5
    depth_std: float = 0.3
    depth_std_per_m: float = 0.02  # tuned on generated clips of seed 7 (docs/results.md)
    lateral_std: float = 0.1
    lateral_std_per_m: float = 0.005
    yaw_std: float = 0.15
    initial_speed_std: float = 10.0
    gate_chi2: float = 16.27
    iou_weight: float = 1.0
    min_iou_2d: float = 0.3
    size_window: int = 20
    trail_length: int = 20

    def __post_init__(self):
        for name in ("min_hits", "max_misses", "size_window", "trail_length"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"track.{name}: expected an integer >= 1, got {value!r}")
        positive = ("frame_rate", "accel_std", "yaw_rate_std", "depth_std", "lateral_std")
        for name in positive + ("yaw_std", "initial_speed_std", "gate_chi2"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or not value > 0:
                raise ValueError(f"track.{name}: expected a number > 0, got {value!r}")
        for name in ("depth_std_per_m", "lateral_std_per_m", "min_score", "iou_weight"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"track.{name}: expected a number >= 0, got {getattr(self, name)}")
        if not 0 < self.min_iou_2d <= 1:
            raise ValueError(
                f"track.min_iou_2d: expected a number in (0, 1], got {self.min_iou_2d}"
            )

    @classmethod
    def from_config(cls, config: Any = None, **overrides) -> TrackerParams:
        """Parameters of a whole config (its ``track`` section, defaults where absent), of a
        ``track`` section or mapping alone, or of another :class:`TrackerParams`; then
        ``overrides``. Unknown keys raise ``ValueError`` naming them."""
        if config is None:
            values: dict = {}
        elif isinstance(config, TrackerParams):
            values = dataclasses.asdict(config)
        else:
            if hasattr(config, "to_dict"):  # a ConfigDict
                config = config.to_dict()
            if not isinstance(config, Mapping):
                raise ValueError(
                    f"expected a config, a track section or TrackerParams, got {config!r}"
                )
            if "track" in config:
                values = dict(config["track"])
            else:  # a track section, or a run config from before the section: defaults
                values = {} if _is_run_config(config) else dict(config)
        values.update(overrides)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown tracker parameter(s): {', '.join(unknown)}")
        return cls(**values)


def _is_run_config(values: Mapping) -> bool:
    """A whole config (model, data, ...) rather than a ``track`` section."""
    return bool({"model", "data"} & set(values))


def track_config() -> ml_collections.ConfigDict:
    """The ``track`` section of a config: :class:`TrackerParams`' defaults."""
    return ml_collections.ConfigDict(dataclasses.asdict(TrackerParams()))
