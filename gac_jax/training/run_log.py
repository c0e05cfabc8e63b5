"""What libraries say during a run goes to ``WORKDIR/details.log``, not to the terminal.

orbax saves checkpoints in background threads; when a write fails there (a full disk) it
logs absl ``ERROR`` lines with tracebacks from every thread, tensorstore's callbacks print
``RuntimeError: Event loop is closed`` tracebacks, and so on: hundreds of lines that bury
the one that matters. For the duration of a run (:func:`library_logs_to`):

* warnings and errors of the ``absl`` (orbax, grain) and ``asyncio`` loggers (orbax's failed
  write tasks) are written to the details file;
* exceptions that end a background thread go there too (those of a disk failure only
  there; any other also to the terminal, as before);
* inside :func:`capture_stderr` (the trainers' checkpoint saves) everything written to
  ``sys.stderr`` goes there.

The terminal then shows the one line the entry point prints (``error: ... (details in
W/details.log)``). Writes to the details file never raise: the disk may be the problem.
In a multi-process run each process has its own file (``details.process<N>.log`` beside
process 0's).
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import threading
import time
import traceback
from collections.abc import Iterator
from pathlib import Path

from gac_jax.data.io_errors import disk_failure

DETAILS_FILE = "details.log"
LIBRARY_LOGGERS = ("absl", "asyncio")


def details_path(workdir: str | os.PathLike, process_index: int = 0) -> Path:
    """The details file of process ``process_index`` in ``workdir``."""
    name = DETAILS_FILE if process_index == 0 else f"details.process{process_index}.log"
    return Path(workdir) / name


class _DetailsStream(io.TextIOBase):
    """Appends to the details file, opened at the first write; never raises."""

    def __init__(self, path: Path):
        self.path = path
        self._file = None
        self._lock = threading.Lock()
        self.last_write = time.monotonic()

    def writable(self) -> bool:
        return True

    def write(self, text: str) -> int:
        self.last_write = time.monotonic()
        with self._lock, contextlib.suppress(OSError, ValueError):
            if self._file is None:
                self._file = open(self.path, "a", encoding="utf-8")  # noqa: SIM115
            self._file.write(text)
            self._file.flush()
        return len(text)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        with self._lock, contextlib.suppress(OSError, ValueError):
            if self._file is not None:
                self._file.close()
            self._file = None


_active: dict[str, _DetailsStream] = {}


def active_path() -> Path | None:
    """The details file of the run in progress in this process (None outside a run)."""
    stream = _active.get("stream")
    return stream.path if stream is not None else None


def record(text: str) -> None:
    """Appends ``text`` (e.g. a traceback) to the details file of the run in progress."""
    stream = _active.get("stream")
    if stream is not None:
        stream.write(text if text.endswith("\n") else text + "\n")


def record_exception(error: BaseException) -> None:
    record("".join(traceback.format_exception(error)))


@contextlib.contextmanager
def library_logs_to(path: str | os.PathLike) -> Iterator[Path]:
    """Routes library diagnostics to ``path`` for the body (see the module docstring).

    Nested use (a run inside a run, e.g. tests) keeps the outer file.
    """
    if "stream" in _active:
        yield _active["stream"].path
        return
    stream = _DetailsStream(Path(path))
    handler = logging.StreamHandler(stream)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in LIBRARY_LOGGERS]
    saved = [(lg, lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.addHandler(handler)
        lg.propagate = False
    previous_hook = threading.excepthook

    def thread_hook(args) -> None:
        text = "".join(
            traceback.format_exception(args.exc_type, args.exc_value, args.exc_traceback)
        )
        name = args.thread.name if args.thread is not None else "?"
        stream.write(f"exception in thread {name}:\n{text}")
        if args.exc_value is None or disk_failure(args.exc_value) is None:
            previous_hook(args)

    threading.excepthook = thread_hook
    _active["stream"] = stream
    try:
        yield stream.path
    finally:
        _active.pop("stream", None)
        threading.excepthook = previous_hook
        for lg, propagate in saved:
            lg.removeHandler(handler)
            lg.propagate = propagate
        stream.close()


def settle(quiet_s: float = 0.5, max_s: float = 5.0) -> None:
    """Waits until nothing was written to the details file for ``quiet_s`` seconds (at most
    ``max_s``): after a failed save, tensorstore's callbacks of writes still in flight print
    their tracebacks for a moment, and they belong in the file, not on the terminal."""
    stream = _active.get("stream")
    if stream is None:
        return
    deadline = time.monotonic() + max_s
    while time.monotonic() < deadline and time.monotonic() - stream.last_write < quiet_s:
        time.sleep(0.05)


@contextlib.contextmanager
def capture_stderr() -> Iterator[None]:
    """Inside, ``sys.stderr`` writes go to the details file of the run in progress (nothing
    happens outside a run). For windows in which background threads may print tracebacks of
    a failed write (checkpoint saves)."""
    stream = _active.get("stream")
    if stream is None:
        yield
        return
    with contextlib.suppress(Exception):
        sys.stderr.flush()
    previous, sys.stderr = sys.stderr, stream
    try:
        yield
    finally:
        sys.stderr = previous
