"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
KITTI_SAMPLES = SHARED / "data" / "kitti_samples"


@pytest.fixture(scope="session")
def kitti_samples() -> Path:
    """Root of the real KITTI sample frames (``../shared/data/kitti_samples``); skips if absent."""
    if not (KITTI_SAMPLES / "object" / "training" / "calib").is_dir():
        pytest.skip(f"real KITTI samples not found at {KITTI_SAMPLES}")
    return KITTI_SAMPLES


@pytest.fixture(scope="session")
def kitti_object_root(kitti_samples: Path) -> Path:
    """KITTI object root of the 13 labeled real frames (split ``labeled``)."""
    return kitti_samples / "object"
