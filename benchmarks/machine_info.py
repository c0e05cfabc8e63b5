"""The machine a benchmark ran on: CPU model, cores, load, library versions.

Every benchmark prints this beside its figures, so a number is never quoted
without the machine (and the load) it was measured on.
"""

from __future__ import annotations

import importlib
import os
import platform
from pathlib import Path


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


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
