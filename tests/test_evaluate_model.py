"""evaluate.py model mode end to end on a tiny trained workdir (the vendored real KITTI frames).

The trainer's own evaluation of the same checkpoint is the reference: the model mode
must write byte-identical result files and the same AP. Also: resume after a lost
result file, refusal to mix settings, converted weights with priors computed on the
fly, pictures (model mode and during training), CPU threads and one-line errors.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gac_jax.cli import evaluate as cli
from gac_jax.data.kitti import read_split
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.weights import pretrained
from tests.conftest import TINY_DETECT3D_OVERRIDES

REPO = Path(__file__).resolve().parents[1]
TINY = str(REPO / "configs" / "detect3d_default.py:tiny")


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def result_texts(folder: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(folder.glob("*.txt"))}


@pytest.fixture
def workdir_copy(tiny_detect3d_workdir, tmp_path) -> Path:
    dst = tmp_path / "wd"
    shutil.copytree(tiny_detect3d_workdir, dst, ignore=shutil.ignore_patterns("eval"))
    return dst


def test_model_mode_reproduces_the_trainer_evaluation(
    workdir_copy, kitti_object_root, tmp_path, capsys
):
    wd = workdir_copy
    n = len(read_split(kitti_object_root / "ImageSets" / "labeled.txt"))
    out_json = tmp_path / "ap.json"
    code, out, err = run(
        ["--task", "detect3d", "--workdir", wd, "--json", out_json, "--save-images", 3], capsys
    )
    assert code == 0, err
    trainer = wd / "results" / "step_2"
    mine = wd / "eval" / "labeled_step2"
    expected = result_texts(trainer / "data")
    assert len(expected) == n and sum(t.count("\n") for t in expected.values()) > n
    assert result_texts(mine / "data") == expected
    reference = json.loads((trainer / "metrics.json").read_text())["metrics"]
    written = json.loads(out_json.read_text())
    assert set(written.pop("_meta")["min_overlap"]) == set(reference["ap40"])
    assert written == reference  # the offline mode's schema and values
    for needle in ("KITTI AP|R40", "frames/s", "model", "post-processing", "I/O", "compile"):
        assert needle in out
    summary = json.loads((mine / "metrics.json").read_text())
    assert summary["predicted"] == n and summary["resumed"] == 0
    assert summary["speed"]["frames_per_s"] > 0 and summary["compile_s"] > 0
    assert summary["threads"] == len(os.sched_getaffinity(0))
    # Tiny config: top_k 20 and score threshold 0, so every frame overflows the cap, and says so.
    cap = summary["candidates"]
    assert cap["top_k"] == cap["kept_per_frame"] == 20 and cap["frames"] == n
    assert cap["frames_over_cap"] == n and cap["max_candidates"] > 20
    assert f"{n} of {n} frames had more anchors above the score threshold" in out
    names = sorted(p.name for p in (mine / "pictures").glob("*.png"))
    assert names == ["000000.png", "000001.png", "000010.png", "grid.png"]
    # Pictures written by the trainer at its evaluation (config.eval.num_pictures = 2).
    names = sorted(p.name for p in (trainer / "pictures").glob("*.png"))
    assert names == ["000000.png", "000001.png", "grid.png"]


def test_resume_redoes_only_the_missing_frame(workdir_copy, kitti_object_root, capsys):
    wd = workdir_copy
    n = len(read_split(kitti_object_root / "ImageSets" / "labeled.txt"))
    argv = ["--task", "detect3d", "--workdir", wd]
    assert run(argv, capsys)[0] == 0
    data = wd / "eval" / "labeled_step2" / "data"
    before = {p.name: p.stat().st_mtime_ns for p in data.glob("*.txt")}
    lost = data / "000036.txt"
    text = lost.read_text()
    lost.unlink()
    # Second run in a fresh process with one CPU thread (the --threads plumbing).
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run(
        [sys.executable, str(REPO / "evaluate.py"), *map(str, argv), "--threads", "1"],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"{n} frames ({n - 1} already done)" in proc.stdout
    assert "speed (1 CPU threads)" in proc.stdout
    summary = json.loads((data.parent / "metrics.json").read_text())
    assert summary["predicted"] == 1 and summary["resumed"] == n - 1
    assert summary["threads"] == 1  # XLA compute threads counted in that process
    assert lost.read_text() == text
    after = {p.name: p.stat().st_mtime_ns for p in data.glob("*.txt")}
    changed = sorted(n for n in after if after[n] != before.get(n))
    assert changed == ["000036.txt"]
    # Other settings than the ones the folder was made with: refused, nothing overwritten.
    code, _, err = run([*argv, "eval.score_threshold=0.5"], capsys)
    assert code == 2 and "run.json" in err and "eval differ" in err
    assert {p.name: p.stat().st_mtime_ns for p in data.glob("*.txt")} == after
    # A moved workdir still resumes (its own checkpoints are identified by step).
    moved = wd.parent / "moved"
    shutil.move(wd, moved)
    code, out, err = run(["--task", "detect3d", "--workdir", moved], capsys)
    assert code == 0 and f"{n} frames ({n} already done)" in out, err


def test_converted_weights_with_priors_computed_on_the_fly(
    tiny_detect3d_workdir, kitti_object_root, tmp_path, capsys
):
    with Checkpoints(tiny_detect3d_workdir) as ckpts:
        variables = ckpts.restore_variables()
    weights = tmp_path / "weights"
    pretrained.save_converted(weights, variables, {"kind": "gac_detector", "model": {}})
    wd = tmp_path / "fresh"
    overrides = [*TINY_DETECT3D_OVERRIDES, f"data.root={kitti_object_root}"]
    argv = ["--task", "detect3d", "--workdir", wd, "--checkpoint", weights, "--config", TINY]
    code, out, err = run([*argv, *overrides], capsys)
    assert code == 0, err
    assert "computing anchor priors" in out
    got = result_texts(wd / "eval" / "labeled_weights" / "data")
    assert got == result_texts(tiny_detect3d_workdir / "results" / "step_2" / "data")
    a = np.load(wd / "anchor_priors.npz")
    b = np.load(tiny_detect3d_workdir / "anchor_priors.npz")
    np.testing.assert_array_equal(a["mean"], b["mean"])


def test_errors_name_the_file_and_the_remedy(tiny_detect3d_workdir, tmp_path, capsys):
    src = tiny_detect3d_workdir

    def error(argv, *needles):
        code, _, err = run(["--task", "detect3d", *argv], capsys)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
        for needle in needles:
            assert needle in lines[0], (needle, lines[0])

    error(["--workdir", tmp_path / "missing"], "missing", "workdir not found")
    bare = tmp_path / "bare"
    bare.mkdir()
    error(["--workdir", bare], "config.json", "python train.py")
    shutil.copy(src / "config.json", bare)
    error(["--workdir", bare], "anchor_priors.npz", "python train.py", "--checkpoint")
    shutil.copy(src / "anchor_priors.npz", bare)
    error(["--workdir", bare], "checkpoints", "train first")
    shutil.copytree(src / "checkpoints", bare / "checkpoints")
    error(["--workdir", bare, "--step", 99], "no checkpoint step 99 (have [2])")
    error(["--workdir", bare, "model.cls_features=24"], "does not fit the model", "head")
    error(["--workdir", bare, "model.nope=1"], "unknown config key")
    error(["--workdir", bare, "--checkpoint", tmp_path / "none"], "no converted weights")
    for argv in (
        ["--workdir", bare, "--checkpoint", "x", "--step", 1],
        ["--workdir", bare, "--threads", 0],
        ["--label-dir", bare, "--result-dir", bare, "--step", 1],  # offline mode
    ):
        with pytest.raises(SystemExit) as exit_info:
            cli.main(["--task", "detect3d", *map(str, argv)])
        assert exit_info.value.code == 2
    assert "only apply with --workdir" in capsys.readouterr().err
