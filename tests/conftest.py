"""Shared pytest fixtures."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
KITTI_SAMPLES = SHARED / "data" / "kitti_samples"

# A compilation cache for this test session only: trainer tests build the same jitted
# programs in several runs (uninterrupted, stopped, resumed); each is compiled once. Set
# before any compilation (JAX decides once per process whether the cache is used); removed
# at exit. GAC_JAX_TEST_COMPILE_CACHE=0 turns it off.
if os.environ.get("GAC_JAX_TEST_COMPILE_CACHE", "1") != "0":
    _cache_dir = tempfile.mkdtemp(prefix="gac_jax_test_xla_cache_")
    atexit.register(shutil.rmtree, _cache_dir, ignore_errors=True)
    jax.config.update("jax_compilation_cache_dir", _cache_dir)


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
