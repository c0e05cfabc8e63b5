"""The machine a benchmark ran on: CPU model, cores, load, library versions.

Every benchmark prints this beside its figures, so a number is never quoted
without the machine (and the load) it was measured on.
"""

from __future__ import annotations

import importlib
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gac_jax.cpu_backend import cpu_model  # noqa: E402

__all__ = ["cpu_model", "describe_machine", "one_line"]


def describe_machine(*libraries: str) -> dict:
    """Cores, CPU model, 1-minute load average now, Python and the given libraries' versions."""
    info = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "python": platform.python_version(),
    }
    for name in libraries:
        module = importlib.import_module(name)
        info[name] = getattr(module, "__version__", "?")
    if "jax" in libraries:
        import jax

        info["devices"] = [str(d) for d in jax.devices()]
        info["xla_flags"] = os.environ.get("XLA_FLAGS", "")
    return info


def one_line(info: dict) -> str:
    extras = ", ".join(f"{k} {v}" for k, v in info.items() if k not in ("cpu", "cores", "platform"))
    return f"{info['cores']} cores, {info['cpu']}, {extras}"
