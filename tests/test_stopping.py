"""Stopping a run: SIGTERM saves and resumes bit for bit, a second Ctrl-C stops at once, and no
loader worker outlives its trainer (SIGKILL included).

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

import jax
import numpy as np

from gac_jax.checkpointing import Checkpoints
from gac_jax.config import apply_overrides, load_config
from gac_jax.multiprocess import EXIT_INTERRUPTED, EXIT_PREEMPTED
from gac_jax.trainers import detect3d

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


def logged_steps(workdir: Path) -> int:
    path = workdir / "metrics.jsonl"
    return path.read_text().count('"train"') if path.exists() else 0


def params(workdir: Path, step: int) -> dict:
    with Checkpoints(workdir) as ckpts:
        raw = ckpts._manager.restore(step)  # noqa: SLF001 - raw restore without a template
    return jax.tree.map(np.asarray, dict(raw["state"])["params"])


def test_sigterm_saves_and_the_rerun_matches_an_uninterrupted_run(kitti_object_root, tmp_path):
    steps = 4
    stopped, clean = tmp_path / "stopped", tmp_path / "clean"
    proc = start(stopped, kitti_object_root, steps, workers=2)
    wait_for(lambda: logged_steps(stopped) >= 1, proc, 300, "first logged step")
    proc.send_signal(signal.SIGTERM)
    out = proc.communicate(timeout=120)[0].decode()
    assert proc.returncode == EXIT_PREEMPTED, out[-3000:]
    with Checkpoints(stopped) as ckpts:
        at = ckpts.latest_step()
    assert 1 <= at < steps, out[-3000:]
    lines = [line for line in out.splitlines() if line.startswith("stopped at")]
    assert lines == [f"stopped at step {at}, checkpoint saved; run the same command to resume"]
    assert "SIGTERM received" in out and "Traceback" not in out
    assert not (stopped / "tensorboard").exists()  # log.tensorboard=false

    rerun = start(stopped, kitti_object_root, steps)
    out = rerun.communicate(timeout=300)[0].decode()
    assert rerun.returncode == 0, out[-3000:]
    assert f"at step {at}" in out
    # The uninterrupted run, in this process (the same compiled step as train.py).
    config = load_config(CONFIG)
    apply_overrides(config, [*overrides(kitti_object_root, steps), "data.num_workers=0"])
    detect3d.train_and_evaluate(config, clean)
    a, b = params(stopped, steps), params(clean, steps)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)


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
from gac_jax.data.worker_lifetime import exit_with_parent
exit_with_parent(poll_s=0.1)
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
    """The watchdog alone, in a plain process tree: parent -> child; SIGKILL the parent."""
    ready = tmp_path / "ready"
    env = dict(os.environ, PYTHONPATH=str(REPO))
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
