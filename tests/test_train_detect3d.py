"""The detection trainer: compile-once step, multi-device equivalence, kill/resume, NaN stop.

Runs the ``:tiny`` default config (ResNet-18 of width 8, 64x256 input) on the
real KITTI frames vendored in ``tests/data/kitti``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from gac_jax.config import apply_overrides, load_config
from gac_jax.trainers import detect3d
from gac_jax.training.checkpointing import Checkpoints

REPO = Path(__file__).resolve().parents[1]


def tiny_overrides(root: Path) -> list[str]:
    return [
        "data.source=kitti",
        f"data.root={root}",
        "data.train_split=labeled",
        "data.val_split=labeled",
        "data.use_right_image=False",
    ]


@pytest.fixture
def tiny_config(kitti_object_root):
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(config, tiny_overrides(kitti_object_root))
    return config


def restore_params(workdir: Path, step: int | None = None) -> dict:
    with Checkpoints(workdir) as ckpts:
        step = ckpts.latest_step() if step is None else step
        raw = ckpts._manager.restore(step)  # noqa: SLF001 - raw restore without a template
    return jax.tree.map(np.asarray, dict(raw["state"])["params"])


def test_default_tiny_run_generates_data_trains_and_evaluates(tmp_path, monkeypatch):
    """``train.py --task detect3d --config ...:tiny`` end to end on the embedded generator."""
    monkeypatch.setenv("GAC_JAX_CACHE", str(tmp_path / "cache"))
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(config, ["train.num_steps=3", "eval.score_threshold=0.0"])
    workdir = tmp_path / "run"
    out = detect3d.train_and_evaluate(config, workdir)
    data_root = tmp_path / "cache" / "synthetic_n16_s0_188x621_val0.3_v3"
    assert (data_root / "synthetic.json").exists()
    num_val = len((data_root / "ImageSets" / "val.txt").read_text().split())
    assert set(out["metrics"]) == {"ap11", "ap40"}
    assert set(out["metrics"]["ap40"]["Car"]) == {"0.70", "0.50"}
    assert out["num_frames"] == num_val > 0
    result_files = sorted((workdir / "results" / "step_3" / "data").glob("*.txt"))
    assert len(result_files) == num_val
    lines = (workdir / "metrics.jsonl").read_text().splitlines()
    assert any('"kind": "eval"' in line for line in lines)
    assert (workdir / "config.json").exists() and (workdir / "anchor_priors.npz").exists()
    with Checkpoints(workdir) as ckpts:
        assert ckpts.latest_step() == 3


def test_train_step_compiles_once_and_two_devices_match_one(kitti_object_root, tmp_path):
    """A 2-device step (fake CPU devices) equals the 1-device step on the same global batch."""
    script = textwrap.dedent(
        f"""
        import os, sys
        # the session's fast-compile flags (tests/conftest.py) stay, two CPU devices are added
        os.environ["XLA_FLAGS"] += " --xla_force_host_platform_device_count=2"
        import jax, numpy as np
        sys.path.insert(0, {str(REPO)!r})
        from gac_jax.training import parallel
        from gac_jax.config import apply_overrides, load_config
        from gac_jax.trainers import detect3d as D
        from gac_jax.builders import detect3d as B
        import optax
        from gac_jax.training.train_state import TrainState
        from gac_jax.detection.anchor_priors import (
            load_or_compute_priors,
            make_detection_constants,
        )
        from gac_jax.detection.anchors import generate_anchors
        from gac_jax.data.loader import DetectionArrays, Loader
        from gac_jax.data.sources import open_object_source
        from pathlib import Path

        assert len(jax.devices()) == 2
        c = load_config({str(REPO / "configs" / "detect3d_default.py:tiny")!r})
        apply_overrides(c, {tiny_overrides(kitti_object_root)!r} + ["data.batch_size=4"])
        layout = B.anchor_layout(c)
        priors = B.compute_priors(c, Path(c.data.root), layout, Path({str(tmp_path)!r}))
        constants = make_detection_constants(generate_anchors(layout), priors)
        model = B.build_model(c, layout.anchors_per_cell)
        # SGD: the update is linear in the gradient, so parameters compare tightly (Adam's
        # m / sqrt(v) turns float-noise gradients of unused weights into full-size steps).
        tx = optax.sgd(1e-2)
        source = open_object_source(c.data.root, "labeled")
        loader = Loader(source, B.train_transform(c), DetectionArrays(("Car",), 32, True),
                        batch_size=4, seed=0)
        batches = [loader.load_batch(s) for s in range(2)]
        # the second batch's frames have pitched planes: an input, not a retrace
        batches[1]["plane"][:] = np.float32([0.0, -0.99, -0.141, 1.6])  # unit normal, 8 deg
        v = jax.tree.map(np.asarray, B.init_variables(model, c, 0))  # host copy: steps donate
        results = []
        for devices in (jax.devices()[:1], jax.devices()):
            mesh = parallel.make_mesh(devices)
            rep = parallel.replicated(mesh)
            state = jax.device_put(TrainState.create(v["params"], v["batch_stats"], tx, 0), rep)
            shard = jax.tree.map(lambda _: rep, state)
            step = D.make_train_step(model, tx, constants, B.loss_config(c), c, mesh, shard)
            losses = []
            for b in batches:
                state, m = step(state, parallel.to_global(b, mesh))
                losses.append((float(m["loss"]), float(m["grad_norm"])))
            assert step._cache_size() == 1, step._cache_size()
            params = jax.tree.map(lambda x: np.asarray(x.addressable_data(0)), state.params)
            results.append((losses, params))
        (l1, p1), (l2, p2) = results
        print("losses", l1, l2)
        np.testing.assert_allclose(l1, l2, rtol=2e-5, atol=1e-6)
        diffs = jax.tree.leaves(jax.tree.map(lambda a, b: float(np.max(np.abs(a - b))), p1, p2))
        scale = max(float(np.max(np.abs(a))) for a in jax.tree.leaves(p1))
        print("max param diff", max(diffs), "scale", scale)
        assert max(diffs) < 1e-5 * max(scale, 1.0)
        assert l1[0][0] > 0
        print("OK")
        """
    )
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "OK" in proc.stdout


def _train_cmd(workdir: Path, root: Path, steps: int) -> list[str]:
    return [
        sys.executable,
        str(REPO / "train.py"),
        "--task",
        "detect3d",
        "--config",
        str(REPO / "configs" / "detect3d_default.py:tiny"),
        "--workdir",
        str(workdir),
        *tiny_overrides(root),
        f"train.num_steps={steps}",
        "train.checkpoint_every=2",
        "train.log_every=2",
        "train.eval_at_end=False",
    ]


def test_killed_and_stopped_run_resumes_to_the_same_parameters(kitti_object_root, tmp_path):
    steps = 12
    env = dict(os.environ, PYTHONPATH=str(REPO))
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    proc = subprocess.Popen(
        _train_cmd(killed, kitti_object_root, steps),
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    deadline = time.time() + 300
    while not (killed / "checkpoints" / "4").exists():
        assert proc.poll() is None, proc.stdout.read().decode()[-3000:]
        assert time.time() < deadline, "no checkpoint at step 4 within 300 s"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    with Checkpoints(killed) as ckpts:
        interrupted_at = ckpts.latest_step()
    assert interrupted_at < steps, "the run finished before it could be killed"

    # Resumed, then stopped by SIGTERM (with loader workers): a checkpoint where it stopped,
    # one line, exit 75.
    stopped = subprocess.Popen(
        [*_train_cmd(killed, kitti_object_root, steps), "data.num_workers=2"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    metrics = killed / "metrics.jsonl"
    deadline = time.time() + 300
    while f'"step": {interrupted_at + 1}, ' not in metrics.read_text():
        assert stopped.poll() is None, stopped.stdout.read().decode()[-3000:]
        assert time.time() < deadline, "no step after the resume within 300 s"
        time.sleep(0.05)
    stopped.send_signal(signal.SIGTERM)
    out = stopped.communicate(timeout=120)[0].decode()
    assert stopped.returncode == 75, out[-3000:]
    assert f"resumed from {killed / 'checkpoints'} at step {interrupted_at}" in out
    with Checkpoints(killed) as ckpts:
        at = ckpts.latest_step()
    assert interrupted_at < at < steps, out[-3000:]
    lines = [line for line in out.splitlines() if line.startswith("stopped at")]
    assert lines == [f"stopped at step {at}, checkpoint saved; run the same command to resume"]
    assert "SIGTERM received" in out and "Traceback" not in out

    resumed = subprocess.run(
        _train_cmd(killed, kitti_object_root, steps), env=env, capture_output=True, text=True
    )
    assert resumed.returncode == 0, resumed.stdout[-2000:] + resumed.stderr[-2000:]
    assert f"resumed from {killed / 'checkpoints'} at step {at}" in resumed.stdout
    # The uninterrupted run, in this process (same code path as train.py).
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(config, _train_cmd(clean, kitti_object_root, steps)[8:])
    detect3d.train_and_evaluate(config, clean)

    a, b = restore_params(killed, steps), restore_params(clean, steps)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(x, y)  # bit for bit, despite the kill and the stop
    # The metrics file tells one history: every logged step once.
    logged = [
        line for line in (killed / "metrics.jsonl").read_text().splitlines() if '"train"' in line
    ]
    assert len(logged) == steps // 2


def test_nonfinite_loss_stops_and_keeps_last_good_checkpoint(tiny_config, tmp_path, monkeypatch):
    apply_overrides(
        tiny_config,
        ["train.num_steps=8", "train.checkpoint_every=2", "train.log_every=1"],
    )
    calls = {"n": 0}
    original = detect3d.parallel.to_global

    def poisoned(batch, mesh):
        calls["n"] += 1
        if calls["n"] == 5:  # the 5th step sees a corrupt image
            batch = dict(batch, image=np.full_like(batch["image"], np.nan))
        return original(batch, mesh)

    monkeypatch.setattr(detect3d.parallel, "to_global", poisoned)
    with pytest.raises(detect3d.NonFiniteLossError, match="non-finite loss at step 5"):
        detect3d.train_and_evaluate(tiny_config, tmp_path)
    with Checkpoints(tmp_path) as ckpts:
        assert ckpts.latest_step() == 4
    params = restore_params(tmp_path)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(params))
