"""The guard command on a depth workdir (gac_jax.cli.guard -> gac_jax.cli.guard_depth).

A depth network trained 2 steps on the real KITTI-depth frame; the guard runs jax float32
and the candidates on 4 generated frames (both cameras): ONNX Runtime float32 is decided
*within* (the same maps up to the 1/256 m PNG step), OpenVINO int8 runs end to end; the
verdicts land in ``W/export/step2/guard.json``, and ``evaluate.py --task depth`` and
``DepthPredictor.precision_line()`` say what the guard decided (or "not guarded"). The guard
normally takes at least 100 frames; these tests lower that minimum to 4 for the run above,
and check that the real minimum refuses fewer frames (and ``--frames`` below it) with one
line before any model runs. Skipped without the deploy extra or NNCF.
"""

from __future__ import annotations

import json

import pytest

pytest.importorskip("onnx", reason="deploy extra (onnx) not installed")
pytest.importorskip("onnxruntime", reason="deploy extra (onnxruntime) not installed")
pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
pytest.importorskip("nncf", reason="deploy extra (nncf) not installed")

from gac_jax import DepthPredictor  # noqa: E402
from gac_jax.cli import evaluate as evaluate_cli  # noqa: E402
from gac_jax.cli import guard  # noqa: E402
from gac_jax.data.synthetic.writer import generate_dataset  # noqa: E402
from gac_jax.guard import (
    depth_rule,  # noqa: E402
    verdict_file,  # noqa: E402
)


@pytest.fixture(scope="module")
def depth_workdir(kitti_samples, tmp_path_factory):
    from gac_jax.trainers import depth
    from tests.test_train_depth import tiny_config

    workdir = tmp_path_factory.mktemp("guard_depth") / "wd"
    depth.train_and_evaluate(tiny_config(kitti_samples / "depth", "train.num_steps=2"), workdir)
    return workdir


def guard_argv(workdir, data) -> list[str]:
    argv = ["--workdir", str(workdir), "--guard-data", str(data)]
    return [*argv, "--candidates", "onnxruntime:f32,openvino:int8", "--int8-frames", "2"]


@pytest.fixture(scope="module")
def guarded(depth_workdir, tmp_path_factory):
    data = tmp_path_factory.mktemp("guard_depth_data") / "gen"
    generate_dataset(data, 8, seed=5, val_fraction=0.5, workers=1)  # 4 val frames
    report = depth_workdir.parent / "report.json"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(depth_rule, "MIN_FRAMES", 4)  # 4 generated frames
        assert guard.main([*guard_argv(depth_workdir, data), "--json", str(report)]) == 0
        again = guard.guard_workdir(
            guard.build_parser().parse_args(guard_argv(depth_workdir, data))
        )
    return depth_workdir, data, json.loads(report.read_text()), again


def test_depth_guard_decides_onnxruntime_within_and_resumes(guarded):
    wd, data, report, again = guarded
    stored = verdict_file.read_guard(wd / "export" / "step2")
    assert stored["model"]["weights"] == "step2" and stored["model"]["onnx_sha256"]
    assert "SILog" in stored["rule"]["text"] and stored["rule"]["margin_silog"] == 0.2
    ort = stored["verdicts"]["onnxruntime:f32"]
    assert ort["verdict"] == "within", ort["reason"]
    assert ort["frames"] == 4 and ort["images"] == 8
    assert abs(ort["criteria"]["silog"]["diff"]) < 0.01
    int8 = stored["verdicts"]["openvino:int8"]
    assert int8["verdict"] in ("within", "beyond", "undecided") and int8["frames"] == 4
    assert int8["int8"]["frames"] == 2
    rep = report["candidates"]["openvino:int8"]["decision"]["reported"]
    assert set(rep) >= {"silog", "abs_rel", "irmse", "rmse"}
    assert report["reference_ms"] > 0
    assert report["candidates"]["onnxruntime:f32"]["decision"]["look"] == 1
    assert ort["rule"]["min_frames"] == 4 and ort["drives"] >= 1
    assert ort["look"] == 2 and [look["frames"] for look in ort["looks"]] == [4, 4]  # the rerun
    # a rerun resumes the depth maps: nothing is predicted again; it is the second look
    assert again["reference_ms"] is None
    assert all(c["model_ms"] is None for c in again["candidates"].values())
    for key, c in again["candidates"].items():
        first = report["candidates"][key]["decision"]
        assert c["decision"]["look"] == 2 and c["decision"]["alpha_look"] == first["alpha"] / 4
        assert c["decision"]["criteria"]["silog"]["diff"] == first["criteria"]["silog"]["diff"]


def test_evaluate_and_the_api_print_the_depth_guards_verdict(guarded, capsys):
    wd = guarded[0]
    argv = ["--task", "depth", "--workdir", str(wd), "--runtime", "onnxruntime"]
    evaluate_cli.main([*argv, "--out", str(wd.parent / "ev_ort")])
    out = capsys.readouterr().out
    assert "precision: onnxruntime float32; guard: within on 4 frames" in out
    evaluate_cli.main(
        [
            "--task",
            "depth",
            "--workdir",
            str(wd),
            "--runtime",
            "openvino",
            "--out",
            str(wd.parent / "ev_ov"),
        ]
    )
    assert "precision: openvino float32; not guarded for these weights" in capsys.readouterr().out
    net = DepthPredictor.from_workdir(wd, runtime="onnxruntime")
    assert net.precision_line().startswith("precision: onnxruntime float32; guard: within on 4")


def test_fewer_frames_than_the_minimum_and_heading_are_refused(depth_workdir, capsys):
    argv = ["--workdir", str(depth_workdir), "--candidates", "onnxruntime:f32"]
    assert guard.main(argv) == 2  # the run's own data: the one real KITTI-depth frame
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "1 frames; the depth guard needs at least 100 frames" in err
    assert guard.main([*argv, "--frames", "50"]) == 2
    err = capsys.readouterr().err
    assert "--frames: the depth guard needs at least 100 frames, got 50" in err
    code = guard.main(["--workdir", str(depth_workdir), "--candidates", "openvino:int8+heading"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "applies to detectors only" in err
