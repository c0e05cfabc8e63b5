"""The cache root where generated data (the embedded dataset, driving clips) is placed."""

from __future__ import annotations

import os
from pathlib import Path


def default_cache_dir() -> Path:
    """``$GAC_JAX_CACHE`` or ``~/.cache/gac_jax``: where the embedded dataset is generated."""
    return Path(os.environ.get("GAC_JAX_CACHE", Path.home() / ".cache" / "gac_jax"))
