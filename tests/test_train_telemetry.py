"""What the trainer tells about its step: the device's wait for data (share and warning), the
compile and memory lines, a profile of chosen steps, and out-of-memory as one line.

The ``:tiny`` detector config on the vendored real KITTI frames (2 steps of 2 frames).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import pytest
from test_train_detect3d import tiny_overrides  # tests/ is on sys.path under pytest

import train
from gac_jax.config import apply_overrides, load_config
from gac_jax.data.loader import Loader
from gac_jax.trainers import detect3d
from gac_jax.training import step_runner
from gac_jax.training.metrics_writer import Progress

REPO = Path(__file__).resolve().parents[1]


def overrides(root: Path) -> list[str]:
    return [*tiny_overrides(root), "train.eval_at_end=False", "train.log_every=1"]


def tiny_config(root: Path, *extra: str):
    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    apply_overrides(config, overrides(root) + list(extra))
    return config


def records(workdir: Path, kind: str) -> list[dict]:
    lines = (workdir / "metrics.jsonl").read_text().splitlines()
    return [r for r in map(json.loads, lines) if r["kind"] == kind]


class SlowSource:
    """A source that takes ``delay`` seconds per frame (a slow disk or decoder)."""

    def __init__(self, source, delay: float):
        self.source, self.delay = source, delay

    def __len__(self):
        return len(self.source)

    def __getitem__(self, i):
        time.sleep(self.delay)
        return self.source[i]


def test_slow_source_shows_a_high_data_wait_and_warns(
    kitti_object_root, tmp_path, monkeypatch, capsys
):
    """Each batch takes ~1 s to load and the tiny step far less: the device waits most of
    the second step's window; the warning names data.num_workers. The compile and memory
    lines are printed and the memory is in metrics.jsonl."""
    opener = detect3d.open_object_source
    monkeypatch.setattr(
        detect3d, "open_object_source", lambda *a, **k: SlowSource(opener(*a, **k), 0.5)
    )
    detect3d.train_and_evaluate(tiny_config(kitti_object_root), tmp_path)
    out, err = capsys.readouterr()
    steps = {r["step"]: r for r in records(tmp_path, "train")}
    assert steps[2]["data_wait"] > 0.5, steps[2]["data_wait"]
    assert "| data " in out
    warnings = [line for line in err.splitlines() if line.startswith("warning: steps 2-2")]
    assert len(warnings) == 1 and "data.num_workers (now 0)" in warnings[0], err
    assert "compiling the train step ... " in out
    memory_lines = [line for line in out.splitlines() if "train step memory per device:" in line]
    assert len(memory_lines) == 1 and "host RAM" in memory_lines[0], out
    (compile_record,) = records(tmp_path, "compile")
    memory = compile_record["memory_bytes"]
    assert memory["total"] == (
        memory["arguments"]
        + memory["outputs"]
        - memory["aliased"]
        + memory["temporaries"]
        + memory["code"]
    )
    assert memory["arguments"] > 4 * 2 * 64 * 256 * 3  # at least the batch of images
    assert compile_record["compile_s"] > 0


def test_prefilled_loader_shows_no_data_wait_and_profiles_two_steps(
    kitti_object_root, tmp_path, monkeypatch, capsys
):
    """Batches loaded before the loop: the device never waits for data (no warning);
    ``train.profile_steps=(1, 2)`` writes a trace in the TensorBoard profile layout."""

    class Prefilled(Loader):
        def iterate(self, start_step=0, num_steps=None):
            return iter([self.load_batch(s) for s in range(start_step, start_step + num_steps)])

    monkeypatch.setattr(detect3d, "Loader", Prefilled)
    config = tiny_config(kitti_object_root, "train.profile_steps=(1, 2)")
    detect3d.train_and_evaluate(config, tmp_path)
    out, err = capsys.readouterr()
    steps = {r["step"]: r for r in records(tmp_path, "train")}
    assert steps[2]["data_wait"] < 0.05, steps[2]["data_wait"]
    assert "warning: steps" not in err
    traces = list((tmp_path / "tensorboard" / "plugins" / "profile").glob("*/*.xplane.pb"))
    assert len(traces) == 1 and traces[0].stat().st_size > 0, traces
    assert "profile of steps 1-2 in" in out


def test_out_of_device_memory_is_one_line_naming_the_batch_size(
    kitti_object_root, tmp_path, monkeypatch, capsys
):
    """XLA's RESOURCE_EXHAUSTED from the step: one line naming data.batch_size and the need,
    exit 1; XLA's text and the traceback go to WORKDIR/details.log."""
    real_compile = step_runner.compile_step
    xla_text = "RESOURCE_EXHAUSTED: Out of memory while trying to allocate 12884901888 bytes."

    def compile_exhausted(*args, **kwargs):
        compiled, seconds = real_compile(*args, **kwargs)

        class Exhausted:
            memory_analysis = compiled.memory_analysis

            def __call__(self, *a):
                raise jax.errors.JaxRuntimeError(xla_text)

        return Exhausted(), seconds

    monkeypatch.setattr(step_runner, "compile_step", compile_exhausted)
    workdir = tmp_path / "run"
    args = ["--task", "detect3d", "--config", "configs/detect3d_default.py:tiny"]
    code = train._run(
        train.parse_args([*args, "--workdir", str(workdir), *overrides(kitti_object_root)])
    )
    err = capsys.readouterr().err
    assert code == 1
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("error: out of device memory: the train step at data.batch_size=2")
    assert "needs " in lines[0] and "per device" in lines[0] and "lower data.batch_size" in lines[0]
    assert "details.log" in lines[0]
    details = (workdir / "details.log").read_text()
    assert "Traceback" in details and xla_text in details


def test_progress_reports_the_data_wait_share_and_warns_above_a_fifth(capsys):
    progress = Progress(100, 0, batch_size=8, num_workers=3)
    progress.restart(0)
    time.sleep(0.2)
    stats = progress.update(10, 1.0, data_wait_s=0.15)
    out, err = capsys.readouterr()
    assert 0.5 < stats["data_wait"] <= 0.75 + 1e-9
    assert "| data " in out
    assert "warning: steps 1-10 waited for data" in err and "data.num_workers (now 3)" in err
    time.sleep(0.2)
    stats = progress.update(20, 1.0, data_wait_s=0.001)
    out, err = capsys.readouterr()
    assert stats["data_wait"] < 0.05 and err == ""
    # Still input-bound: the share is on every progress line, the warning every 10 windows.
    warned = []
    for window in range(3, 24):
        progress.restart(window * 10 - 10)
        progress.update(window * 10, 1.0, data_wait_s=1.0)
        warned += [window] if "warning:" in capsys.readouterr().err else []
    assert warned == [11, 21]  # 10 windows after the first warning (window 1), and so on


@pytest.mark.parametrize("value", ["(0, 2)", "(3,)", "'x'"])
def test_profile_steps_must_be_a_start_and_count(value, kitti_object_root, tmp_path, capsys):
    args = ["--task", "detect3d", "--config", "configs/detect3d_default.py:tiny"]
    extra = [f"train.profile_steps={value}"]
    code = train._run(
        train.parse_args([*args, "--workdir", str(tmp_path), *overrides(kitti_object_root), *extra])
    )
    assert code == 2
    assert "error: train.profile_steps:" in capsys.readouterr().err
