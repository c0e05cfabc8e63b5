"""Helper processes that never outlive the process that started them.

Loader workers (grain ``mp_prefetch``) and the scene generator's pool are ordinary
child processes: when their parent dies without closing them (SIGKILL, a crash,
the OOM killer) they are re-parented to init and stay alive, holding their
memory. :func:`exit_with_parent`, called first thing in each child, starts a
daemon thread that watches the parent pid and ends the child within ``poll_s``
seconds after the parent is gone, by any signal.

A spawned child spends its first seconds importing what it needs (jax, grain, the
data pipeline) before grain calls its ``worker_init_fn``; an entry point that starts
such children therefore calls :func:`mark_parent` at start-up and
:func:`guard_spawned_child` at the top of its module, which ``multiprocessing``'s
spawn start method runs first in every child (it imports the main module as
``__mp_main__``), so the watch starts before the heavy imports.

A watchdog thread rather than Linux's ``prctl(PR_SET_PDEATHSIG)``: the death
signal fires when the *thread* that forked the child exits, and grain starts its
workers from a helper thread, so it could end healthy workers; the thread is also
portable (macOS). The child ignores SIGINT: Ctrl-C in a terminal reaches the whole
process group, and the parent, not its workers, decides how to stop (it finishes
the step, saves, and then closes its workers).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

POLL_S = 0.5
PARENT_PID_ENV = "GAC_JAX_PARENT_PID"


def exit_with_parent(parent_pid: int | None = None, poll_s: float = POLL_S) -> None:
    """In a child process: exit (status 1) within ``poll_s`` s once the parent has died.

    Args:
      parent_pid: the pid of the process that started this one, as that process saw
        it (``os.getpid()`` there), so that a parent that died before this call is
        noticed too; None: ``os.getppid()`` at the call (e.g. under a fork server).
      poll_s: seconds between checks.

    Also ignores SIGINT (see the module docstring). Idempotent.
    """
    global _watching
    if _watching == os.getpid():  # (a forked child inherits the flag, not the thread)
        return
    _watching = os.getpid()
    with contextlib.suppress(ValueError):  # not the main thread: keep SIGINT as it is
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid() if parent_pid is None else parent_pid
    threading.Thread(
        target=_watch_parent, args=(parent, poll_s), name="gac-parent-watch", daemon=True
    ).start()


_watching: int | None = None


def mark_parent() -> None:
    """In an entry point, before it starts helper processes: tells them who their parent is
    (environment variable ``GAC_JAX_PARENT_PID``, inherited by every child)."""
    os.environ[PARENT_PID_ENV] = str(os.getpid())


def guard_spawned_child() -> None:
    """At the top of an entry-point module: in a child that ``multiprocessing`` spawned
    (the module imported as ``__mp_main__``), watch the parent from the first moment."""
    pid = os.environ.get(PARENT_PID_ENV)
    exit_with_parent(int(pid) if pid and pid.isdigit() else None)


def _watch_parent(parent: int, poll_s: float) -> None:
    stop = threading.Event()
    while not stop.wait(poll_s):
        if os.getppid() != parent:
            os._exit(1)  # the parent is gone; nobody reads our results any more


def grain_worker_init(worker_index: int, worker_count: int, *, parent_pid: int) -> None:
    """``worker_init_fn`` for grain's ``mp_prefetch`` (bind ``parent_pid`` with
    ``functools.partial``): see :func:`exit_with_parent`."""
    del worker_index, worker_count
    exit_with_parent(parent_pid)
