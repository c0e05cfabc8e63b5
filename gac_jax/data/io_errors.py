"""Failed reads and writes told in one line that names the file: ``PATH: problem``.

A full disk (or an exceeded quota, a failing device) reaches the code in different shapes:
an ``OSError`` from Python's own writes, often without a file name (``write``/``flush``/
``close`` do not know it), or the text of a tensorstore error from a checkpoint's background
threads (``RESOURCE_EXHAUSTED: Error writing ... No space left on device
[os_error_code='28']``). :func:`disk_failure` recognises both, :func:`error_line` turns any
``OSError`` into the line an entry point prints (with the free space for a disk failure),
:func:`naming` gives nameless ``OSError``\\ s the path being written, and
:class:`DiskWriteError` carries a finished message (the trainers add what was kept).
Exit codes: :func:`exit_code` (1 for a disk failure, 2 for a bad path or permission).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

# The storage itself failed (as opposed to a wrong path or a permission): exit code 1.
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EFBIG, errno.EROFS})
EXIT_DISK_FAILURE = 1
EXIT_BAD_PATH = 2
_TEXT_MARKERS = {
    "no space left on device": errno.ENOSPC,
    "disk quota exceeded": errno.EDQUOT,
}
_OS_ERROR_CODE = re.compile(r"os_error_code='?(\d+)")
_QUOTED_PATH = re.compile(r'(?:Failed writing|Error writing local file|local file): "([^"]+)"')


class DiskFailure(NamedTuple):
    """What :func:`disk_failure` found: the error number, the file when known, and the
    finished message of a :class:`DiskWriteError` (None for other errors)."""

    errno: int
    path: str | None
    message: str | None = None


class DiskWriteError(OSError):
    """Writing failed for lack of space (or a failing disk); ``str()`` is the whole story.

    The message names the path, the reason and the free space (:func:`describe`), and the
    trainers add what was kept (the last complete checkpoint) and where the details are.
    """

    def __init__(self, errno_: int, path: str | os.PathLike, message: str):
        super().__init__(errno_, message, os.fspath(path))
        self.message = message

    def __str__(self) -> str:
        return self.message

    def __reduce__(self):
        return (type(self), (self.errno, self.filename, self.message))


def _chain(error: BaseException) -> Iterator[BaseException]:
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        yield error
        error = error.__cause__ or error.__context__


def disk_failure(error: BaseException) -> DiskFailure | None:
    """The disk failure behind ``error`` (or its causes), or None if it is something else.

    Recognises ``OSError``\\ s with an errno of :data:`DISK_ERRNOS` and errors whose text says
    "No space left on device", "Disk quota exceeded" or carries such an ``os_error_code``
    (tensorstore). A bare ``RESOURCE_EXHAUSTED`` is not enough: XLA reports running out of
    device memory that way. A :class:`DiskWriteError` anywhere in the chain wins: it is the
    first failure, already described.
    """
    for e in _chain(error):  # a finished report first (a later failure may chain onto it)
        if isinstance(e, DiskWriteError):
            return DiskFailure(e.errno, e.filename, e.message)
    for e in _chain(error):
        if isinstance(e, OSError) and e.errno in DISK_ERRNOS:
            return DiskFailure(e.errno, e.filename)
        text = str(e)
        code = _OS_ERROR_CODE.search(text)
        number = int(code.group(1)) if code else None
        if number not in DISK_ERRNOS:
            low = text.lower()
            number = next((n for m, n in _TEXT_MARKERS.items() if m in low), None)
        if number is not None:
            paths = _QUOTED_PATH.findall(text)
            return DiskFailure(number, paths[-1] if paths else None)
    return None


def free_bytes(path: str | os.PathLike) -> int | None:
    """Free bytes (for this user) on the filesystem of ``path`` or of its nearest existing
    ancestor; None when that cannot be told."""
    p = Path(path).absolute()
    for candidate in (p, *p.parents):
        try:
            return shutil.disk_usage(candidate).free
        except OSError:
            continue
    return None


def megabytes(n: int | None) -> str:
    return "unknown" if n is None else f"{n / 1e6:.1f} MB"


def describe(failure: DiskFailure, path: str | os.PathLike | None = None) -> str:
    """``PATH: no space left on device (3.1 MB free)``; ``path`` overrides the failure's own."""
    where = os.fspath(path) if path is not None else (failure.path or "?")
    reason = os.strerror(failure.errno)
    reason = reason[0].lower() + reason[1:]
    return f"{where}: {reason} ({megabytes(free_bytes(where))} free)"


def error_line(error: OSError, fallback: str | os.PathLike | None = None) -> str:
    """The ``error:`` line's text for ``error``: ``PATH: problem`` (the path of the error, else
    ``fallback``, the file or folder the command was writing); the free space for a disk
    failure; a :class:`DiskWriteError`'s own message."""
    if isinstance(error, DiskWriteError):
        return str(error)
    if error.errno is None and error.filename is None and str(error):
        return str(error)  # a message of this project's own (it names its file)
    where = error.filename or (os.fspath(fallback) if fallback is not None else None)
    failure = disk_failure(error)
    if failure is not None:
        return describe(failure, where or failure.path)
    reason = error.strerror or str(error)
    if error.filename2:
        return f"{error.filename} -> {error.filename2}: {reason}"
    return f"{where}: {reason}" if where else reason


def exit_code(error: BaseException) -> int:
    """:data:`EXIT_DISK_FAILURE` for a disk failure, else :data:`EXIT_BAD_PATH`."""
    return EXIT_DISK_FAILURE if disk_failure(error) is not None else EXIT_BAD_PATH


@contextlib.contextmanager
def naming(path: str | os.PathLike) -> Iterator[None]:
    """Inside: an ``OSError`` without a file name (from ``write``, ``flush``, ``close``) is
    raised again naming ``path``, the file being written."""
    try:
        yield
    except OSError as e:
        if e.filename or e.errno is None:
            raise
        raise OSError(e.errno, e.strerror or os.strerror(e.errno), os.fspath(path)) from e
