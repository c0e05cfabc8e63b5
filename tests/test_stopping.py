"""Stopping a run: a second Ctrl-C stops at once, and no loader worker outlives its trainer
(SIGKILL included). (SIGTERM's checkpoint and bit-exact resume: tests/test_train_detect3d.py.)

``train.py`` subprocesses of the ``:tiny`` detector on the vendored real frames, with grain
loader workers (``data.num_workers=2``); steps are few and the compilation cache of the test
session is shared (tests/conftest.py).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from gac_jax.training.multiprocess import EXIT_INTERRUPTED

REPO = Path(__file__).resolve().parents[1]
CONFIG = str(REPO / "configs" / "detect3d_default.py:tiny")


def overrides(root: Path, steps: int) -> list[str]:
    return [
        "data.source=kitti",
        f"data.root={root}",
        "data.train_split=labeled",
        "data.val_split=labeled",
        "data.use_right_image=False",
        f"train.num_steps={steps}",
        "train.checkpoint_every=1000",  # checkpoints only from the stop and the end
        "train.log_every=1",
        "train.eval_at_end=False",
        "log.tensorboard=false",
    ]


def start(workdir: Path, root: Path, steps: int, workers: int = 0) -> subprocess.Popen:
    cmd = [sys.executable, str(REPO / "train.py"), "--task", "detect3d", "--config", CONFIG]
    cmd += ["--workdir", str(workdir), *overrides(root, steps), f"data.num_workers={workers}"]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def children(pid: int) -> list[int]:
    """Pids of all living descendants of ``pid`` (from /proc)."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2 :].split()
            if fields[0] != "Z":
                parents.setdefault(int(fields[1]), []).append(int(entry.name))
    out, todo = [], [pid]
    while todo:
        kids = parents.get(todo.pop(), [])
        out += kids
        todo += kids
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return state[state.rindex(")") + 2] != "Z"


def wait_for(condition, proc: subprocess.Popen, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(
                f"exited ({proc.returncode}) before {what}: " + proc.stdout.read().decode()[-3000:]
            )
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.05)


def test_sigkill_leaves_no_loader_worker_behind(kitti_object_root, tmp_path):
    proc = start(tmp_path / "wd", kitti_object_root, 50, workers=2)
    wait_for(lambda: len(children(proc.pid)) >= 2, proc, 300, "loader workers")
    workers = children(proc.pid)
    proc.kill()
    proc.wait()
    deadline = time.monotonic() + 10
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in workers if alive(p)], "loader workers outlived the killed trainer"
    assert not (tmp_path / "wd" / "tensorboard").exists()  # log.tensorboard=false


def test_second_interrupt_stops_at_once(kitti_object_root, tmp_path):
    proc = start(tmp_path / "wd", kitti_object_root, 50, workers=2)
    wait_for(lambda: len(children(proc.pid)) >= 2, proc, 300, "loader workers")
    workers = children(proc.pid)
    proc.send_signal(signal.SIGINT)
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    out = proc.communicate(timeout=10)[0].decode()
    assert proc.returncode == EXIT_INTERRUPTED, out[-3000:]
    assert "SIGINT received" in out and "second interrupt" in out
    deadline = time.monotonic() + 10
    while any(alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [p for p in workers if alive(p)]


CHILD = """
import sys, time
from gac_jax.data.worker_lifetime import exit_with_owner
exit_with_owner(poll_s=0.1)
open(sys.argv[1], "w").close()
time.sleep(60)
"""
PARENT = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", sys.argv[1], sys.argv[2]])
print(child.pid, flush=True)
time.sleep(60)
"""


def test_a_worker_exits_when_its_parent_is_killed(tmp_path):
    """The watchdog alone, in a plain process tree: parent -> child (no owner named: the
    parent is the owner); SIGKILL the parent."""
    ready = tmp_path / "ready"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.pop("GAC_JAX_OWNER", None)
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT, CHILD, str(ready)], stdout=subprocess.PIPE, env=env
    )
    child = int(parent.stdout.readline())
    deadline = time.monotonic() + 30
    while not ready.exists():
        assert time.monotonic() < deadline, "child did not start"
        time.sleep(0.02)
    assert alive(child)
    parent.kill()
    parent.wait()
    deadline = time.monotonic() + 5
    while alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not alive(child)


def test_sigterm_while_generating_the_dataset_stops_at_once(tmp_path):
    """A stop signal during the first run's dataset generation stops it within a frame or two
    (exit 75, what was written kept, one line saying so), not after the whole dataset."""
    cmd = [sys.executable, str(REPO / "train.py"), "--task", "detect3d", "--config", CONFIG]
    cmd += ["--workdir", str(tmp_path / "w"), "data.synthetic.num_frames=600"]
    env = dict(os.environ, PYTHONPATH=str(REPO), GAC_JAX_CACHE=str(tmp_path / "cache"))
    proc = subprocess.Popen(
        cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
    )
    try:
        pngs = lambda: list((tmp_path / "cache").rglob("image_2/*.png"))  # noqa: E731
        wait_for(lambda: len(pngs()) >= 3, proc, 120, "the first frames")
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    text = out.decode()
    assert proc.returncode == 75, text[-2000:]
    assert "stopped while generating the embedded dataset" in text, text[-2000:]
    assert 3 <= len(pngs()) < 300, text[-500:]  # far from the whole dataset
