"""How long the device waits for the input pipeline: is the step input-bound?

The step loop dispatches step ``k`` asynchronously and then asks the loader for the batch of
step ``k + 1``. Time spent in that ``next()`` is lost only while the device has nothing left
to do, i.e. after step ``k`` finished. :class:`DataWaitClock` counts exactly that overlap:

    wait_k = max(0, t_batch_ready - max(t_next_called, t_step_k_done))

``t_step_k_done`` comes from a background thread that blocks on each dispatched step's outputs
(it releases the GIL while it waits, so the loop is not slowed). A loader that keeps up (a
filled prefetch buffer) gives ~0 however the loop runs ahead of the device; a loader slower
than the device gives its share of the wall time. The wait for the very first batch (worker
start-up, before any step) is not counted.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Iterator
from typing import Any

import jax


class _Dispatched:
    """One dispatched step: its outputs and when the device finished them."""

    def __init__(self, outputs: Any):
        leaves = jax.tree.leaves(outputs)
        self.probe = leaves[0] if leaves else None
        self.outputs = outputs
        self.done_at: float | None = None
        self.done = threading.Event()


class DataWaitClock:
    """Seconds the device waited for batches (see the module docstring).

    Use::

        clock = DataWaitClock()
        for batch in clock.batches(loader_iterator):
            state, metrics = step(state, batch)
            clock.dispatched(metrics)
            ...
            seconds = clock.take()  # waited since the last take()
        clock.close()
    """

    def __init__(self):
        self._last: _Dispatched | None = None
        self._waited = 0.0
        self._queue: queue.SimpleQueue[_Dispatched | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._watch, name="data-wait-clock", daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        while (item := self._queue.get()) is not None:
            # A failed step is reported by the loop itself.
            with contextlib.suppress(Exception):
                jax.block_until_ready(item.outputs)
            item.done_at = time.perf_counter()
            item.outputs = None
            item.done.set()

    def dispatched(self, outputs: Any) -> None:
        """After dispatching a step: ``outputs`` are (any of) its results."""
        item = _Dispatched(outputs)
        self._last = item
        self._queue.put(item)

    def batches(self, iterator: Iterator[dict]) -> Iterator[dict]:
        """Yields from ``iterator``, counting the device's wait for each batch."""
        iterator = iter(iterator)
        while True:
            start = time.perf_counter()
            try:
                batch = next(iterator)
            except StopIteration:
                return
            self._waited += self._idle_during(start, time.perf_counter())
            yield batch

    def _idle_during(self, start: float, end: float) -> float:
        last = self._last
        if last is None:  # before the first step: start-up, not a stall
            return 0.0
        if not last.done.is_set():
            probe_ready = last.probe is None or last.probe.is_ready()
            if not probe_ready:
                return 0.0  # the device was still busy when the batch arrived
            last.done.wait(1.0)  # done: the watcher records the time at once
        done_at = last.done_at if last.done_at is not None else start
        return max(0.0, end - max(start, done_at))

    def take(self) -> float:
        """Seconds waited since the previous call (or since the start)."""
        waited, self._waited = self._waited, 0.0
        return waited

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=5.0)
