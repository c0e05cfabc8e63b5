"""Run folders that cannot be corrupted: one writer per workdir, and a full disk in one line.

* The workdir lock (``WORKDIR/.lock``): a second process is refused with the holder's pid,
  host and command; the lock is re-entrant in one process; a stale lock of a killed process
  is taken over, saying so.
* Two ``train.py`` on one workdir (plus ``evaluate.py`` on it meanwhile): the second trainer
  and the evaluation stop at once (exit 2, one line naming the holder), the first finishes
  unharmed, bit for bit equal to a lone run.
* A full disk: a 48 MB tmpfs where the test may mount one (root); otherwise a patched writer
  raising ``OSError(ENOSPC)``, so the test always runs. The depth trainer (``train.py``) whose
  first checkpoint fails in orbax's background threads prints one line and nothing else
  (the details go to ``W/details.log``), leaves no partial checkpoint and runs again to the
  end; the detector whose disk fills after checkpoint 4 stops at checkpoint 8 naming the
  kept checkpoint 4 and resumes from it to the lone run's parameters; ``evaluate.py`` on a
  full disk names the file it could not write.

The detector runs are ``configs/detect3d_default.py:tiny`` on the vendored real frames, the
depth runs ``configs/depth_default.py:tiny`` on the vendored KITTI-depth frame.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from gac_jax.cli import evaluate as evaluate_cli
from gac_jax.config import apply_overrides, load_config
from gac_jax.data import files
from gac_jax.data.io_errors import DiskWriteError, disk_failure, error_line, naming
from gac_jax.trainers import depth, detect3d
from gac_jax.training import workdir_lock
from gac_jax.training.checkpointing import TMP_MARKER, Checkpoints
from gac_jax.training.metrics_writer import MetricsWriter
from tests.conftest import tiny_train_args

REPO = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(REPO))
STEPS = 8  # detector runs: checkpoints 4 and 8


def detect3d_args(root: Path, workdir: Path) -> list[str]:
    return [
        *tiny_train_args(root, workdir),
        f"train.num_steps={STEPS}",
        "train.checkpoint_every=4",
        "train.log_every=1",
        "train.eval_at_end=False",
        "log.tensorboard=false",
    ]


def depth_args(root: Path, workdir: Path) -> list[str]:
    return [
        "--task",
        "depth",
        "--config",
        str(REPO / "configs" / "depth_default.py:tiny"),
        "--workdir",
        str(workdir),
        "data.source=kitti",
        f"data.root={root}",
        "data.val_split=train",
        "data.val_cameras=(2, 3)",
        "data.crop_height=352",
        "train.num_steps=2",  # one checkpoint, at the end
        "train.checkpoint_every=2",
        "train.log_every=1",
        "train.eval_at_end=False",
        "log.tensorboard=false",
    ]


def config_of(args: list[str]):
    """The config ``train.py args`` runs (the in-process runs share its code path)."""
    config = load_config(args[args.index("--config") + 1])
    apply_overrides(config, args[args.index("--workdir") + 2 :])
    return config


def train_py(args: list[str], **kwargs) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(REPO / "train.py"), *args],
        env=ENV,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        **kwargs,
    )


def state_arrays(workdir: Path, step: int) -> dict[str, np.ndarray]:
    """Every array of checkpoint ``step`` (parameters, batch stats, optimizer state ...)."""
    with Checkpoints(workdir) as ckpts:
        raw = ckpts._manager.restore(step)  # noqa: SLF001 - raw restore without a template
    leaves = jax.tree_util.tree_leaves_with_path(dict(raw["state"]))
    return {jax.tree_util.keystr(k): np.asarray(v) for k, v in leaves}


def assert_same_checkpoint(workdir: Path, reference: Path, step: int) -> None:
    got, expected = state_arrays(workdir, step), state_arrays(reference, step)
    assert got.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_array_equal(got[key], value, err_msg=key)


def wait_for(condition, proc: subprocess.Popen, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            raise AssertionError(f"exited ({proc.returncode}) before {what}: {proc.stdout.read()}")
        assert time.monotonic() < deadline, f"no {what} within {timeout} s"
        time.sleep(0.02)


def error_lines(output: str) -> list[str]:
    return [line for line in output.splitlines() if line.startswith("error:")]


@pytest.fixture(scope="module")
def lone_run(kitti_object_root, tmp_path_factory) -> Path:
    """The detector run of :func:`detect3d_args`, undisturbed, in this process."""
    workdir = tmp_path_factory.mktemp("lone") / "run"
    detect3d.train_and_evaluate(config_of(detect3d_args(kitti_object_root, workdir)), workdir)
    return workdir


@pytest.fixture
def small_disk(tmp_path):
    """A 48 MB tmpfs (``tmp_path/disk``) where this process may mount one, else None."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = False
    if hasattr(os, "geteuid") and os.geteuid() == 0 and shutil.which("mount"):
        cmd = ["mount", "-t", "tmpfs", "-o", "size=48m", "tmpfs", str(disk)]
        mounted = subprocess.run(cmd, capture_output=True).returncode == 0
    try:
        yield disk if mounted else None
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(disk)], check=True)


def fill(disk: Path, leave: int) -> Path:
    """Fills ``disk`` up to ``leave`` free bytes with one file; returns it."""
    filler = disk / "filler"
    size = shutil.disk_usage(disk).free - leave
    with open(filler, "wb") as f:
        os.posix_fallocate(f.fileno(), 0, size)
    return filler


# ----------------------------------------------------------------------------- the lock

HOLD = """
import sys, time
from gac_jax.training import workdir_lock
try:
    workdir_lock.acquire(sys.argv[1])
except workdir_lock.WorkdirBusyError as e:
    print("busy:", e, flush=True)
    sys.exit(2)
print("holding", flush=True)
time.sleep(float(sys.argv[2]))
"""


def other_process(workdir: Path, hold_s: float = 0.0) -> subprocess.Popen:
    cmd = [sys.executable, "-c", HOLD, str(workdir), str(hold_s)]
    return subprocess.Popen(cmd, env=ENV, stdout=subprocess.PIPE, text=True)


def test_the_lock_refuses_another_process_names_it_and_is_reentrant(tmp_path):
    workdir = tmp_path / "run"
    with workdir_lock.hold(workdir):
        info = json.loads((workdir / ".lock").read_text())
        assert info["pid"] == os.getpid() and info["host"] and info["command"]
        with workdir_lock.hold(workdir):  # re-entrant: the trainer evaluates in-process
            pass
        assert workdir_lock.is_held(workdir)
        out = other_process(workdir).communicate(timeout=60)[0]
        assert out.startswith(f"busy: {workdir / '.lock'}: run folder in use by pid {os.getpid()}")
        assert info["command"] in out and "wait for it to finish or stop it" in out
    assert not workdir_lock.is_held(workdir)
    assert (workdir / ".lock").read_text() == ""  # a clean release leaves no stale lock
    proc = other_process(workdir)
    assert proc.communicate(timeout=60)[0] == "holding\n" and proc.returncode == 0
    # Nothing is locked (or created) for a folder that does not exist, or outside it.
    with workdir_lock.hold_if_inside(tmp_path / "absent", None):
        assert not (tmp_path / "absent").exists()
    with workdir_lock.hold_if_inside(workdir, tmp_path / "elsewhere"):
        assert not workdir_lock.is_held(workdir)
    with workdir_lock.hold_if_inside(workdir, tmp_path / "elsewhere", workdir / "export"):
        assert workdir_lock.is_held(workdir)


def test_a_filesystem_without_locks_is_named_not_skipped(tmp_path, monkeypatch):
    def no_locks(fd, operation):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(workdir_lock.fcntl, "flock", no_locks)
    with pytest.raises(workdir_lock.LockUnsupportedError) as raised:
        workdir_lock.acquire(tmp_path)
    line = error_line(raised.value)
    assert line.startswith(f"{tmp_path / '.lock'}: cannot lock the run folder (No locks")
    assert "does not support file locks" in line and not workdir_lock.is_held(tmp_path)


def test_a_stale_lock_of_a_killed_process_is_taken_over(tmp_path, capsys):
    workdir = tmp_path / "run"
    holder = other_process(workdir, hold_s=60)
    assert holder.stdout.readline() == "holding\n"
    with pytest.raises(workdir_lock.WorkdirBusyError, match=f"in use by pid {holder.pid} on"):
        workdir_lock.acquire(workdir)
    holder.kill()  # SIGKILL: the kernel releases the lock, the file still names the holder
    holder.wait()
    with workdir_lock.hold(workdir):
        out = capsys.readouterr().out
        assert f"took over the stale lock of pid {holder.pid} on" in out
        assert json.loads((workdir / ".lock").read_text())["pid"] == os.getpid()


def test_a_second_trainer_and_an_evaluation_are_refused_the_first_finishes_unharmed(
    kitti_object_root, lone_run, tmp_path, request
):
    workdir = tmp_path / "run"
    args = detect3d_args(kitti_object_root, workdir)
    first = train_py(args)
    request.addfinalizer(lambda: first.poll() is None and first.kill())
    lock = workdir / ".lock"
    config = workdir / "config.json"  # written after the lock is taken
    wait_for(
        lambda: lock.exists() and lock.read_text().strip() and config.exists(),
        first,
        300,
        "the lock and config.json",
    )
    first.send_signal(signal.SIGSTOP)  # it holds the folder while the others try
    try:
        config_before = config.read_text()
        second = train_py([*args, "train.learning_rate=1e-2"])
        evaluation = subprocess.Popen(
            [sys.executable, str(REPO / "evaluate.py"), "--task", "detect3d"]
            + ["--workdir", str(workdir)],
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        outputs = [p.communicate(timeout=300)[0] for p in (second, evaluation)]
    finally:
        first.send_signal(signal.SIGCONT)
    holder = f"error: {lock}: run folder in use by pid {first.pid} on "
    for proc, out in zip((second, evaluation), outputs, strict=True):
        assert proc.returncode == 2, out[-3000:]
        lines = error_lines(out)
        assert len(lines) == 1 and lines[0].startswith(holder), out[-3000:]
        assert "train.py --task detect3d" in lines[0] and "Traceback" not in out
    assert (workdir / "config.json").read_text() == config_before  # the first run's config
    assert not (workdir / "eval").exists()
    out = first.communicate(timeout=600)[0]
    assert first.returncode == 0, out[-3000:]
    assert_same_checkpoint(workdir, lone_run, STEPS)
    rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    keys = [(r["kind"], r["step"]) for r in rows]
    assert len(keys) == len(set(keys)) and len(rows) == STEPS + 1  # + the compile row
    assert lock.read_text() == ""


# ----------------------------------------------------------------------------- a full disk


def test_disk_failures_are_recognised_and_named(tmp_path):
    tensorstore = ValueError(
        'RESOURCE_EXHAUSTED: Error writing "params.conv/0" in OCDBT database at local file '
        '"/w/checkpoints/6.orbax-checkpoint-tmp/state/ocdbt.process_0/": Failed writing: '
        '"/w/checkpoints/6.orbax-checkpoint-tmp/d/ab12": Failed to write 122923 bytes to '
        "file 6: No space left on device [os_error_code='28']"
    )
    assert disk_failure(RuntimeError("a bug")) is None
    failure = disk_failure(tensorstore)
    assert failure.errno == errno.ENOSPC
    assert failure.path == "/w/checkpoints/6.orbax-checkpoint-tmp/d/ab12"
    oom = ValueError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 2.0GiB")
    assert disk_failure(oom) is None  # device memory, not the disk
    # A nameless OSError (write/flush/close) gets the file being written, and the free space.
    with pytest.raises(OSError) as raised, naming(tmp_path / "metrics.jsonl"):
        raise OSError(errno.ENOSPC, "No space left on device")
    line = error_line(raised.value)
    assert line.startswith(f"{tmp_path / 'metrics.jsonl'}: no space left on device (")
    assert line.endswith(" MB free)")
    assert error_line(OSError(errno.EACCES, "Permission denied"), tmp_path) == (
        f"{tmp_path}: Permission denied"
    )
    # A real full device: the metrics file on /dev/full.
    writer = MetricsWriter(tmp_path)
    os.symlink("/dev/full", tmp_path / "metrics.jsonl")
    with pytest.raises(OSError) as raised:
        writer.write(1, loss=1.0)
    assert raised.value.errno == errno.ENOSPC
    assert raised.value.filename == str(tmp_path / "metrics.jsonl")


def test_a_writer_removes_partial_checkpoints_a_reader_leaves_them(tmp_path):
    partial = tmp_path / "checkpoints" / f"6{TMP_MARKER}"
    (partial / "state").mkdir(parents=True)
    Checkpoints(tmp_path).close()  # evaluation, export: a save may be in progress
    assert partial.exists()
    Checkpoints(tmp_path, writer=True).close()  # the trainer, holding the folder
    assert not partial.exists()


def test_depth_first_checkpoint_on_a_full_disk_one_line_then_runs_again(
    kitti_samples, small_disk, tmp_path, monkeypatch
):
    root = kitti_samples / "depth"
    if small_disk is None:  # no tmpfs here: orbax's save raises ENOSPC instead
        workdir = tmp_path / "run"
        args = depth_args(root, workdir)
        original = ocp.CheckpointManager.save

        def full(self, step, *a, **k):
            raise OSError(errno.ENOSPC, "No space left on device", str(workdir / "x"))

        monkeypatch.setattr(ocp.CheckpointManager, "save", full)
        with pytest.raises(DiskWriteError) as raised:
            depth.train_and_evaluate(config_of(args), workdir)
        line = f"error: {raised.value}"
        monkeypatch.setattr(ocp.CheckpointManager, "save", original)
        filler = None
    else:
        workdir = small_disk / "run"
        args = depth_args(root, workdir)
        proc = train_py(args)
        prior = workdir / "prior_mean.json"
        wait_for(prior.exists, proc, 300, "the prior mean")  # long before checkpoint 2
        proc.send_signal(signal.SIGSTOP)
        filler = fill(small_disk, leave=256_000)  # room for metrics, not for a checkpoint
        proc.send_signal(signal.SIGCONT)
        out = proc.communicate(timeout=600)[0]
        assert proc.returncode == 1, out[-3000:]
        for noise in ("Traceback", "ERROR", "absl", "Event loop", "RESOURCE_EXHAUSTED"):
            assert noise not in out, out[-3000:]
        lines = error_lines(out)
        assert len(lines) == 1, out[-3000:]
        line = lines[0]
        assert "No space left on device" in (workdir / "details.log").read_text()
        assert (workdir / ".lock").read_text() == ""  # handed back, not stale
    assert line.startswith(f"error: {workdir / 'checkpoints' / '2'}: no space left on device (")
    assert line.endswith(
        f"no checkpoint was complete yet (details in {workdir / 'details.log'})"
    ), line
    assert not list((workdir / "checkpoints").glob(f"*{TMP_MARKER}*"))
    if filler is not None:
        filler.unlink()  # space again: the same command runs to the end
        rerun = train_py(args)
        out = rerun.communicate(timeout=600)[0]
        assert rerun.returncode == 0 and "stale lock" not in out, out[-3000:]
    else:
        depth.train_and_evaluate(config_of(args), workdir)
    with Checkpoints(workdir) as ckpts:
        assert ckpts.all_steps() == [2]


def test_detector_disk_full_after_a_checkpoint_resumes_to_the_lone_run(
    kitti_object_root, lone_run, small_disk, tmp_path, monkeypatch, capsys
):
    workdir = (small_disk or tmp_path) / "run"
    args = detect3d_args(kitti_object_root, workdir)
    fillers = []
    if small_disk is not None:  # the disk fills up after checkpoint 4
        original = Checkpoints.save

        def save_then_fill(self, step, *a, **k):
            original(self, step, *a, **k)
            if step == 4:
                fillers.append(fill(small_disk, leave=64_000))

        monkeypatch.setattr(Checkpoints, "save", save_then_fill)
    else:  # no tmpfs here: orbax's save of checkpoint 8 raises ENOSPC
        original = ocp.CheckpointManager.save

        def full_at_8(self, step, *a, **k):
            if step == 8:
                raise OSError(errno.ENOSPC, "No space left on device", str(workdir / "x"))
            return original(self, step, *a, **k)

        monkeypatch.setattr(ocp.CheckpointManager, "save", full_at_8)
    with pytest.raises(DiskWriteError) as raised:
        detect3d.train_and_evaluate(config_of(args), workdir)
    message = str(raised.value)
    assert "\n" not in message and message.startswith(f"{workdir / 'checkpoints' / '8'}: ")
    if fillers:  # the check before the save: nothing was written
        assert "not enough space for checkpoint 8 (" in message and "MB free, a checkpoint" in (
            message
        )
    assert message.endswith(
        f"; kept checkpoint 4 in {workdir / 'checkpoints'} (details in {workdir / 'details.log'})"
    )
    assert not list((workdir / "checkpoints").glob(f"*{TMP_MARKER}*"))
    assert not workdir_lock.is_held(workdir)
    monkeypatch.undo()
    for filler in fillers:
        filler.unlink()
    capsys.readouterr()
    detect3d.train_and_evaluate(config_of(args), workdir)
    assert f"resumed from {workdir / 'checkpoints'} at step 4" in capsys.readouterr().out
    assert_same_checkpoint(workdir, lone_run, STEPS)


class _OsWritingToDevFull:
    """``os`` for :mod:`gac_jax.data.files`: every file it writes goes to ``/dev/full``."""

    def __getattr__(self, name):
        return getattr(os, name)

    @staticmethod
    def fdopen(fd, mode="r", *args, **kwargs):
        os.close(fd)
        return open("/dev/full", mode)  # noqa: SIM115 - closed by atomic_write


def test_evaluate_on_a_full_disk_names_the_file(
    lone_run, small_disk, tmp_path, monkeypatch, capsys
):
    workdir = (small_disk or tmp_path) / "run"
    shutil.copytree(lone_run, workdir)
    with contextlib.ExitStack() as stack:
        stack.enter_context(workdir_lock.hold(workdir))  # written before the disk is full
        if small_disk is not None:
            stack.callback(fill(small_disk, leave=0).unlink)
        else:  # no tmpfs here: its files are written to /dev/full
            monkeypatch.setattr(files, "os", _OsWritingToDevFull())
        capsys.readouterr()
        code = evaluate_cli.main(["--task", "detect3d", "--workdir", str(workdir)])
    err = capsys.readouterr().err
    assert code == 1, err
    lines = error_lines(err)
    assert len(lines) == 1 and err.strip() == lines[0], err
    assert lines[0].startswith(f"error: {workdir / 'eval'}"), err  # the file, not ": No space"
    assert ": no space left on device (" in lines[0] and lines[0].endswith(" MB free)"), err
    assert not workdir_lock.is_held(workdir)


def test_atomic_writes_get_the_mode_of_a_plain_open(tmp_path):
    """A file written atomically (config.json, results, the generated dataset) is readable as a
    plain ``open(path, 'w')`` file would be, not mkstemp's owner-only 0600."""
    import stat

    from gac_jax.data.files import atomic_write

    with atomic_write(tmp_path / "a.txt") as f:
        f.write("a")
    (tmp_path / "b.txt").write_text("b")
    modes = [stat.S_IMODE((tmp_path / n).stat().st_mode) for n in ("a.txt", "b.txt")]
    assert modes[0] == modes[1]
