"""Shared pytest fixtures."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED = REPO_ROOT.parent / "shared"
KITTI_SAMPLES = SHARED / "data" / "kitti_samples"


_JIT_CACHE: str | None = None


def pytest_configure(config):
    """One persistent XLA compilation cache per test session (subprocesses inherit it).

    Tests compile the same tiny models many times (in-process and in the train.py
    subprocesses of the kill/resume tests); the cache makes repeats cheap. It lives in a
    fresh temporary folder, so no state survives the session.
    """
    global _JIT_CACHE
    _JIT_CACHE = tempfile.mkdtemp(prefix="gac_jax_test_jit_cache_")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _JIT_CACHE
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"


def pytest_unconfigure(config):
    if _JIT_CACHE:
        shutil.rmtree(_JIT_CACHE, ignore_errors=True)


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
