"""Checks every share option of the generator (``photo``, ``large_vehicles``, ``gardens``, ...)
passes the same way: how a dataset records it, how its cache folder is named, and that a
frame drawn with it is deterministic per seed while share 0 is the frame without it."""

from __future__ import annotations

import ml_collections
import numpy as np
import pytest

from gac_jax.builders.datasets import SHARE_SUFFIXES, synthetic_config, synthetic_dataset_dir
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.data.synthetic.writer import DatasetSpec


def check_described_and_named(key: str, share: float, invalid: float) -> None:
    """``DatasetSpec`` records ``key`` only when set, refuses ``invalid``, and the cache
    folder gets ``_<suffix><share>``."""
    # (a dataset without it is described as before, so existing caches stay valid)
    assert key not in DatasetSpec(num_frames=4, seed=3).to_json()
    assert DatasetSpec(num_frames=4, seed=3, **{key: share}).to_json()[key] == share
    with pytest.raises(ValueError, match=f"{key} must be a share"):
        DatasetSpec(num_frames=4, seed=3, **{key: invalid}).validate()
    cfg = ml_collections.ConfigDict({"source": "synthetic", "synthetic": synthetic_config()})
    plain_dir = synthetic_dataset_dir(cfg)
    cfg.synthetic[key] = share
    assert synthetic_dataset_dir(cfg).name == f"{plain_dir.name}_{SHARE_SUFFIXES[key]}{share:g}"


def check_deterministic_and_zero(key: str, index: int, size, plain, frame, depth=False) -> None:
    """``frame`` (seed 0, ``key`` = 1) is drawn again identically (both views, labels; the
    depth maps too with ``depth``), seed 1 differs, and ``key`` = 0 gives ``plain``."""
    again = make_frame(0, index, size, **{key: 1.0})
    for cam in (2, 3):
        np.testing.assert_array_equal(again.views[cam].image, frame.views[cam].image)
        if depth:
            np.testing.assert_array_equal(again.views[cam].depth, frame.views[cam].depth)
    np.testing.assert_array_equal(again.objects.bbox, frame.objects.bbox)
    other = make_frame(1, index, size, **{key: 1.0})
    assert not np.array_equal(other.views[2].image, frame.views[2].image)
    zero = make_frame(0, index, size, **{key: 0.0})
    np.testing.assert_array_equal(zero.views[2].image, plain.views[2].image)
