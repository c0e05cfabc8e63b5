"""One stream per output: a lock on every folder (and outside video) a stream writes.

Two streams into one ``--out`` would write the same video and result files, and each would
report the other's frames as its own; a second run with ``--overwrite`` would delete a running
stream's results. So a stream holds an exclusive ``flock`` on ``OUT/.gac_jax_stream.lock``
(and, for an ``--out-video`` outside ``OUT``, on ``.<video name>.lock`` beside it) from
before the model loads until it ends; a second stream stops at once with one line naming the
holder (:class:`OutputBusyError`, exit 2)::

    error: out: in use by another stream (pid 4711: python -m gac_jax.cli.predict ...,
    since 2026-01-01 12:00:00); wait for it to end, stop it, or choose another --out

The kernel releases a lock when its process ends, however it ends, so a killed stream never
blocks the next one; the lock file is removed on release (while still locked, so that a
process that opened the old file retries on the new one) and left, harmless, only by a kill.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

from gac_jax.data.io_errors import naming
from gac_jax.training.workdir_lock import holder_info, try_lock

FOLDER_LOCK = ".gac_jax_stream.lock"


class OutputBusyError(RuntimeError):
    """Another stream holds the output's lock; the message names it."""


def lock_file(output: Path, folder: bool) -> Path:
    """The lock file of an output folder (``folder``) or of an output file."""
    return output / FOLDER_LOCK if folder else output.with_name(f".{output.name}.lock")


class OutputLock:
    """The lock of one output (module doc): :meth:`acquire`, :meth:`release` (idempotent).

    Args:
      output: the folder or file.
      folder: whether ``output`` is a folder (that exists).
      option: the command-line option that chose it (``--out``), named in the message.
    """

    def __init__(self, output: Path, folder: bool, option: str):
        self.output, self.option = output, option
        self.path = lock_file(output, folder)
        self._fd = -1

    def acquire(self) -> None:
        """Takes the lock, or raises :class:`OutputBusyError` (another stream holds it) or
        ``OSError`` naming the lock file (its folder cannot be written, no ``flock``)."""
        while True:
            with naming(self.path):
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            holder = error = None
            try:
                holder = try_lock(fd)
            except OSError as e:
                error = e
            if holder is None and error is None and _same_file(fd, self.path):
                break
            os.close(fd)
            if error is not None:
                why = f"cannot lock ({error.strerror}): its filesystem has no file locks"
                why += ", so a second stream into it could not be refused; choose a local folder"
                raise OSError(error.errno, why, os.fspath(self.path))
            if holder is not None:
                raise OutputBusyError(self._busy(holder))
            # else its holder removed the file as we opened it: lock the new one
        try:
            data = (json.dumps(holder_info()) + "\n").encode()
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
        except OSError:
            pass  # the lock holds without the description (a full disk)
        self._fd = fd

    def release(self) -> None:
        if self._fd < 0:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self._fd)
        self._fd = -1

    def _busy(self, holder: dict) -> str:
        who = f"pid {holder['pid']}" if holder.get("pid") else "another process"
        if holder.get("command"):
            who += f": {holder['command']}"
        if holder.get("started"):
            who += f", since {holder['started']}"
        return (
            f"{os.fspath(self.output)}: in use by another stream ({who}); wait for it to end, "
            f"stop it, or choose another {self.option}"
        )


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


_held: list[OutputLock] = []


def hold(locks: list[OutputLock]) -> None:
    """Acquires ``locks`` in order (all or none) for the rest of the process, or until
    :func:`release_all`."""
    taken = []
    try:
        for lock in locks:
            lock.acquire()
            taken.append(lock)
    except BaseException:
        for lock in taken:
            lock.release()
        raise
    _held.extend(taken)


def release_all() -> None:
    """Gives back every lock :func:`hold` took (the end of a stream, and before ``os._exit``)."""
    while _held:
        _held.pop().release()
