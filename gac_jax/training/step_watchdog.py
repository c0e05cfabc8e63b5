"""A watchdog for the training loop of multi-process runs: a peer that hangs (or dies without
the coordination service noticing) stops this process with the peer-lost exit status."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import jax

from gac_jax.training import multiprocess
from gac_jax.training.multiprocess import EXIT_PEER_LOST, _where


def _default_on_timeout(message: str) -> None:
    print(f"error: {message}", file=sys.stderr, flush=True)
    sys.stdout.flush()
    os._exit(EXIT_PEER_LOST)  # the main thread is stuck in a collective; no clean way out


class ProgressWatchdog:
    """Exits the process when training makes no progress for ``timeout_s`` seconds.

    A peer that hangs while alive (stuck I/O, a deadlock) still sends
    heartbeats, and the survivors would wait in the step's collective forever.
    The trainer calls :meth:`step` after dispatching every step; it waits for
    the *previous* step to finish (one step stays in flight) and restarts the
    clock, so the clock measures real progress. The clock starts at
    construction (the first step includes compilation). Exiting closes this
    process's connections, which stops the peers' collectives in turn.

    Active only in multi-process runs (``enabled=None``); elsewhere every call is
    free. ``on_timeout(message)`` defaults to printing and ``os._exit(3)``.
    """

    def __init__(
        self,
        timeout_s: float | None = None,
        hint: str = "",
        enabled: bool | None = None,
        on_timeout: Callable[[str], None] | None = None,
        poll_s: float = 0.5,
    ):
        self.timeout_s = (
            multiprocess.settings.step_timeout if timeout_s is None else float(timeout_s)
        )
        self.hint = hint
        self.enabled = jax.process_count() > 1 if enabled is None else enabled
        self._on_timeout = on_timeout or _default_on_timeout
        self._pending = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._deadline: float | None = None
        self._phase = "the first training step (includes compilation)"
        self._thread = None
        if self.enabled:
            self._arm(self._phase)
            self._thread = threading.Thread(
                target=self._watch, args=(poll_s,), name="gac-watchdog", daemon=True
            )
            self._thread.start()

    def _arm(self, phase: str) -> None:
        with self._lock:
            self._phase = phase
            self._deadline = time.monotonic() + self.timeout_s

    def _watch(self, poll_s: float) -> None:
        while not self._stop.wait(poll_s):
            with self._lock:
                expired = self._deadline is not None and time.monotonic() > self._deadline
                phase = self._phase
            if expired:
                self._stop.set()
                self._on_timeout(
                    f"{_where()}: no progress for {self.timeout_s:g} s while waiting for "
                    f"{phase}; another process probably hung or died. Stopping instead of "
                    f"waiting forever (timeout: --step-timeout / GAC_STEP_TIMEOUT). {self.hint}"
                )

    def step(self, step: int, outputs: Any) -> None:
        """After dispatching step ``step`` (outputs: any of its results)."""
        if not self.enabled:
            return
        if self._pending is not None:
            jax.block_until_ready(self._pending)
        self._pending = outputs
        self._arm(f"training step {step} to finish")

    @contextlib.contextmanager
    def paused(self) -> Iterator[None]:
        """No deadline inside (work with its own timeout); the clock restarts after."""
        if not self.enabled:
            yield
            return
        if self._pending is not None:
            jax.block_until_ready(self._pending)
            self._pending = None
        with self._lock:
            self._deadline = None
        try:
            yield
        finally:
            self._arm("the next training step")

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> ProgressWatchdog:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
