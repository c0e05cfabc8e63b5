"""Default XLA flags for the CPU backend, applied by the entry points before JAX starts.

Measured with ``benchmarks/bench_train_step.py`` (default detector config, batch 8; run it
with ``GAC_JAX_DEFAULT_XLA_FLAGS=0`` for JAX's own flags): XLA's experimental YNNPACK
fusions make the train step slower, 0.94 s vs 0.62 s per step on a 2-core Intel Xeon and
2.49 s vs 1.10 s on a 2-core AMD EPYC, so the entry points (and the benchmarks) switch them
off with ``--xla_cpu_experimental_ynn_fusion_type=`` (an empty list of fusion types).
Flags only affect the CPU backend. A user's own ``XLA_FLAGS`` entry for the same flag wins, and
``GAC_JAX_DEFAULT_XLA_FLAGS=0`` leaves ``XLA_FLAGS`` untouched.
"""

from __future__ import annotations

import os
import platform
from collections.abc import MutableMapping
from pathlib import Path

DEFAULT_FLAGS = ("--xla_cpu_experimental_ynn_fusion_type=",)


def apply_default_xla_flags(env: MutableMapping[str, str] | None = None) -> str:
    """Adds :data:`DEFAULT_FLAGS` to ``XLA_FLAGS`` (unless set or disabled); returns the value.

    Must run before JAX initialises its backend (importing jax is fine; creating arrays
    is not), so entry points call it first thing.
    """
    env = os.environ if env is None else env
    flags = env.get("XLA_FLAGS", "")
    if env.get("GAC_JAX_DEFAULT_XLA_FLAGS", "1") == "0":
        return flags
    for flag in DEFAULT_FLAGS:
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
    env["XLA_FLAGS"] = flags
    return flags


def cpu_model() -> str:
    """The CPU's model name (``/proc/cpuinfo``; else what ``platform`` knows), for the notes
    that say which machine measured a figure."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"
