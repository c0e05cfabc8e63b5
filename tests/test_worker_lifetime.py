"""Helper processes live exactly as long as their owner, under every start method.

An owner script written like ``train.py`` (``mark_owner()`` at start-up, the
``__mp_main__`` guard at the top of the module, which spawn and forkserver children and
the fork server itself run) starts a process pool with the generator's initializer; the
workers must stay alive while the owner lives (the forkserver crash of issue 22: they
exited at once) and be gone within seconds of a SIGKILL of the owner.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gac_jax.data import worker_lifetime
from gac_jax.data.worker_lifetime import Owner

REPO = Path(__file__).resolve().parents[1]

OWNER_SCRIPT = """
import os, sys, time
if __name__ == "__mp_main__":
    from gac_jax.data.worker_lifetime import guard_spawned_child
    guard_spawned_child()


def work(_):
    time.sleep(0.3)  # every worker gets a task
    return os.getpid()


if __name__ == "__main__":
    import concurrent.futures, multiprocessing
    from gac_jax.data.synthetic import generated_dir
    from gac_jax.data.worker_lifetime import Owner, mark_owner
    mark_owner()
    context = multiprocessing.get_context(sys.argv[1])
    pool = concurrent.futures.ProcessPoolExecutor(
        2, mp_context=context, initializer=generated_dir.init_worker,
        initargs=(Owner.current().token(),))
    pids = sorted(set(pool.map(work, range(8))))
    print(" ".join(map(str, pids)), flush=True)
    time.sleep(120)
"""


def alive(pid: int) -> bool:
    return Owner(pid).alive()


@pytest.mark.parametrize("method", ["forkserver", "spawn", "fork"])
def test_workers_live_with_their_owner_and_die_with_it(method, tmp_path):
    script = tmp_path / "owner.py"
    script.write_text(OWNER_SCRIPT)
    env = dict(os.environ, PYTHONPATH=str(REPO))
    owner = subprocess.Popen(
        [sys.executable, str(script), method],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    try:
        line = owner.stdout.readline().decode()
        assert line.strip(), f"no workers reported: {owner.stderr.read().decode()[-3000:]}"
        workers = [int(p) for p in line.split()]
        assert len(workers) >= 1
        time.sleep(4 * worker_lifetime.POLL_S)  # several watchdog polls with the owner alive
        assert owner.poll() is None, owner.stderr.read().decode()[-3000:]
        assert all(alive(p) for p in workers), "a worker exited while its owner lived"
    finally:
        owner.kill()
        owner.wait()  # reaped: the workers' watchdogs see the owner gone
    deadline = time.monotonic() + 5
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [p for p in workers if alive(p)], "workers outlived their killed owner"


def test_an_unreaped_owner_counts_as_gone(tmp_path):
    """A SIGKILLed owner whose parent has not waited for it yet (a zombie) is gone."""
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    owner = Owner.of(proc.pid)
    assert owner.alive()
    proc.kill()
    deadline = time.monotonic() + 5
    while owner.alive() and time.monotonic() < deadline:
        time.sleep(0.02)
    assert not owner.alive()
    assert Path(f"/proc/{proc.pid}").exists() or sys.platform != "linux"  # not reaped yet
    proc.wait()


def test_a_recycled_pid_is_not_the_owner():
    me = Owner.current()
    assert me.alive()
    if me.start is not None:
        assert not Owner(me.pid, me.start + 1).alive()
    assert Owner.parse(me.token()) == me
    assert Owner.parse("") is None and Owner.parse("12:x") is None
    assert not Owner(0).alive()
