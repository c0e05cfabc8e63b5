"""Multi-process runs (``jax.distributed``): start-up, coordination and failure detection.

What a trainer needs so that N processes behave like one and a lost process
never leaves the others hanging (the data-parallel step itself is
:mod:`gac_jax.training.parallel`):

* :func:`initialize_distributed` from flags or launcher environment variables;
* :func:`barrier`, :func:`main_process_first`, :func:`run_on_main`: work done by
  process 0 alone (dataset generation, anchor priors, evaluation) while the
  others wait with a timeout; :func:`check_shared_directory`;
* :class:`~gac_jax.training.step_watchdog.ProgressWatchdog` (its own module, which imports
  this one): exits a process whose training step has not completed for ``step_timeout``
  seconds (a peer that hangs while alive);
  :func:`raise_if_peer_failure` turns the collective / coordination errors seen
  when a peer dies into a clear :class:`PeerLostError`;
* :func:`install_stop_handlers` and :func:`preemption_requested`: SIGTERM or
  SIGINT (Ctrl-C) to any process makes all of them stop at the same step after a
  checkpoint (across processes through the JAX preemption service); a second
  SIGINT exits at once.

A dead peer is noticed at once by the surviving processes' next collective
(the CPU/gloo or GPU transport reports the closed connection) or, when a
survivor waits in a coordination-service barrier, after ``heartbeat_timeout``
seconds. When process 0 (the coordinator) dies, JAX terminates the others
itself ("the JAX distributed service detected fatal errors").

In a single process every function here is free and trivial.
"""

from __future__ import annotations

import atexit
import contextlib
import dataclasses
import itertools
import os
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import jax
import numpy as np

from gac_jax.training import workdir_lock

EXIT_PEER_LOST = 3  # another process died or hung; restart all processes to resume
EXIT_PREEMPTED = 75  # stopped on SIGTERM/SIGINT after a checkpoint (EX_TEMPFAIL: run again)
EXIT_INTERRUPTED = 130  # a second SIGINT: stopped at once, without a checkpoint


class PeerLostError(RuntimeError):
    """Another process of a multi-process run died, hung or could not be reached."""


class PreemptedError(RuntimeError):
    """All processes stopped at the same step after SIGTERM/SIGINT, with a checkpoint saved."""

    def __init__(self, step: int, message: str | None = None):
        super().__init__(
            message or f"stopped at step {step}, checkpoint saved; run the same command to resume"
        )
        self.step = step


@dataclasses.dataclass
class DistributedSettings:
    """Timeouts of a multi-process run (seconds), set by :func:`initialize_distributed`.

    Attributes:
      step_timeout: longest time between two completed training steps (the first
        includes compilation, any includes a checkpoint save) before the
        :class:`ProgressWatchdog` declares a peer hung and exits the process.
      wait_timeout: longest time processes wait at a barrier for work that
        process 0 does alone (dataset generation, anchor priors, evaluation).
      heartbeat_timeout: after this long without heartbeats JAX declares a process dead.
      peer_lost_hint: what the peer-lost error tells the user to do (the trainers name
        their checkpoint folder).
    """

    step_timeout: float = 900.0
    wait_timeout: float = 7200.0
    heartbeat_timeout: int = 100
    peer_lost_hint: str = "Restart all processes to resume from the last checkpoint."


settings = DistributedSettings()

_ENV = {
    "coordinator": ("GAC_COORDINATOR", "JAX_COORDINATOR_ADDRESS"),
    "num_processes": ("GAC_NUM_PROCESSES", "JAX_NUM_PROCESSES"),
    "process_id": ("GAC_PROCESS_ID", "JAX_PROCESS_ID"),
    "heartbeat_timeout": ("GAC_HEARTBEAT_TIMEOUT",),
    "step_timeout": ("GAC_STEP_TIMEOUT",),
    "wait_timeout": ("GAC_WAIT_TIMEOUT",),
}


def _env(name: str) -> str | None:
    for var in _ENV[name]:
        if os.environ.get(var):
            return os.environ[var]
    return None


def _env_number(name: str, kind: type):
    value = _env(name)
    if value is None:
        return None
    try:
        return kind(value)
    except ValueError:
        raise ValueError(f"{'/'.join(_ENV[name])} must be a number, got {value!r}") from None


def initialize_distributed(
    coordinator: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
    *,
    heartbeat_timeout: int | None = None,
    step_timeout: float | None = None,
    wait_timeout: float | None = None,
    initialization_timeout: int = 300,
    shutdown_timeout: int = 300,
) -> bool:
    """Starts the multi-process runtime when asked to; returns True if it did.

    Arguments fall back to the environment variables that cluster launchers
    can set: ``GAC_COORDINATOR``/``JAX_COORDINATOR_ADDRESS`` (``HOST:PORT`` of
    process 0), ``GAC_NUM_PROCESSES``/``JAX_NUM_PROCESSES``,
    ``GAC_PROCESS_ID``/``JAX_PROCESS_ID``, ``GAC_HEARTBEAT_TIMEOUT``,
    ``GAC_STEP_TIMEOUT``, ``GAC_WAIT_TIMEOUT`` (see :class:`DistributedSettings`).
    ``coordinator='auto'`` lets JAX detect all three from the cluster (SLURM,
    Open MPI, TPU pods). Nothing given (or one process): nothing happens.
    Must run before anything touches a device. On CPU, cross-process
    collectives use gloo.
    """
    coordinator = coordinator or _env("coordinator")
    if num_processes is None:
        num_processes = _env_number("num_processes", int)
    if process_id is None:
        process_id = _env_number("process_id", int)
    for name, value, kind in (
        ("heartbeat_timeout", heartbeat_timeout, int),
        ("step_timeout", step_timeout, float),
        ("wait_timeout", wait_timeout, float),
    ):
        value = _env_number(name, kind) if value is None else value
        if value is not None:
            if value <= 0:
                raise ValueError(f"{name} must be positive, got {value}")
            setattr(settings, name, value)
    auto = coordinator == "auto"
    if not auto:
        if coordinator is None and num_processes is None and process_id is None:
            return False
        if coordinator is None or num_processes is None or process_id is None:
            raise ValueError(
                "multi-process training needs all of --coordinator, --num-processes and "
                f"--process-id (got {coordinator=}, {num_processes=}, {process_id=})"
            )
        if num_processes == 1:
            return False
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(
        coordinator_address=None if auto else coordinator,
        num_processes=num_processes,
        process_id=process_id,
        initialization_timeout=initialization_timeout,
        heartbeat_timeout_seconds=settings.heartbeat_timeout,
        shutdown_timeout_seconds=shutdown_timeout,
    )
    multi = jax.process_count() > 1
    if multi:
        _start_beacon()
    return multi


# ----------------------------------------------------------------------------- liveness

BEACON_S = 1.0  # how often each process signals that it is alive (coordination service)


def _beacon_key(process_id: int) -> str:
    return f"gac_jax/alive/{process_id}"


def _start_beacon() -> None:
    """Every process increments its own counter in the coordination service every second.

    :func:`watch_peers` reads the counters: a peer whose counter stops moving is dead
    (or frozen) long before JAX's own heartbeat timeout ends the survivors with a C++
    abort.

    The beacon is stopped and joined at exit (registered with ``atexit`` after JAX's
    own handler, so it runs first): a daemon thread still inside
    a coordination-service call while the interpreter finalizes is ended by a forced
    unwind that the C++ binding catches, and the process aborts ("terminate called
    after throwing an instance of ''  FATAL: exception not rethrown", exit -6) after a
    run that finished.
    """
    from jax._src import distributed

    client, me = distributed.global_state.client, distributed.global_state.process_id
    stop = threading.Event()

    def beat() -> None:
        while not stop.is_set():
            with contextlib.suppress(Exception):  # the service may be gone: watchers decide
                client.key_value_increment(_beacon_key(me), 1)
            stop.wait(BEACON_S)

    thread = threading.Thread(target=beat, name="gac-beacon", daemon=True)
    thread.start()
    atexit.register(_stop_beacon, stop, thread)  # LIFO: before JAX's shutdown of the client


def _stop_beacon(stop: threading.Event, thread: threading.Thread, timeout_s: float = 10.0):
    """At exit: the beacon leaves its service call and ends (a call blocked on a dead
    service is left alone after ``timeout_s``)."""
    stop.set()
    thread.join(timeout_s)


@contextlib.contextmanager
def watch_peers(what: str, stall_s: float | None = None, poll_s: float = 0.5) -> Iterator[None]:
    """Inside: a peer that stops signalling for ``stall_s`` seconds (default: half the
    heartbeat timeout) ends this process with the one-line peer-lost error (exit 3).

    For waits that no collective interrupts when a peer dies (orbax's checkpoint
    barriers): JAX would notice only after ``heartbeat_timeout`` and then abort with a
    C++ stack trace. Single process: nothing happens.
    """
    client = _client()
    if client is None or jax.process_count() == 1:
        yield
        return
    stall_s = settings.heartbeat_timeout / 2 if stall_s is None else stall_s
    me, n = jax.process_index(), jax.process_count()
    done = threading.Event()

    def watch() -> None:
        seen: dict[int, tuple[str, float]] = {}
        while not done.wait(poll_s):
            now = time.monotonic()
            for peer in range(n):
                if peer == me:
                    continue
                try:
                    value = client.key_value_try_get(_beacon_key(peer))
                except Exception:  # noqa: BLE001 - not there yet, or the service is gone
                    value = None
                last = seen.get(peer)
                if last is None or value != last[0]:
                    seen[peer] = (value, now)
                elif now - last[1] > stall_s and not done.is_set():
                    exit_peer_lost(f"process {peer} gave no sign of life for {stall_s:g} s {what}")

    thread = threading.Thread(target=watch, name="gac-peer-watch", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        if thread is not threading.current_thread():
            thread.join(poll_s + 10.0)  # not left inside a service call at exit (see beacon)


_exit_lock = threading.Lock()


def exit_peer_lost(detail: str, hint: str | None = None) -> None:
    """Prints the one-line peer-lost error and ends this process with :data:`EXIT_PEER_LOST`.

    For threads that notice a dead peer while the main thread waits (a checkpoint
    barrier, :func:`watch_peers`).
    """
    hint = settings.peer_lost_hint if hint is None else hint
    first = detail.strip().splitlines()[0][:300] if detail.strip() else "no detail"
    exit_once(
        f"error: {_where_safe()}: lost contact with another process ({first}): it died "
        f"or hung. Stopping instead of waiting. {hint}".strip(),
        EXIT_PEER_LOST,
    )


def exit_once(message: str, code: int) -> None:
    """Prints ``message`` to stderr and ends the process with ``code`` at once, without
    Python's shutdown (peers may be dead or stuck in a collective with this process).
    When several threads get here, only the first one prints."""
    if _exit_lock.acquire(blocking=False):
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        _say(message)
    workdir_lock.release_all()  # a clean hand-back, not a stale lock for the next run
    os._exit(code)


def _say(text: str) -> None:
    with contextlib.suppress(OSError):
        os.write(2, (text + "\n").encode())


def _where_safe() -> str:
    try:
        return _where()
    except Exception:  # noqa: BLE001 - the backend may be unusable by now
        return "this process"


def is_main_process() -> bool:
    return jax.process_index() == 0


# ----------------------------------------------------------------------------- coordination


def _where() -> str:
    return f"process {jax.process_index()}/{jax.process_count()}"


_barrier_ids = itertools.count()


def _client():
    """The coordination-service client of ``jax.distributed.initialize`` (None if not started)."""
    from jax._src import distributed

    return distributed.global_state.client


def barrier(name: str, timeout_s: float | None = None) -> None:
    """Waits until every process reaches this barrier (no-op in a single process).

    Uses the coordination service (no device collective), so it fails within
    ``heartbeat_timeout`` when a peer dies and after ``timeout_s`` (default
    ``wait_timeout``) when one never arrives; both raise :class:`PeerLostError`.
    All processes must call the same barriers in the same order.
    """
    if jax.process_count() == 1:
        return
    timeout_s = settings.wait_timeout if timeout_s is None else timeout_s
    key = f"gac_jax/{next(_barrier_ids)}/{name}"
    client = _client()
    try:
        if client is None:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(key)
        else:
            client.wait_at_barrier(key, int(timeout_s * 1000))
    except Exception as e:
        raise PeerLostError(
            f"{_where()}: the other processes did not reach barrier {name!r} within "
            f"{timeout_s:g} s (or one of them died): {_first_line(e)}"
        ) from e


@contextlib.contextmanager
def main_process_first(name: str, timeout_s: float | None = None) -> Iterator[None]:
    """Runs the body on process 0 first and on the others after it finished.

    For work whose result process 0 writes to the shared work directory and
    the others then read (``with main_process_first('priors'): priors = load_or_compute()``).
    """
    if jax.process_count() > 1 and not is_main_process():
        barrier(name, timeout_s)
    yield
    if jax.process_count() > 1 and is_main_process():
        barrier(name, timeout_s)


class Pausable(Protocol):
    """What :func:`run_on_main` pauses while process 0 works alone (the trainers pass their
    :class:`~gac_jax.training.step_watchdog.ProgressWatchdog`, which imports this module)."""

    def paused(self) -> contextlib.AbstractContextManager[None]: ...


def run_on_main(
    fn: Callable[[], Any],
    name: str,
    watchdog: Pausable | None = None,
    timeout_s: float | None = None,
) -> Any:
    """Process 0 runs ``fn()`` while the others wait; returns its result there, None elsewhere.

    ``fn`` must not use collectives (evaluation uses local copies of replicated
    weights). The ``watchdog`` is paused meanwhile.
    """
    if jax.process_count() == 1:
        return fn()
    with watchdog.paused() if watchdog is not None else contextlib.nullcontext():
        result = fn() if is_main_process() else None
        barrier(name, timeout_s)
    return result


def check_shared_directory(directory: str | os.PathLike) -> None:
    """Checks that all processes see the same ``directory`` (orbax and the priors need it).

    Process 0 writes a random token there and publishes it through the
    coordination service; the others must read the same token from the file.
    Raises FileNotFoundError otherwise.
    """
    if jax.process_count() == 1:
        return
    path = Path(directory) / ".gac_jax_process_check"
    key = f"gac_jax/{next(_barrier_ids)}/shared_directory"
    client = _client()
    if is_main_process():
        token = os.urandom(8).hex()
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(token)
        if client is not None:
            client.key_value_set(key, token)
    if client is None:  # started without jax.distributed: share the token via a collective
        from jax.experimental import multihost_utils

        data = np.frombuffer(bytes.fromhex(token), np.uint8) if is_main_process() else None
        data = multihost_utils.broadcast_one_to_all(np.zeros(8, np.uint8) if data is None else data)
        token = bytes(np.asarray(data)).hex()
    elif not is_main_process():
        try:
            token = client.blocking_key_value_get(key, int(settings.wait_timeout * 1000))
        except Exception as e:
            raise PeerLostError(f"{_where()}: no word from process 0: {_first_line(e)}") from e
    seen = path.read_text().strip() if path.exists() else None
    if seen != token:
        raise FileNotFoundError(
            f"{_where()}: work directory {Path(directory).resolve()} is not the one process 0 "
            "writes to; in a multi-host run it must be on a filesystem shared by all hosts"
        )


# ----------------------------------------------------------------------------- stopping

_PEER_FAILURE_MARKERS = (
    "gloo",
    "nccl",
    "connection closed by peer",
    "connection reset",
    "coordination service",
    "heartbeat",
    "barrier",
    "deadline_exceeded",
    "unavailable:",
)


def is_peer_failure(error: BaseException) -> bool:
    """Whether ``error`` (or its cause) is a collective/coordination failure between processes."""
    if jax.process_count() == 1:
        return False
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, PeerLostError):
            return True
        text = str(error).lower()
        if any(marker in text for marker in _PEER_FAILURE_MARKERS):
            return True
        error = error.__cause__ or error.__context__
    return False


def raise_if_peer_failure(error: BaseException, hint: str = "") -> None:
    """Raises :class:`PeerLostError` (with ``hint``) from ``error`` if it is a peer failure."""
    if isinstance(error, PeerLostError) or not is_peer_failure(error):
        return
    raise PeerLostError(
        f"{_where()}: lost contact with another process ({_first_line(error)}): it died or "
        f"hung. Stopping instead of waiting. {hint}".strip()
    ) from error


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return text[0][:300] if text else type(error).__name__
