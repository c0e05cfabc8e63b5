"""The train step as both trainers run it: compiled ahead of time, timed, profiled.

:class:`StepRunner` wraps the jitted ``step(state, batch) -> (state, metrics)``:

* the first call compiles it (``.lower(...).compile()``, announced with its seconds) and
  prints what the compiled step needs per device next to what the device has
  (:mod:`gac_jax.training.step_memory`); later calls run that executable;
* :meth:`batches` times the device's wait for the input pipeline
  (:mod:`gac_jax.training.data_wait`); :meth:`take_data_wait` hands the seconds to the
  progress line;
* ``train.profile_steps`` traces those steps (:mod:`gac_jax.training.step_profiler`);
* :meth:`raise_if_out_of_memory` turns XLA's out-of-memory error into one line naming
  ``data.batch_size``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from gac_jax.training import parallel
from gac_jax.training.data_wait import DataWaitClock
from gac_jax.training.step_memory import (
    StepMemory,
    compile_step,
    memory_line,
    raise_if_out_of_memory,
)
from gac_jax.training.step_profiler import StepProfiler, profile_range


class StepRunner:
    """See the module docstring.

    Args:
      jitted: the ``jax.jit`` train step (state donated).
      mesh: the data mesh (batches are sharded over it with :func:`parallel.to_global`).
      batch_size: the global ``data.batch_size`` (named in the out-of-memory line).
      profile_steps: ``train.profile_steps`` (None: no trace).
      tensorboard_dir: where the trace goes (``WORKDIR/tensorboard``).
      announce: print the compile and memory lines (process 0).
    """

    def __init__(
        self,
        jitted,
        mesh,
        *,
        batch_size: int,
        profile_steps=None,
        tensorboard_dir: Path,
        announce: bool = True,
    ):
        self.jitted, self.mesh = jitted, mesh
        self.batch_size, self.announce = batch_size, announce
        self.profiler = StepProfiler(profile_range(profile_steps), tensorboard_dir, announce)
        self.clock = DataWaitClock()
        self.compiled = None
        self.compile_s: float | None = None
        self.memory: StepMemory | None = None

    def batches(self, iterator: Iterator[dict]) -> Iterator[dict]:
        """The host batches of ``iterator``, with the device's wait for each counted."""
        return self.clock.batches(iterator)

    def __call__(self, state, host_batch: dict, step: int):
        """Runs training step ``step`` (counted from 1) on this process's ``host_batch``."""
        batch = parallel.to_global(host_batch, self.mesh)
        if self.compiled is None:
            self.compiled, self.compile_s = compile_step(
                self.jitted, state, batch, announce=self.announce
            )
            self.memory = StepMemory.of(self.compiled)
            if self.announce:
                print(memory_line(self.memory), flush=True)
        with self.profiler.step(step):
            state, metrics = self.compiled(state, batch)
        self.clock.dispatched(metrics)
        self.profiler.after(step, metrics)
        return state, metrics

    def take_data_wait(self) -> float:
        """Seconds the device waited for batches since the previous call."""
        return self.clock.take()

    def compile_record(self) -> dict:
        """The ``kind='compile'`` metrics record: seconds and the per-device memory."""
        record = {"compile_s": self.compile_s}
        if self.memory is not None:
            record["memory_bytes"] = self.memory.as_record()
        return record

    def raise_if_out_of_memory(self, error: BaseException) -> None:
        raise_if_out_of_memory(error, self.batch_size, self.memory)

    def close(self) -> None:
        self.profiler.stop()
        self.clock.close()
