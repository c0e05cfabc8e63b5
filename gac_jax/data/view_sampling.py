"""One view per stereo frame and epoch: the reference depth trainer's random left/right choice.

KITTI-depth annotates both rectified colour cameras (2 and 3) of every frame. The
reference's dataset has one item per frame and picks the left or the right view
(p = 0.5) each time it is read, so an epoch is one pass over the *frames*. Treating
both views as separate items (what :class:`~gac_jax.data.loader.Loader` does with a
two-camera source) doubles the epoch instead, which changes a per-epoch schedule.

:class:`RandomViewLoader` keeps the reference's epoch: epoch ``e`` visits every frame
once, as the view drawn from ``(seed, e)``, in a shuffled order; like the Loader, the
order and the view of any step are pure functions of ``(seed, step)`` (resumable,
identical on every process).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from gac_jax.data.kitti_depth import DepthFrame
from gac_jax.data.loader import Loader


def view_groups(frames: Sequence[DepthFrame]) -> np.ndarray:
    """Groups a depth source's items by (drive, frame).

    Args:
      frames: the source's items in source order (``KittiDepthSource.frames``).
    Returns:
      (N, 2) int64 source indices ``[camera-2 item, camera-3 item]`` per distinct
      (drive, frame), -1 where that view is absent; rows sorted by (drive, frame).
    """
    rows: dict[tuple[str, str], list[int]] = {}
    for index, f in enumerate(frames):
        slot = rows.setdefault((f.drive, f.frame), [-1, -1])
        column = f.camera - 2
        if column not in (0, 1):
            raise ValueError(f"camera must be 2 or 3, got {f.camera} ({f.frame_id})")
        if slot[column] != -1:
            raise ValueError(f"{f.frame_id} camera {f.camera} is listed twice")
        slot[column] = index
    if not rows:
        raise ValueError("no frames to group")
    return np.asarray([rows[k] for k in sorted(rows)], np.int64).reshape(-1, 2)


class RandomViewLoader(Loader):
    """A :class:`Loader` whose epoch visits every row of ``groups`` once, as one random view.

    Args:
      source: the two-camera source (``len``, ``[i] -> sample``).
      groups: (N, 2) source indices per frame (:func:`view_groups`), -1 = view absent
        (frames with one view always use it).
      transform, to_arrays, **kwargs: as for :class:`Loader` (``batch_size``, ``seed``,
        ``shuffle``, ``drop_remainder``, sharding, workers ...).

    ``steps_per_epoch`` counts frames, not views.
    """

    def __init__(self, source, groups: np.ndarray, transform, to_arrays, **kwargs):
        super().__init__(source, transform, to_arrays, **kwargs)
        groups = np.asarray(groups, np.int64)
        if groups.ndim != 2 or groups.shape[1] != 2 or len(groups) == 0:
            raise ValueError(f"groups must be a non-empty (N, 2) index table, got {groups.shape}")
        if (groups.max(axis=1) < 0).any() or groups.max() >= len(source):
            raise ValueError("every frame needs a view, and view indices must index the source")
        self.groups = groups
        self.num_records = len(groups)
        g = self.global_batch_size
        n = self.num_records
        self.steps_per_epoch = n // g if self.drop_remainder else math.ceil(n / g)
        if self.steps_per_epoch == 0:
            raise ValueError(f"{n} frames are fewer than one global batch of {g}")

    def epoch_order(self, epoch: int) -> np.ndarray:
        """(N,) source indices: a view of every frame, in the order epoch ``epoch`` visits them."""
        cached = self._order
        if cached is not None and cached[0] == epoch:
            return cached[1]
        rng = np.random.default_rng([self.seed, epoch, 2])
        right = rng.random(len(self.groups)) < 0.5
        pick = np.where(right, self.groups[:, 1], self.groups[:, 0])
        pick = np.where(pick < 0, self.groups.max(axis=1), pick)  # the only view there is
        if self.shuffle:
            pick = pick[np.random.default_rng([self.seed, epoch, 0]).permutation(len(pick))]
        self._order = (epoch, pick)
        return pick
