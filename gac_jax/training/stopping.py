"""Stopping a run on SIGTERM/SIGINT: finish the step, checkpoint, exit 75 (a second SIGINT
exits at once); multi-process runs stop at a common step through JAX's preemption service."""

from __future__ import annotations

import os
import signal
import threading

import jax

from gac_jax.training import workdir_lock
from gac_jax.training.multiprocess import (
    EXIT_INTERRUPTED,
    _say,
)  # noqa: F401

_stop = {"requested": False, "installed": False}


def _multi_process_started() -> bool:
    """Whether ``jax.distributed`` runs (without starting a backend, unlike process_count)."""
    from jax._src import distributed

    return distributed.global_state.client is not None


def install_stop_handlers() -> None:
    """SIGTERM and SIGINT stop the run after the current step, with a checkpoint.

    For entry points (``train.py``), from the main thread, after
    :func:`initialize_distributed`. The trainers poll :func:`preemption_requested`
    after every step; when it says so they save a checkpoint and raise
    :class:`PreemptedError` (exit status :data:`EXIT_PREEMPTED`).

    * Single process: either signal sets the flag that :func:`preemption_requested` reads.
    * Multi-process: SIGTERM belongs to JAX's preemption service (installed by
      ``jax.distributed.initialize``), which makes all processes agree on the step;
      a first SIGINT is passed on to it as a SIGTERM to this process.
    * A second SIGINT exits at once (status :data:`EXIT_INTERRUPTED`), without a
      checkpoint, even while the main thread waits inside XLA: the signal numbers
      reach a small thread through ``signal.set_wakeup_fd``, not the main thread's
      Python handlers (which run only between bytecodes).
    """
    if _stop["installed"]:
        return
    multi = _multi_process_started()
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    signals = (signal.SIGINT,) if multi else (signal.SIGINT, signal.SIGTERM)
    for signum in signals:
        # A Python-level handler makes CPython's C handler write to the wakeup fd.
        signal.signal(signum, lambda *_: None)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(
        target=_watch_stop_signals, args=(read_fd, multi), name="gac-signals", daemon=True
    ).start()
    _stop["installed"] = True


def _watch_stop_signals(read_fd: int, multi: bool) -> None:
    interrupts = 0
    while True:
        data = os.read(read_fd, 64)
        if not data:
            return
        for signum in data:
            if signum == signal.SIGINT:
                interrupts += 1
                if interrupts > 1:
                    _say("second interrupt: stopping now, without a checkpoint")
                    workdir_lock.release_all()
                    os._exit(EXIT_INTERRUPTED)
            elif signum != signal.SIGTERM:
                continue
            if _stop["requested"]:
                continue
            _stop["requested"] = True
            name = signal.Signals(signum).name
            _say(
                f"{name} received: stopping after the current step with a checkpoint "
                "(Ctrl-C again to stop at once, without one)"
            )
            if multi and signum == signal.SIGINT:
                os.kill(os.getpid(), signal.SIGTERM)  # JAX's preemption notifier takes it on


def stop_requested() -> bool:
    """Whether a stop signal arrived (this process; no synchronisation): for work before the
    first step, such as generating the embedded dataset, which stops at once."""
    return _stop["requested"]


def preemption_requested(step: int) -> bool:
    """True at the step where the run stops after a SIGTERM or SIGINT (see
    :func:`install_stop_handlers`).

    Must be called at every step by every process. Multi-process: all processes
    agree on the step (JAX's preemption sync point). Single process: the first
    call after the signal arrived.
    """
    if jax.process_count() == 1:
        return _stop["requested"]
    from jax._src import distributed
    from jax.experimental import multihost_utils

    if distributed.global_state.preemption_sync_manager is None:
        return False
    return multihost_utils.reached_preemption_sync_point(int(step))


# ----------------------------------------------------------------------------- failure detection
