"""A command's stdout and stderr that never stop it: ``with safe_console(): ...``.

What a command prints is a report about its work, not its work: a reader that went away
(``| head``, a ``tee`` that died), a full disk behind a redirection (``> /dev/full``) or a
name that the terminal's encoding cannot show (a file name that is not UTF-8, under a strict
UTF-8 locale) must not end a stream or change what it writes. Inside :func:`safe_console`:

* text the stream's encoding cannot represent is written with backslash escapes
  (``errors="backslashreplace"``) instead of raising ``UnicodeEncodeError``;
* the first write or flush that fails (``BrokenPipeError``, ``ENOSPC``, a closed file) makes
  that stream drop everything after it, silently: its file descriptor is pointed at
  ``/dev/null`` so that the interpreter's final flush does not fail either (no "Exception
  ignored" message, no exit status 120). The other stream goes on.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator


class DroppingStream:
    """A text stream that forwards to ``stream`` until a write fails, then drops everything
    (:attr:`dropped`: whether that happened). Other attributes are ``stream``'s."""

    def __init__(self, stream):
        self._stream = stream
        self.dropped = False

    def __getattr__(self, name):
        return getattr(self._stream, name)

    def _failed(self) -> None:
        self.dropped = True
        with contextlib.suppress(OSError, ValueError, AttributeError):
            fd = self._stream.fileno()
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, fd)  # what is still buffered goes nowhere, without an error
            os.close(devnull)

    def write(self, text: str) -> int:
        if not self.dropped:
            try:
                return self._stream.write(text)
            except (OSError, ValueError):
                self._failed()
        return len(text)

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if not self.dropped:
            try:
                self._stream.flush()
            except (OSError, ValueError):
                self._failed()


@contextlib.contextmanager
def safe_console() -> Iterator[None]:
    """``sys.stdout`` and ``sys.stderr`` as :class:`DroppingStream` s with backslash escapes
    for what their encoding cannot represent (module doc); restored on exit."""
    saved = sys.stdout, sys.stderr
    for stream in saved:
        with contextlib.suppress(AttributeError, ValueError, OSError):
            stream.reconfigure(errors="backslashreplace")
    sys.stdout, sys.stderr = DroppingStream(saved[0]), DroppingStream(saved[1])
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.stderr):
            stream.flush()
        sys.stdout, sys.stderr = saved
