"""Default XLA CPU flags of the entry points."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from gac_jax.cpu_backend import DEFAULT_FLAGS, apply_default_xla_flags

REPO = Path(__file__).resolve().parents[1]


def test_defaults_are_added_to_existing_flags():
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    flags = apply_default_xla_flags(env)
    assert flags.startswith("--xla_force_host_platform_device_count=2 ")
    assert all(f in flags for f in DEFAULT_FLAGS)
    assert apply_default_xla_flags(env) == flags  # idempotent


def test_user_setting_wins_and_opt_out():
    env = {"XLA_FLAGS": "--xla_cpu_experimental_ynn_fusion_type=dot"}
    assert apply_default_xla_flags(env) == "--xla_cpu_experimental_ynn_fusion_type=dot"
    env = {"GAC_JAX_DEFAULT_XLA_FLAGS": "0"}
    assert apply_default_xla_flags(env) == ""
    assert "XLA_FLAGS" not in env


def test_jax_accepts_the_flags():
    """The flags are known to this jaxlib (an unknown flag aborts the backend start)."""
    env = dict(os.environ, XLA_FLAGS=" ".join(DEFAULT_FLAGS))
    code = "import jax, jax.numpy as jnp; print(float(jnp.ones(3).sum()))"
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "3.0"
