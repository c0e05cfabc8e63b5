"""The model arguments the API's ``from_workdir`` / ``from_weights`` share: runtime,
precision, threads, batch size, and the translation of the loaders' file errors into
:class:`~gac_jax.api.inputs.InputError`."""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Iterator
from pathlib import Path

from gac_jax.api.inputs import InputError, check_choice, check_positive_int
from gac_jax.data.files import KittiFormatError
from gac_jax.deploy.runtimes import (
    PRECISIONS,
    RUNTIMES,
    RuntimeUnavailableError,
    check_runtime,
)


def check_runtime_choice(runtime: str, precision: str, threads: int | None) -> None:
    """Checks that ``runtime``/``precision`` can run here; emulated precisions (JAX bf16)
    give a ``UserWarning`` saying so.

    ``threads`` (CPU threads of ONNX Runtime / OpenVINO) cannot apply to ``jax``: XLA sizes
    its thread pool when JAX starts (from the process's CPU affinity, e.g. ``taskset``).

    Raises:
      InputError: an unknown runtime or precision, one that cannot run on this machine
        (missing package, no native bf16, int8 outside OpenVINO), ``threads`` < 1 or given
        with ``jax``.
    """
    check_choice(runtime, RUNTIMES, "runtime")
    check_choice(precision, PRECISIONS, "precision")
    check_positive_int(threads, "threads", allow_none=True)
    if threads is not None and runtime == "jax":
        raise InputError(
            "threads",
            "applies to runtime onnxruntime/openvino; JAX's CPU threads are fixed when it starts "
            "(run the process under taskset -c ... to limit them)",
        )
    try:
        note = check_runtime(runtime, precision)
    except RuntimeUnavailableError as e:
        raise InputError("precision" if precision != "f32" else "runtime", str(e)) from None
    if note:
        warnings.warn(note.removeprefix("note: "), UserWarning, stacklevel=3)


def model_options(
    runtime: str,
    precision: str,
    threads: int | None,
    batch_size: int,
    export_dir: str | os.PathLike | None,
) -> dict:
    """The checked keyword arguments every API model's constructor takes
    (:func:`check_runtime_choice`; ``batch_size`` >= 1)."""
    check_runtime_choice(runtime, precision, threads)
    return {
        "runtime": runtime,
        "precision": precision,
        "threads": threads,
        "batch_size": check_positive_int(batch_size, "batch_size"),
        "export_dir": export_dir,
    }


def check_workdir(workdir, name: str = "workdir") -> Path:
    if workdir is None or not Path(workdir).is_dir():
        raise InputError(name, f"{workdir}: not a folder")
    return Path(workdir)


@contextlib.contextmanager
def file_errors_as(argument: str) -> Iterator[None]:
    """A :class:`KittiFormatError` (missing or unfitting config, priors, checkpoint, export)
    inside the block becomes ``InputError(argument, <file>: <problem>)``."""
    try:
        yield
    except KittiFormatError as e:
        raise InputError(argument, str(e)) from None
