"""Multi-process training: 2 processes on localhost (CPU, gloo) through ``train.py``.

The detection runs are the ``:tiny`` detector on the vendored real KITTI frames with a global
batch of 4 and plain SGD (patched in by the worker below: the update is linear in the gradient,
so parameters of different process counts compare to float tolerance; Adam's m / sqrt(v) turns
float-noise gradients of near-unused weights into full-size steps). A persistent compilation
cache shared by all launches and cheap XLA CPU optimisation settings keep their start-up short
(JAX writes the cache from process 0 only, and process 1's keys differ on CPU, so process 1
compiles in every launch).

One test, in the order a user would meet these situations:

* reference: one process (two CPU devices), steps 0 -> 12, a checkpoint at every step;
* 1 -> 2 processes: two processes resume the reference's step-4 checkpoint;
  SIGKILL process 1 mid-run: process 0 exits at once with a clear message;
* restart both: they resume the last checkpoint; SIGTERM to process 1: both
  stop at the same step after a checkpoint. Every logged loss and the
  parameters there equal the reference's;
* 2 -> 1 processes: one process resumes and finishes; step 12 == reference.

Two quick ones: a process that hangs while alive (heartbeats go on) is caught by
the step watchdog on both sides; work directories that are not shared are refused.

The depth trainer: two processes of its ``:tiny`` config on the embedded generated
scenes (one random view per frame, the paper's epoch) make the same updates as one,
and process 0 evaluates mid-run while process 1 waits.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from gac_jax.training.checkpointing import Checkpoints
from tests.conftest import tiny_train_args

REPO = Path(__file__).resolve().parents[1]
TOTAL_STEPS = 12
SGD_LR = 0.05
# Single-process runs use two CPU devices: each device then computes on the same
# per-device batch as in the two-process runs (XLA's CPU kernels round differently for
# different shapes, and a few steps of training amplify that to visible differences).
ONE_PROCESS_TWO_DEVICES = "--xla_force_host_platform_device_count=2"

# train.py with the optimizer replaced by constant-rate SGD (see the module docstring).
WORKER = f"""
import sys
sys.path.insert(0, {str(REPO)!r})
import optax
import train
from gac_jax.trainers import depth, detect3d
detect3d.make_optimizer = depth.make_optimizer = lambda *args, **kwargs: optax.sgd({SGD_LR})
sys.exit(train.main(sys.argv[1:]))
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_pair(command, env: dict, timeout: float = 120) -> tuple[list, list[str]]:
    """Runs ``command(i)`` for processes 0 and 1 to their end (both must end within
    ``timeout``: no hang); returns the processes and their outputs. Leftovers are killed."""
    procs = [
        subprocess.Popen(
            command(i),
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        for i in range(2)
    ]
    try:
        outs = [p.communicate(timeout=timeout)[0] for p in procs]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    return procs, outs


def tiny_args(root: Path, workdir: Path) -> list[str]:
    return [
        *tiny_train_args(root, workdir),
        "data.batch_size=4",
        f"train.num_steps={TOTAL_STEPS}",
        "train.log_every=1",
        "train.keep_checkpoints=20",
        "train.eval_at_end=False",
        # Gradients that jump when a value crosses a threshold turn float noise into visible
        # parameter differences within a few steps: the reference's loss cut-offs, and the
        # GAC module's sampling at predicted rows (floor / clamp), here a plain conv instead.
        "loss.focal_min_loss=0.0",
        "loss.smooth_l1_min_residual=0.0",
        "model.regression_block=conv",
    ]


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict:
    cache = tmp_path_factory.mktemp("jax_cache")
    env = dict(os.environ)
    env.update(
        # One CPU device per process; fast compilation of the tiny model.
        XLA_FLAGS="--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true",
        PYTHONPATH=str(REPO),
        PYTHONUNBUFFERED="1",
        JAX_PLATFORMS="cpu",
        JAX_COMPILATION_CACHE_DIR=str(cache),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
        JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
        GAC_HEARTBEAT_TIMEOUT="10",
        GAC_STEP_TIMEOUT="120",
    )
    return env


class Run:
    """``num_processes`` workers of one job (train.py + SGD), logging to ``tmp/<name>.pI.log``."""

    def __init__(
        self,
        name: str,
        args: list[str],
        env: dict,
        num_processes: int,
        tmp: Path,
        worker: str = WORKER,
    ):
        port = free_port()
        self.logs = [tmp / f"{name}.p{i}.log" for i in range(num_processes)]
        self.procs = []
        if num_processes == 1:  # two devices, so per-device shapes match the 2-process runs
            env = dict(env, XLA_FLAGS=f"{env['XLA_FLAGS']} {ONE_PROCESS_TWO_DEVICES}")
        for i, log in enumerate(self.logs):
            flags = []
            if num_processes > 1:
                flags = ["--coordinator", f"localhost:{port}", "--num-processes"]
                flags += [str(num_processes), "--process-id", str(i)]
            with open(log, "w") as f:
                self.procs.append(
                    subprocess.Popen(
                        [sys.executable, "-c", worker, *flags, *args],
                        env=env,
                        stdout=f,
                        stderr=subprocess.STDOUT,
                        start_new_session=True,
                    )
                )

    def log(self, i: int) -> str:
        return self.logs[i].read_text()

    def tails(self) -> str:
        return "\n".join(f"--- process {i}:\n{self.log(i)[-2500:]}" for i in range(len(self.logs)))

    def wait(self, timeout: float) -> list[int]:
        deadline = time.time() + timeout
        try:
            return [p.wait(timeout=max(deadline - time.time(), 0.1)) for p in self.procs]
        except subprocess.TimeoutExpired:
            self.kill()
            pytest.fail(f"processes still running after {timeout} s\n{self.tails()}")

    def kill(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def wait_for(condition, run: Run, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while not condition():
        if any(p.poll() is not None for p in run.procs):
            run.kill()
            pytest.fail(f"a process ended before {what}\n{run.tails()}")
        if time.time() > deadline:
            run.kill()
            pytest.fail(f"no {what} within {timeout} s\n{run.tails()}")
        time.sleep(0.05)


def params(workdir: Path, step: int) -> dict:
    with Checkpoints(workdir) as ckpts:
        state, meta = ckpts.restore_local(step)  # from 1 or 2 processes alike
    assert meta["step"] == step
    return state["params"]


def assert_params_close(workdir: Path, reference: Path, step: int) -> None:
    def max_abs_diff(x, y) -> float:
        return max(jax.tree.leaves(jax.tree.map(lambda a, b: float(np.max(np.abs(a - b))), x, y)))

    got, expected = params(workdir, step), params(reference, step)
    diff, moved = max_abs_diff(got, expected), max_abs_diff(expected, params(reference, 1))
    print(f"step {step}: max |param - reference| {diff:.2e}, moved since step 1 {moved:.2e}")
    # Float-noise level, and far below how far SGD moved the weights since step 1.
    assert diff < 2e-6, (step, diff)
    assert moved > 1e-3, moved


def train_losses(workdir: Path) -> dict[int, float]:
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    return {r["step"]: r["loss"] for r in records if r["kind"] == "train"}


def test_two_processes_train_like_one_survive_a_kill_and_resume_across_counts(
    kitti_object_root, env, tmp_path
):
    # Reference: one process, steps 0 -> 12, a checkpoint at every step.
    reference = tmp_path / "reference"
    args = tiny_args(kitti_object_root, reference) + ["train.checkpoint_every=1"]
    run = Run("reference", args, env, 1, tmp_path)
    assert run.wait(300) == [0], run.tails()
    with Checkpoints(reference) as ckpts:
        assert ckpts.all_steps() == list(range(1, TOTAL_STEPS + 1))

    # 1 -> 2 processes: two processes resume the reference's step-4 checkpoint.
    workdir = tmp_path / "work"
    shutil.copytree(reference, workdir)
    for ckpt in (workdir / "checkpoints").iterdir():
        if ckpt.name.isdigit() and int(ckpt.name) != 4:
            shutil.rmtree(ckpt)
    args = tiny_args(kitti_object_root, workdir) + ["train.checkpoint_every=2"]
    run = Run("killed", args, env, 2, tmp_path)
    try:
        # SIGKILL process 1 mid-run: process 0 must stop with a clear message, not hang.
        wait_for((workdir / "checkpoints" / "6").exists, run, 300, "checkpoint at step 6")
        run.procs[1].kill()
        killed_at = time.time()
        code = run.procs[0].wait(timeout=60)
        print(f"process 0 exited {time.time() - killed_at:.1f} s after process 1 was killed")
    finally:
        run.kill()
    assert f"resumed from {workdir / 'checkpoints'} at step 4" in run.log(0)
    assert code == 3, run.tails()
    assert "lost contact with another process" in run.log(0), run.tails()
    assert "Restart all processes to resume from the last checkpoint" in run.log(0)
    # Only process 0 reports progress.
    assert "step 5/12" in run.log(0) and "step 5/12" not in run.log(1)
    with Checkpoints(workdir) as ckpts:
        last = ckpts.latest_step()
    assert 6 <= last < TOTAL_STEPS - 2, run.tails()

    # Restart both: they resume the last checkpoint. SIGTERM (a preemption notice) to
    # process 1 after its first step: both stop at the same step after a checkpoint.
    metrics = workdir / "metrics.jsonl"
    run = Run("restarted", args, env, 2, tmp_path)
    try:
        wait_for(
            lambda: f'"step": {last + 1}, "kind": "train"' in metrics.read_text(),
            run,
            300,
            f"step {last + 1}",
        )
        run.procs[1].send_signal(signal.SIGTERM)
        codes = run.wait(120)
    finally:
        run.kill()
    assert f"resumed from {workdir / 'checkpoints'} at step {last}" in run.log(0)
    assert codes == [75, 75], run.tails()
    with Checkpoints(workdir) as ckpts:
        stopped = ckpts.latest_step()
    assert last < stopped < TOTAL_STEPS, run.tails()
    assert (
        f"stopped at step {stopped}, checkpoint saved; run the same command to resume" in run.log(0)
    )

    # Two processes made the same updates as one on the same global batches: every
    # logged loss (one history despite the kill) and the parameters where they stopped.
    losses, expected = train_losses(workdir), train_losses(reference)
    assert sorted(losses) == list(range(1, stopped + 1))
    np.testing.assert_allclose(
        [losses[s] for s in losses], [expected[s] for s in losses], rtol=1e-5
    )
    assert_params_close(workdir, reference, stopped)
    # One copy on disk: no larger than a single-process checkpoint plus per-process indexes.
    size = sum(f.stat().st_size for f in (workdir / "checkpoints" / str(stopped)).rglob("*"))
    ref_size = sum(f.stat().st_size for f in (reference / "checkpoints" / "1").rglob("*"))
    assert size < 1.5 * ref_size, (size, ref_size)

    # 2 -> 1 processes: one process resumes and finishes.
    run = Run("one", args, env, 1, tmp_path)
    assert run.wait(300) == [0], run.tails()
    assert f"resumed from {workdir / 'checkpoints'} at step {stopped}" in run.log(0)
    assert_params_close(workdir, reference, TOTAL_STEPS)


# train.py whose process 1 dies (SIGKILL) while its step-2 checkpoint is being written.
DIES_DURING_SAVE = WORKER.replace(
    "sys.exit(train.main",
    """import os, signal, jax
from gac_jax.training.checkpointing import Checkpoints
save = Checkpoints.save
def dying_save(self, step, state, meta=None, wait=True):
    if jax.process_index() == 1 and step == 2:
        save(self, step, state, meta, wait=False)  # the asynchronous write is under way
        print("process 1 dies while saving", flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    return save(self, step, state, meta, wait)
Checkpoints.save = dying_save
sys.exit(train.main""",
)


def test_a_peer_lost_while_a_checkpoint_is_written_is_a_clean_stop(
    kitti_object_root, env, tmp_path
):
    workdir = tmp_path / "work"
    args = tiny_args(kitti_object_root, workdir) + ["train.checkpoint_every=2"]
    run = Run("dies_saving", args, env, 2, tmp_path, worker=DIES_DURING_SAVE)
    try:
        wait_for(lambda: "dies while saving" in run.log(1), run, 300, "process 1's save")
        died = time.time()
        code = run.procs[0].wait(timeout=60)
        waited = time.time() - died
        print(f"process 0 exited {waited:.1f} s after process 1 died")
    finally:
        run.kill()
    log = run.log(0)
    assert code == 3, run.tails()
    errors = [line for line in log.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1 and "lost contact with another process" in errors[0], run.tails()
    assert "Check failure" not in log and "Traceback" not in log, run.tails()
    assert waited < 10 + 5  # GAC_HEARTBEAT_TIMEOUT, plus the poll interval and exit
    with Checkpoints(workdir) as ckpts:
        assert ckpts.latest_step() is None  # the half-written step-2 checkpoint is not one


HANGING_WORKER = f"""
import os, sys, time
sys.path.insert(0, {str(REPO)!r})
from gac_jax.training import multiprocess, parallel, step_watchdog
process_id, port = int(sys.argv[1]), sys.argv[2]
multiprocess.initialize_distributed(f"localhost:{{port}}", 2, process_id, step_timeout=3)
import jax, numpy as np
mesh = parallel.make_mesh()
total = jax.jit(lambda x: x.sum(), out_shardings=parallel.replicated(mesh))
try:  # the trainer's loop, in miniature
    with step_watchdog.ProgressWatchdog(hint="(restart hint)") as watchdog:
        for step in range(1, 1000):
            batch = parallel.to_global({{"x": np.full((1,), step, np.float32)}}, mesh)
            out = total(batch["x"])
            watchdog.step(step, out)
            assert float(out) == 2 * step
            if process_id == 1 and step == 20:
                print("process 1 hangs", flush=True)
                time.sleep(1000)  # alive, heartbeats go on, never joins the next collective
except Exception as e:
    multiprocess.raise_if_peer_failure(e, "(restart hint)")
    raise
"""
# (train.py prints PeerLostError and leaves with exit code 3; here the traceback shows it.)


def test_a_hanging_process_is_stopped_by_the_step_watchdog(env, tmp_path):
    port = str(free_port())
    procs, outs = run_pair(lambda i: [sys.executable, "-c", HANGING_WORKER, str(i), port], env)
    assert "process 1 hangs" in outs[1]
    assert all(p.returncode != 0 for p in procs), outs
    # Whichever watchdog fires first (their clocks start a step apart), the stop cascades:
    # the hung process exits on its own watchdog (then process 0's collective fails:
    # PeerLostError) or on JAX's when process 0 (the coordinator) has left on its watchdog.
    watchdog_message = "no progress for 3 s while waiting for training step"
    assert any(f"error: process {i}/2: {watchdog_message}" in outs[i] for i in (0, 1)), outs
    assert watchdog_message in outs[0] or "PeerLostError: process 0/2: lost contact" in outs[0]
    assert "(restart hint)" in outs[0]


def test_a_work_directory_not_shared_by_all_processes_is_refused(kitti_object_root, env, tmp_path):
    # Each process gets its own folder, as on hosts without a shared filesystem.
    port = free_port()
    procs = []
    for i in range(2):
        args = tiny_args(kitti_object_root, tmp_path / f"host{i}")
        flags = ["--coordinator", f"localhost:{port}", "--num-processes", "2", "--process-id"]
        procs.append(
            subprocess.Popen(
                [sys.executable, str(REPO / "train.py"), *flags, str(i), *args],
                env=env,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                start_new_session=True,
            )
        )
    try:
        out = procs[1].communicate(timeout=120)[0]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
    assert procs[1].returncode == 2, out
    assert f"work directory {tmp_path / 'host1'} is not the one process 0 writes to" in out
    assert "must be on a filesystem shared by all hosts" in out


def test_two_depth_processes_train_like_one(env, tmp_path):
    from gac_jax.data.synthetic import generate_dataset

    # The tiny config's scenes, generated here once so both runs can start together.
    root = tmp_path / "data"
    generate_dataset(root, 16, 0, height=188, width=621, val_fraction=0.3, workers=1)
    steps = 6  # 5 per epoch: the second epoch's order and views are drawn anew

    def args(workdir: Path, *extra: str) -> list[str]:
        return [
            "--task",
            "depth",
            "--config",
            str(REPO / "configs" / "depth_default.py:tiny"),
            "--workdir",
            str(workdir),
            f"data.root={root}",
            "data.synthetic.val_fraction=0.3",
            "data.train_views=random",  # the RandomViewLoader's shards (the Loader's: above)
            f"train.num_steps={steps}",
            "train.eval_at_end=False",
            "train.keep_checkpoints=10",
            # As above, no gradient that jumps when float noise crosses a threshold: the
            # residual cut-off, |d log z| at the 0 of flat image regions, the GAC's sampling.
            "loss.residual_clip=0.0",
            "loss.smooth_weight=0.0",
            "model.use_gac=False",
            *extra,
        ]

    reference, workdir = tmp_path / "reference", tmp_path / "work"
    runs = [
        Run("depth_reference", args(reference, "train.checkpoint_every=1"), env, 1, tmp_path),
        Run(
            "depth_two",
            args(workdir, "train.eval_every=2", "train.eval_max_batches=1"),
            env,
            2,
            tmp_path,
        ),
    ]
    codes = [run.wait(300) for run in runs]
    assert codes == [[0], [0, 0]], "\n".join(run.tails() for run in runs)

    # Process 0 alone reports progress and evaluates (step 2) while process 1 waits.
    two = runs[1]
    assert "step 3/6" in two.log(0) and "step 3/6" not in two.log(1)
    evaluation = json.loads((workdir / "results" / "step_2" / "metrics.json").read_text())
    assert evaluation["num_scored"] == 2 and np.isfinite(evaluation["metrics"]["silog"])
    assert (workdir / "prior_mean.json").read_text() == (reference / "prior_mean.json").read_text()

    # The same updates on the same global batches: every logged loss, and the parameters.
    losses, expected = train_losses(workdir), train_losses(reference)
    assert sorted(losses) == sorted(expected) == list(range(1, steps + 1))
    np.testing.assert_allclose(
        [losses[s] for s in losses], [expected[s] for s in losses], rtol=1e-5
    )
    assert_params_close(workdir, reference, steps)


# Two processes that start the liveness beacon (polling the coordination service without a
# pause, to widen the window) and end normally. Before the beacon was stopped and joined at
# exit, about half of such pairs aborted in Python's finalization ("terminate called after
# throwing an instance of ''", exit -6): a daemon thread inside a C++ service call.
BEACON_WORKER = """
import sys
sys.path.insert(0, {repo!r})
from gac_jax.training import multiprocess
multiprocess.BEACON_S = 0.0
assert multiprocess.initialize_distributed("localhost:" + sys.argv[1], 2, int(sys.argv[2]))
from jax.experimental import multihost_utils
with multiprocess.watch_peers("for the test", poll_s=0.0):
    total = int(multihost_utils.process_allgather(multiprocess.jax.process_index()).sum())
print("gathered", total, flush=True)
"""


def test_processes_with_the_liveness_beacon_exit_cleanly(env, tmp_path):
    script = tmp_path / "beacon.py"
    script.write_text(BEACON_WORKER.format(repo=str(REPO)))
    for _ in range(4):
        port = str(free_port())
        procs, outs = run_pair(
            lambda i, port=port: [sys.executable, str(script), port, str(i)], env
        )
        assert [p.returncode for p in procs] == [0, 0], "\n---\n".join(outs)
        assert all("gathered 1" in out for out in outs), outs
