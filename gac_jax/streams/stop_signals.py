"""Ctrl-C, SIGTERM and SIGHUP end a stream the same way, at any moment.

Service managers, containers and schedulers stop a program with SIGTERM (SIGHUP: its
terminal closed), a user with Ctrl-C (SIGINT); all three are handled alike by
:class:`StopSignals`, installed for the whole command:

* **during start-up** (opening the input, loading, exporting, quantizing, warming up) the
  first signal raises :class:`StartupInterrupted` in the main thread, so that the work in
  progress unwinds through its ``finally`` clauses (temporary files removed, nothing half
  written left), and the command exits with :func:`exit_status`; if a library swallowed
  the exception (an ``Exception ignored in ...`` callback), :meth:`StopSignals.check` between
  the start-up steps raises it again. A second signal exits at once (``os._exit``): what
  exists on disk was written atomically.
* **during the stream** the first signal stops reading and lets the frames in flight finish
  (:meth:`~gac_jax.streams.pipeline.StreamPipeline.stop`), the second drops them
  (:meth:`~gac_jax.streams.pipeline.StreamPipeline.abort`); the frame being written is
  finished either way and the outputs are closed as at the end of the input.

Before a command has written anything (parsing its arguments, opening its input, checking
its outputs) a signal ends it at once with one line (:func:`exit_during_start`, installed
first thing by ``python -m gac_jax.cli.predict``); :func:`record_early` takes over where it
starts to create and lock its outputs. Whatever leaves through ``os._exit`` runs the
callbacks given to :func:`at_exit` first (the output locks given back, results moved aside
restored).

Exit statuses follow the shell's convention, 128 + the signal number: 130 (SIGINT), 143
(SIGTERM), 129 (SIGHUP).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys

NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM", signal.SIGHUP: "SIGHUP"}
_early: list[int] = []  # signals that came before StopSignals was entered
_before: dict[int, object] = {}  # the handlers before record_early
_cleanups: list = []  # run before os._exit


def at_exit(callback) -> None:
    """``callback()`` runs before the command leaves through :func:`exit_now` (its errors are
    ignored)."""
    _cleanups.append(callback)


def forget_at_exit() -> None:
    """Drops the :func:`at_exit` callbacks (the command ended without ``os._exit``)."""
    _cleanups.clear()


def exit_now(status: int) -> None:
    """The :func:`at_exit` callbacks (newest first), then ``os._exit(status)``."""
    while _cleanups:
        with contextlib.suppress(Exception):
            _cleanups.pop()()
    os._exit(status)


def _exit_at_once(signum, frame) -> None:
    with contextlib.suppress(OSError):
        name = NAMES.get(signum, f"signal {signum}")
        os.write(2, f"interrupted: {name} during start-up; nothing was written\n".encode())
    os._exit(exit_status(signum))


def _default(signum: int):
    return signal.default_int_handler if signum == signal.SIGINT else signal.SIG_DFL


def exit_during_start() -> None:
    """Until :func:`record_early` or :func:`restore_defaults`: a stop signal ends the process
    at once with one line on stderr (nothing has been written yet)."""
    for signum in NAMES:
        signal.signal(signum, _exit_at_once)


def restore_defaults() -> None:
    """Python's own handlers back where :func:`exit_during_start` installed its own (a
    command that handles ``KeyboardInterrupt`` itself)."""
    for signum in NAMES:
        if signal.getsignal(signum) is _exit_at_once:
            signal.signal(signum, _default(signum))


def _record(signum, frame) -> None:
    _early.append(signum)
    if len(_early) > 1:
        exit_now(exit_status(_early[0]))


def record_early() -> None:
    """Where a stream command starts to write (its outputs created and locked, before JAX
    loads): the stop signals are recorded, not acted on, until :class:`StopSignals` takes
    over and ends the start-up (its exit restores the handlers from before this call, or
    :func:`forget_early`)."""
    for signum in NAMES:
        previous = signal.signal(signum, _record)
        _before.setdefault(signum, _default(signum) if previous is _exit_at_once else previous)


def forget_early() -> None:
    """The handlers from before :func:`record_early` back (the command ends without a
    stream)."""
    for signum, previous in list(_before.items()):
        signal.signal(signum, previous)
    _before.clear()
    _early.clear()


def exit_status(signum: int) -> int:
    """128 + the signal number (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP)."""
    return 128 + int(signum)


class StartupInterrupted(BaseException):
    """A stop signal before the stream began (a ``BaseException``, as ``KeyboardInterrupt``:
    no ``except Exception`` of a library takes it for an error of its own)."""

    def __init__(self, signum: int):
        super().__init__(f"{NAMES[signum]} during start-up")
        self.signum = signum


class StopSignals:
    """The stop-signal handler of a stream command (module doc). Use as a context manager;
    set :attr:`pipeline` when the stream begins."""

    def __init__(self, log=print):
        self.signum: int | None = None  # the first signal received
        self.count = 0
        self.pipeline = None
        self.log = log
        self._previous: dict[int, object] = {}

    def __enter__(self) -> StopSignals:
        for signum in NAMES:
            self._previous[signum] = signal.signal(signum, self)
        if _early:
            self.signum, self.count = _early[0], len(_early)
        self._unraisable = sys.unraisablehook
        sys.unraisablehook = self._unraisable_hook
        return self

    def __exit__(self, *exc) -> None:
        for signum, previous in self._previous.items():
            signal.signal(signum, _before.pop(signum, previous))
        _early.clear()
        sys.unraisablehook = self._unraisable

    def _unraisable_hook(self, unraisable) -> None:
        """A :class:`StartupInterrupted` raised inside a callback that cannot raise (a garbage
        collector callback) is dropped silently: :meth:`check` raises it again."""
        if not isinstance(unraisable.exc_value, StartupInterrupted):
            self._unraisable(unraisable)

    @property
    def exit_status(self) -> int | None:
        return None if self.signum is None else exit_status(self.signum)

    def check(self) -> None:
        """Between start-up steps: raises :class:`StartupInterrupted` if a signal came."""
        if self.signum is not None and self.pipeline is None:
            raise StartupInterrupted(self.signum)

    def __call__(self, signum, frame) -> None:
        self.count += 1
        if self.signum is None:
            self.signum = signum
        name = NAMES.get(signum, f"signal {signum}")
        if self.pipeline is None:
            if self.count == 1:
                raise StartupInterrupted(signum)
            sys.stderr.write(f"{name} again during start-up: stopped at once\n")
            sys.stderr.flush()
            sys.stdout.flush()
            exit_now(exit_status(self.signum))
        if self.count == 1:
            self.pipeline.stop()
            self.log(
                f"{name}: reading stopped; finishing the frames in flight ({name} again or "
                "another stop signal drops them)"
            )
        elif self.count == 2:
            self.pipeline.abort()
            self.log(f"{name} again: dropping the frames in flight")
