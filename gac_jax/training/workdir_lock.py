"""One writer per run folder: ``WORKDIR/.lock``, held for the writing process's lifetime.

A process that writes into a run folder (``train.py``; ``evaluate.py`` writing results there;
an export into it) holds an exclusive ``flock`` on ``WORKDIR/.lock`` while it writes. The
kernel releases the lock when the process ends, however it ends (``kill -9`` included), so a
lock is never left behind by a dead process. A second writer stops at once with
:class:`WorkdirBusyError` (exit code 2)::

    error: W/.lock: run folder in use by pid 4711 on host1 (python train.py ...) since
    2025-01-01 12:00:00; wait for it to finish or stop it

The file holds JSON (pid, host, start time, command line) for that message; a clean release
empties it. A file still naming a process that is gone (killed, or ended through
``os._exit``) is a stale lock: it is taken over with one line saying so. Read-only use
(TensorBoard, reading checkpoints, ``--report-only``) takes no lock and is never blocked.

Within one process the lock is re-entrant (the trainer evaluates in-process, and
``evaluate.py --runtime onnxruntime`` exports into the folder it already holds). Where the
filesystem cannot lock files (some network filesystems), :class:`LockUnsupportedError` says
so instead of writing unprotected. Multi-process training takes the lock on process 0 only
(the one that owns the folder); see :mod:`gac_jax.trainers.common`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import fcntl
import json
import os
import shlex
import socket
import sys
import time
from collections.abc import Iterator
from pathlib import Path

from gac_jax.data.io_errors import naming

LOCK_FILE = ".lock"
EXIT_BUSY = 2  # the exit code of a second writer (bad invocation: run it elsewhere or later)
_COMMAND_CHARS = 160


class WorkdirBusyError(RuntimeError):
    """Another process holds the run folder's lock; the message names it."""

    def __init__(self, path: str | os.PathLike, holder: str):
        super().__init__(f"{os.fspath(path)}: {holder}")
        self.path = os.fspath(path)


class LockUnsupportedError(OSError):
    """The filesystem of the run folder cannot lock files (``flock``)."""


@dataclasses.dataclass
class _Held:
    fd: int
    count: int
    pid: int  # a forked child inherits the descriptor (and this table) but must not empty it


_held: dict[Path, _Held] = {}


def lock_path(workdir: str | os.PathLike) -> Path:
    return Path(workdir) / LOCK_FILE


def holder_info() -> dict:
    """What the lock file records about this process."""
    command = shlex.join([Path(sys.executable).name, *sys.argv])
    if len(command) > _COMMAND_CHARS:
        command = command[: _COMMAND_CHARS - 3] + "..."
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": command,
    }


def acquire(workdir: str | os.PathLike) -> None:
    """Takes the lock of ``workdir`` (created if absent) for this process, or raises.

    Re-entrant: a process that holds it just counts one more :func:`release`.

    Raises:
      WorkdirBusyError: another process holds it.
      LockUnsupportedError: the filesystem does not support ``flock``.
    """
    key = Path(workdir).resolve()
    held = _held.get(key)
    if held is not None:
        held.count += 1
        return
    key.mkdir(parents=True, exist_ok=True)
    path = lock_path(workdir)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        holder = try_lock(fd)
    except OSError as e:
        os.close(fd)
        raise LockUnsupportedError(
            e.errno,
            f"cannot lock the run folder ({e.strerror}): its filesystem does not support file "
            "locks, so concurrent writers could not be refused; use a local or lock-capable "
            "filesystem for the workdir",
            os.fspath(path),
        ) from None
    if holder is not None:
        os.close(fd)
        raise WorkdirBusyError(path, _describe_holder(holder))
    try:
        previous = _read(fd)
        if previous.get("pid") not in (None, os.getpid()):
            print(
                f"{path}: took over the stale lock of {_who(previous)} (it ended without "
                "giving it back)",
                flush=True,
            )
        with naming(path):  # a full disk: "W/.lock: no space left on device"
            _write(fd, holder_info())
    except BaseException:
        os.close(fd)
        raise
    _held[key] = _Held(fd, 1, os.getpid())


def try_lock(fd: int) -> dict | None:
    """An exclusive ``flock`` on the lock file ``fd`` without waiting: None when taken; when
    another process holds it, what the file says about that process (``{}`` if nothing).
    Raises the ``OSError`` of a filesystem that cannot lock files."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
            return _read(fd)
        raise
    return None


def release(workdir: str | os.PathLike) -> None:
    """Gives the lock back (the last of nested :func:`acquire` calls empties the file)."""
    key = Path(workdir).resolve()
    held = _held.get(key)
    if held is None:
        return
    held.count -= 1
    if held.count > 0:
        return
    del _held[key]
    _close(held)


def release_all() -> None:
    """Empties and unlocks every lock of this process: for exits through ``os._exit``, so the
    next run does not report them as stale."""
    while _held:
        _close(_held.popitem()[1])


@contextlib.contextmanager
def hold(workdir: str | os.PathLike) -> Iterator[None]:
    """The lock of ``workdir`` for the body (see :func:`acquire`)."""
    acquire(workdir)
    try:
        yield
    finally:
        release(workdir)


def hold_if_inside(workdir: str | os.PathLike | None, *paths) -> contextlib.AbstractContextManager:
    """:func:`hold` of the run folder ``workdir`` when one of ``paths`` (a command's outputs;
    None = its default output, inside the workdir) lies inside it; nothing otherwise.

    A folder that does not exist is nobody's run folder yet: nothing is held (and nothing
    created, so the command still reports it missing).
    """
    if workdir is None or not Path(workdir).is_dir():
        return contextlib.nullcontext()
    root = Path(workdir).resolve()
    for p in paths:
        if p is None or Path(p).resolve().is_relative_to(root):
            return hold(workdir)
    return contextlib.nullcontext()


def is_held(workdir: str | os.PathLike) -> bool:
    """Whether this process holds the lock of ``workdir``."""
    return Path(workdir).resolve() in _held


def _close(held: _Held) -> None:
    if held.pid == os.getpid():
        with contextlib.suppress(OSError):
            os.ftruncate(held.fd, 0)
    os.close(held.fd)  # unlocks (once no forked child holds the descriptor any more)


def _read(fd: int) -> dict:
    try:
        data = os.pread(fd, 4096, 0)
        info = json.loads(data.decode()) if data.strip() else {}
    except (OSError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _write(fd: int, info: dict) -> None:
    data = (json.dumps(info) + "\n").encode()
    os.ftruncate(fd, 0)
    os.pwrite(fd, data, 0)
    with contextlib.suppress(OSError):
        os.fsync(fd)


def _who(info: dict) -> str:
    return f"pid {info.get('pid', '?')} on {info.get('host', '?')}"


def _describe_holder(info: dict) -> str:
    if not info:
        return (
            "run folder in use by another process (it is just taking or giving back the "
            "lock); try again in a moment"
        )
    text = f"run folder in use by {_who(info)}"
    if info.get("command"):
        text += f" ({info['command']})"
    if info.get("started"):
        text += f" since {info['started']}"
    if info.get("host") == socket.gethostname() and not _alive(info.get("pid")):
        return text + (
            "; that process has ended but a child of it still holds the lock: wait a moment "
            "or stop the child"
        )
    return text + "; wait for it to finish or stop it"


def _alive(pid) -> bool:
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
