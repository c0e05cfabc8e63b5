"""What every "run a trained model" command shares: its arguments and CPU threads.

``evaluate.py --workdir W`` (model mode) and ``python -m gac_jax.cli.predict`` take the same
model arguments; the run config comes from :mod:`gac_jax.trained.run_config`.

CPU threads: XLA's CPU client sizes its compute thread pool (threads named
``tf_XLAEigen``) by the CPU affinity of the process when the backend starts,
and has no flag for it (``--xla_cpu_multi_thread_eigen=false`` only forces one
thread). :func:`limit_cpu_threads` therefore narrows the affinity before JAX
starts, like ``taskset -c 0-1 python evaluate.py ...``. The default is every core
the process may use (2 on the evaluation machine).
"""

from __future__ import annotations

import argparse
import os

from gac_jax.deploy.int8 import INT8_OPTIONS, add_int8_arguments
from gac_jax.streams.thread_budget import xla_threads


def add_model_mode_arguments(parser: argparse.ArgumentParser) -> None:
    """The model-mode options of ``evaluate.py`` (task-independent)."""
    g = parser.add_argument_group(
        "model mode (--workdir): run a trained model on a split, write result files, score them"
    )
    g.add_argument("--workdir", help="training workdir (config.json, checkpoints/, priors)")
    g.add_argument("--config", help="config file[:arg] instead of WORKDIR/config.json")
    g.add_argument("--data", metavar="DIR", help="dataset root (default: the config's data)")
    g.add_argument("--split", help="split to evaluate (default: the config's val split)")
    g.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    g.add_argument(
        "--checkpoint", metavar="DIR", help="converted weights (python -m gac_jax.weights.convert)"
    )
    g.add_argument("--batch-size", type=int, help="images per model call (default: config)")
    g.add_argument(
        "--save-images", type=int, default=0, metavar="K", help="draw the first K frames"
    )
    g.add_argument(
        "--threads", type=int, help="CPU threads of the XLA backend (default: every usable core)"
    )
    g.add_argument(
        "--runtime",
        choices=RUNTIME_CHOICES,
        help="what runs the network: jax (default, jitted) or the exported ONNX file in "
        "onnxruntime / openvino (exported into the run folder when absent)",
    )
    g.add_argument(
        "--precision",
        choices=PRECISION_CHOICES,
        help="f32 (default), bf16 (openvino: native bf16 kernels where the CPU has them) or "
        "int8 (openvino: the network quantized by NNCF, calibrated on the training split)",
    )
    add_int8_arguments(g)
    g.add_argument(
        "--export", metavar="DIR", help="export folder to use (default: W/export/<weights>)"
    )
    g.add_argument("overrides", nargs="*", help="config overrides key.sub=value (model mode)")


MODEL_MODE_OPTIONS = (
    "config", "data", "split", "step", "checkpoint", "batch_size", "threads", "overrides",
    "runtime", "precision", "export", *INT8_OPTIONS,
)  # fmt: skip


RUNTIME_CHOICES = ("jax", "onnxruntime", "openvino")  # gac_jax.deploy.runtimes.RUNTIMES


PRECISION_CHOICES = ("f32", "bf16", "int8")  # gac_jax.deploy.runtimes.PRECISIONS


def reject_model_mode_arguments(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """Offline mode: model-mode options without ``--workdir`` are an error, not ignored."""
    given = [name for name in MODEL_MODE_OPTIONS if getattr(args, name, None)]
    if getattr(args, "save_images", 0):
        given.append("save_images")
    if given:
        flags = ", ".join(
            "key=value overrides" if g == "overrides" else "--" + g.replace("_", "-") for g in given
        )
        parser.error(f"{flags} only apply with --workdir (model mode)")


def backend_started() -> bool:
    from jax._src import xla_bridge

    return xla_bridge.backends_are_initialized()


def available_cores() -> list[int]:
    """The CPU cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def limit_cpu_threads(threads: int | None) -> int:
    """Restricts XLA's CPU compute threads to ``threads`` cores; returns the count in effect.

    Must run before JAX starts its backend (first computation or ``jax.devices()``);
    afterwards only the current count is accepted. ``None`` keeps every usable core.

    Raises:
      ValueError: ``threads`` < 1, more than the usable cores, or the backend already
        runs with another count (start a fresh process, or use ``taskset``).
    """
    cores = available_cores()
    if threads is None:
        return len(cores)
    if threads < 1 or threads > len(cores):
        raise ValueError(f"--threads must be in [1, {len(cores)}] (usable cores), got {threads}")
    if threads == len(cores):
        return threads
    if backend_started():
        raise ValueError(
            f"--threads {threads}: JAX already runs with {len(cores)} threads in this process; "
            "set it before the first JAX computation (or run under taskset)"
        )
    if not hasattr(os, "sched_setaffinity"):
        raise ValueError("--threads needs os.sched_setaffinity (Linux); use taskset instead")
    os.sched_setaffinity(0, cores[:threads])
    return threads


def xla_thread_count() -> int | None:
    """Number of XLA CPU compute threads alive in this process (Linux; None elsewhere)."""
    return xla_threads()
