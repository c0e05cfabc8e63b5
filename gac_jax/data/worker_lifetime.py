"""Helper processes that never outlive the process that owns their work.

Loader workers (grain ``mp_prefetch``) and the scene generator's pool are helper
processes: when the process that started them dies without closing them (SIGKILL, a
crash, the OOM killer) they would stay alive, holding their memory. Each helper
therefore watches its **owner**, the process whose work it does, named explicitly:
:func:`exit_with_owner`, called first thing in each helper, starts a daemon thread that
ends the helper within ``poll_s`` seconds after the owner is gone, by any signal, and
never while it lives.

The owner is named, not taken to be the helper's parent: under the ``forkserver`` start
method a worker is a child of the fork server, not of the process that owns the pool,
and a helper of a helper (a pool started in a grain worker) has a parent that is itself
a helper. An :class:`Owner` is a pid plus, on Linux, the process's start time from
``/proc/PID/stat``, so that a recycled pid does not pass for the owner; a zombie (dead,
not yet reaped) counts as gone.

A spawned child spends its first seconds importing what it needs (jax, grain, the
data pipeline) before the pool calls its initializer; an entry point that starts such
children therefore calls :func:`mark_owner` at start-up and :func:`guard_spawned_child`
at the top of its module, which ``multiprocessing``'s spawn and forkserver start methods
run first in every child and in the fork server (they import the main module as
``__mp_main__``), so the watch starts before the heavy imports.

A watchdog thread rather than Linux's ``prctl(PR_SET_PDEATHSIG)``: the death signal
fires when the *thread* that forked the child exits (grain starts its workers from a
helper thread, so it could end healthy workers), it follows the parent, not the owner,
and the thread is portable (macOS). The helper ignores SIGINT: Ctrl-C in a terminal
reaches the whole process group, and the owner, not its workers, decides how to stop (it
finishes the step, saves, and then closes its workers).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import threading
from pathlib import Path

POLL_S = 0.5
OWNER_ENV = "GAC_JAX_OWNER"  # "PID" or "PID:START" of the entry point's process


@dataclasses.dataclass(frozen=True)
class Owner:
    """A process, identified so that a recycled pid does not pass for it.

    Attributes:
      pid: its process id.
      start: its start time (clock ticks since boot, ``/proc/PID/stat`` field 22) on
        Linux; None where ``/proc`` is not available (then only the pid is checked).
    """

    pid: int
    start: int | None = None

    @classmethod
    def current(cls) -> Owner:
        """This process."""
        return cls.of(os.getpid())

    @classmethod
    def of(cls, pid: int) -> Owner:
        """Process ``pid`` as it is now (start time read where ``/proc`` has it)."""
        stat = _proc_stat(pid)
        return cls(pid, int(stat[19]) if stat else None)

    def token(self) -> str:
        """``PID`` or ``PID:START``: the text form :meth:`parse` reads (environment, argv)."""
        return str(self.pid) if self.start is None else f"{self.pid}:{self.start}"

    @classmethod
    def parse(cls, token: str) -> Owner | None:
        """Inverse of :meth:`token`; None for text that is not one."""
        pid, _, start = token.strip().partition(":")
        if not pid.isdigit() or (start and not start.isdigit()):
            return None
        return cls(int(pid), int(start) if start else None)

    def alive(self) -> bool:
        """True while the process runs (a zombie, or a new process with its pid, is not it)."""
        if self.pid <= 0:
            return False
        if Path("/proc/self/stat").exists():
            stat = _proc_stat(self.pid)
            if stat is None or stat[0] in ("Z", "X"):
                return False
            return self.start is None or int(stat[19]) == self.start
        try:  # no /proc (macOS): signal 0 only checks that the pid exists
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True


def _proc_stat(pid: int) -> list[str] | None:
    """Fields 3.. of ``/proc/PID/stat`` (state first, start time at index 19); None if absent."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2 :].split()  # the name (field 2) may hold spaces and ')'


def exit_with_owner(owner: Owner | None = None, poll_s: float = POLL_S) -> None:
    """In a helper process: exit (status 1) within ``poll_s`` s once ``owner`` has died.

    Args:
      owner: the process whose work this one does, as that process named itself
        (:meth:`Owner.current` there), so that an owner that died before this call is
        noticed too; None: the owner named by :func:`mark_owner` in the environment, else
        this process's parent at the call.
      poll_s: seconds between checks.

    Also ignores SIGINT (see the module docstring). Idempotent per process.
    """
    global _watching
    if _watching == os.getpid():  # (a forked child inherits the flag, not the thread)
        return
    _watching = os.getpid()
    with contextlib.suppress(ValueError):  # not the main thread: keep SIGINT as it is
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    if owner is None:
        owner = marked_owner() or Owner.of(os.getppid())
    threading.Thread(
        target=_watch_owner, args=(owner, poll_s), name="gac-owner-watch", daemon=True
    ).start()


_watching: int | None = None


def mark_owner() -> None:
    """In an entry point, before it starts helper processes: names this process as their
    owner (environment variable ``GAC_JAX_OWNER``, inherited by every descendant)."""
    os.environ[OWNER_ENV] = Owner.current().token()


def marked_owner() -> Owner | None:
    """The owner :func:`mark_owner` named in this process's environment, if any."""
    return Owner.parse(os.environ.get(OWNER_ENV, ""))


def guard_spawned_child() -> None:
    """At the top of an entry-point module: in a child that ``multiprocessing`` spawned or
    forked from its fork server (the module imported as ``__mp_main__``), watch the owner
    from the first moment."""
    exit_with_owner()


def _watch_owner(owner: Owner, poll_s: float) -> None:
    stop = threading.Event()
    while not stop.wait(poll_s):
        if not owner.alive():
            os._exit(1)  # the owner is gone; nobody reads our results any more


def grain_worker_init(worker_index: int, worker_count: int, *, owner: str) -> None:
    """``worker_init_fn`` for grain's ``mp_prefetch`` (bind ``owner``, an
    :meth:`Owner.token`, with ``functools.partial``): see :func:`exit_with_owner`."""
    del worker_index, worker_count
    exit_with_owner(Owner.parse(owner))
