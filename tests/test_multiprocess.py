"""The multiprocess and parallel modules in one process: start-up, shards, watchdog.

The multi-process behaviour itself is tested with real processes in test_multihost.py.
"""

from __future__ import annotations

import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.training import multiprocess, parallel, step_watchdog, stopping


@pytest.fixture(autouse=True)
def clean(monkeypatch):
    for names in multiprocess._ENV.values():  # noqa: SLF001 - the variables the module reads
        for name in names:
            monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(multiprocess, "settings", multiprocess.DistributedSettings())


def test_without_flags_or_variables_nothing_starts():
    assert multiprocess.initialize_distributed() is False
    assert (
        multiprocess.initialize_distributed(num_processes=1, coordinator="h:1", process_id=0)
        is False
    )
    assert jax.process_count() == 1


def test_incomplete_or_bad_arguments_are_refused(monkeypatch):
    with pytest.raises(ValueError, match="--coordinator, --num-processes and --process-id"):
        multiprocess.initialize_distributed(coordinator="host:1234")
    monkeypatch.setenv("GAC_NUM_PROCESSES", "2")
    with pytest.raises(ValueError, match="coordinator=None"):
        multiprocess.initialize_distributed()
    monkeypatch.setenv("GAC_NUM_PROCESSES", "two")
    with pytest.raises(ValueError, match="GAC_NUM_PROCESSES/JAX_NUM_PROCESSES must be a number"):
        multiprocess.initialize_distributed()
    monkeypatch.delenv("GAC_NUM_PROCESSES")
    with pytest.raises(ValueError, match="step_timeout must be positive"):
        multiprocess.initialize_distributed(step_timeout=0)


def test_timeouts_come_from_arguments_or_environment(monkeypatch):
    monkeypatch.setenv("GAC_STEP_TIMEOUT", "12.5")
    monkeypatch.setenv("GAC_WAIT_TIMEOUT", "60")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "1")  # the launcher's variables, one process
    monkeypatch.setenv("JAX_PROCESS_ID", "0")
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "localhost:1")
    assert multiprocess.initialize_distributed(heartbeat_timeout=7) is False
    assert multiprocess.settings == multiprocess.DistributedSettings(
        step_timeout=12.5, wait_timeout=60.0, heartbeat_timeout=7
    )


def test_single_process_shard_and_coordination_are_trivial(tmp_path):
    mesh = parallel.make_mesh()
    assert parallel.process_shard(mesh) == (0, 1)
    assert parallel.check_batch_size(4, mesh) == 4
    order = []
    with multiprocess.main_process_first("x"):
        order.append("body")
    multiprocess.barrier("y", timeout_s=0.001)
    multiprocess.check_shared_directory(tmp_path)
    assert multiprocess.run_on_main(lambda: 42, "z") == 42
    assert order == ["body"]
    assert stopping.preemption_requested(3) is False
    assert multiprocess.is_peer_failure(ValueError("Gloo all-reduce failed")) is False
    multiprocess.raise_if_peer_failure(ValueError("Gloo all-reduce failed"))  # no-op here


def test_to_global_shards_numeric_arrays_and_drops_strings():
    mesh = parallel.make_mesh()
    batch = {"image": np.ones((2, 3), np.float32), "frame_id": np.array(["a", "b"])}
    out = parallel.to_global(batch, mesh)
    assert set(out) == {"image"}
    assert out["image"].sharding == parallel.data_sharded(mesh)
    np.testing.assert_array_equal(parallel.to_host(out)["image"], batch["image"])


class Recorder:
    def __init__(self):
        self.messages = []
        self.fired = threading.Event()

    def __call__(self, message):
        self.messages.append(message)
        self.fired.set()


def test_watchdog_fires_only_when_steps_stop():
    rec = Recorder()
    with step_watchdog.ProgressWatchdog(
        timeout_s=0.4, hint="(hint)", enabled=True, on_timeout=rec, poll_s=0.02
    ) as dog:
        for step in range(1, 9):  # 0.8 s of steady progress, longer than the timeout
            dog.step(step, jnp.zeros(()))
            time.sleep(0.1)
        assert not rec.fired.is_set()
        t0 = time.monotonic()
        assert rec.fired.wait(2.0)
        assert 0.25 < time.monotonic() - t0 < 1.0
    (message,) = rec.messages
    assert "no progress for 0.4 s while waiting for training step 8 to finish" in message
    assert message.endswith("(hint)")


def test_watchdog_pauses_and_restarts_its_clock():
    rec = Recorder()
    with step_watchdog.ProgressWatchdog(
        timeout_s=0.3, enabled=True, on_timeout=rec, poll_s=0.02
    ) as dog:
        dog.step(1, jnp.zeros(()))
        with dog.paused():
            time.sleep(0.6)  # e.g. waiting for process 0's evaluation
        assert not rec.fired.is_set()
        assert rec.fired.wait(2.0)
    assert "the next training step" in rec.messages[0]


def test_watchdog_is_off_in_a_single_process_run():
    dog = step_watchdog.ProgressWatchdog(timeout_s=0.01)
    assert not dog.enabled and dog._thread is None  # noqa: SLF001
    dog.step(1, jnp.zeros(()))
    with dog.paused():
        pass
    dog.close()
