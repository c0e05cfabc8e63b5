"""One random view per frame and epoch (the reference depth trainer's left/right choice)."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.kitti_depth import DepthFrame
from gac_jax.data.view_sampling import RandomViewLoader, view_groups

DRIVE = "2011_09_26_drive_0001_sync"


class FrameSource:
    """Camera-major items like KittiDepthSource; frame 3 has no right view."""

    def __init__(self, num_frames: int = 6):
        left = [DepthFrame(DRIVE, f"{i:010d}", 2) for i in range(num_frames)]
        right = [DepthFrame(DRIVE, f"{i:010d}", 3) for i in range(num_frames) if i != 3]
        self.frames = left + right

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, i):
        f = self.frames[i]
        return {"frame": np.int32(int(f.frame)), "camera": np.int32(f.camera)}


def to_arrays(sample):
    return {"frame": sample["frame"], "camera": sample["camera"]}


def test_view_groups_pair_the_views_of_a_frame():
    source = FrameSource()
    groups = view_groups(source.frames)
    assert groups.shape == (6, 2)
    for row, (left, right) in enumerate(groups):
        assert source.frames[left] == DepthFrame(DRIVE, f"{row:010d}", 2)
        if row == 3:
            assert right == -1
        else:
            assert source.frames[right] == DepthFrame(DRIVE, f"{row:010d}", 3)
    with pytest.raises(ValueError, match="listed twice"):
        view_groups(source.frames + source.frames[:1])


def test_each_epoch_visits_every_frame_once_as_a_random_view():
    source = FrameSource()
    loader = RandomViewLoader(
        source, view_groups(source.frames), None, to_arrays, batch_size=2, seed=3
    )
    assert loader.steps_per_epoch == 3  # 6 frames, not 11 views
    cameras = []
    for epoch in range(8):
        batches = list(loader.epoch(epoch))
        frames = np.concatenate([b["frame"] for b in batches])
        assert sorted(frames.tolist()) == list(range(6))
        cam = dict(
            zip(
                frames.tolist(),
                np.concatenate([b["camera"] for b in batches]).tolist(),
                strict=True,
            )
        )
        assert cam[3] == 2  # the only view it has
        cameras.append([cam[i] for i in range(6)])
    cameras = np.asarray(cameras)
    both = np.delete(cameras, 3, axis=1)
    assert (both == 3).mean() == pytest.approx(0.5, abs=0.2)  # p = 0.5 each epoch
    assert len({tuple(row) for row in cameras}) > 1  # the choice changes between epochs
    # A pure function of (seed, step): a second loader (e.g. a resumed run) agrees.
    again = RandomViewLoader(
        source, view_groups(source.frames), None, to_arrays, batch_size=2, seed=3
    )
    for step in (0, 4, 17):
        a, b = loader.load_batch(step), again.load_batch(step)
        assert (
            a["frame"].tolist() == b["frame"].tolist()
            and a["camera"].tolist() == b["camera"].tolist()
        )


def test_sharded_loaders_split_each_global_batch():
    source = FrameSource()
    groups = view_groups(source.frames)
    shards = [
        RandomViewLoader(
            source, groups, None, to_arrays, batch_size=1, seed=0, shard_index=k, num_shards=2
        )
        for k in range(2)
    ]
    assert shards[0].steps_per_epoch == 3
    for step in range(3):
        frames = [int(s.load_batch(step)["frame"][0]) for s in shards]
        assert frames[0] != frames[1]
