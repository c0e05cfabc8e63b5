"""``train.profile_steps = (start, count)``: a ``jax.profiler`` trace of training steps
``start .. start + count - 1`` (step numbers as the progress line counts them, from 1).

The trace goes to ``WORKDIR/tensorboard`` in the TensorBoard profile plugin's layout
(``plugins/profile/<run>/*.xplane.pb``): ``tensorboard --logdir WORKDIR/tensorboard``, tab
"Profile" (needs ``pip install tensorboard-plugin-profile``), or Perfetto / XProf. Each step
carries a ``StepTraceAnnotation`` so the tools mark step boundaries. Compilation is not in the
trace (the step is compiled before the loop).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import jax

from gac_jax.config import ConfigError


def profile_range(value) -> tuple[int, int] | None:
    """``(start, count)`` from ``train.profile_steps`` (None: no profile)."""
    if value is None:
        return None
    try:
        start, count = (int(v) for v in value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"train.profile_steps: expected (start, count) such as (10, 3) or None, got {value!r}"
        ) from None
    if start < 1 or count < 1:
        raise ConfigError(f"train.profile_steps: start and count must be >= 1, got {value!r}")
    return start, count


class StepProfiler:
    """Starts and stops the trace around the configured steps (process 0 only)."""

    def __init__(self, steps: tuple[int, int] | None, logdir: Path, enabled: bool = True):
        self.steps = steps if enabled else None
        self.logdir = Path(logdir)
        self.active = False

    def step(self, step: int):
        """Context of dispatching step ``step``: starts the trace at the first profiled step
        and annotates the step."""
        if self.steps is not None and step == self.steps[0]:
            self.logdir.mkdir(parents=True, exist_ok=True)
            jax.profiler.start_trace(str(self.logdir))
            self.active = True
        if not self.active:
            return contextlib.nullcontext()
        return jax.profiler.StepTraceAnnotation("train", step_num=step)

    def after(self, step: int, outputs: Any) -> None:
        """After dispatching step ``step``: stops the trace after its last profiled step
        (once that step has finished on the device)."""
        if self.active and step >= self.steps[0] + self.steps[1] - 1:
            self.stop(outputs)

    def stop(self, outputs: Any = None) -> None:
        if not self.active:
            return
        self.active = False
        if outputs is not None:
            jax.block_until_ready(outputs)
        jax.profiler.stop_trace()
        start, count = self.steps
        print(
            f"profile of steps {start}-{start + count - 1} in {self.logdir / 'plugins' / 'profile'}"
            " (tensorboard --logdir, tab Profile)",
            flush=True,
        )
