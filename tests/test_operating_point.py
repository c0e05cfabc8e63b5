"""The operating point (gac_jax/evaluation/operating_point.py) on hand-made labels, and the
deployed threshold bound to the weights (gac_jax/trained/operating_point.py) on a trained
tiny run: recorded by the trainer's evaluation, used by the API, refused for other weights."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from label_cases import label_line, objects

from gac_jax.evaluation.operating_point import (
    best_threshold,
    check_beta,
    describe,
    f_beta,
    frame_counts,
    operating_point,
    threshold_grid,
    threshold_sweep,
)

GT = objects(
    [
        label_line("Car", (100, 100, 200, 160)),
        label_line("Car", (400, 100, 440, 120)),  # 20 px tall: not counted as a car to find
        label_line("Van", (600, 100, 700, 180)),
        label_line("DontCare", (800, 100, 900, 150)),
        label_line("Pedestrian", (300, 100, 330, 180)),
        label_line("Person_sitting", (1000, 200, 1030, 260)),
    ],
    False,
)


def test_false_positives_excuse_neighbours_and_dontcare_and_take_each_object_once():
    dt = objects(
        [
            label_line("Car", (100, 100, 200, 160), score=0.9),  # the car
            label_line("Car", (102, 100, 202, 160), score=0.8),  # the same car again: false
            label_line("Car", (600, 100, 700, 180), score=0.7),  # on the Van: excused
            label_line("Car", (810, 110, 860, 140), score=0.7),  # inside DontCare: excused
            label_line("Car", (1000, 100, 1050, 140), score=0.6),  # nothing there: false
            label_line("Car", (300, 100, 350, 140), score=0.3),  # below the threshold
            label_line("Pedestrian", (1000, 200, 1030, 260), score=0.9),  # Person_sitting: excused
            label_line("Pedestrian", (600, 100, 700, 180), score=0.9),  # a Van is no excuse: false
        ],
        True,
    )
    assert frame_counts(GT, dt, 0.5) == (5, 2, 1, 1)
    assert frame_counts(GT, dt, 0.85) == (1, 0, 1, 1)
    assert frame_counts(GT, dt, 0.5, "Pedestrian") == (2, 1, 0, 0)


def test_threshold_sweep_and_best_f1_by_hand():
    dt = objects(
        [
            label_line("Car", (100, 100, 200, 160), score=0.9),  # the car (the one >= 25 px tall)
            label_line("Car", (1000, 100, 1050, 140), score=0.7),  # nothing there: false
            label_line("Car", (1100, 100, 1150, 140), score=0.55),  # nothing there: false
        ],
        True,
    )
    empty = objects([], True)
    sweep = threshold_sweep([GT, GT], [dt, empty], (0.5, 0.6, 0.8, 0.95))
    # two frames: 3 detections of which 2 false at 0.5; one of the two tall cars found
    assert sweep[0.5]["detections"] == 1.5 and sweep[0.5]["false_positives"] == 1.0
    assert sweep[0.5]["precision"] == pytest.approx(1 / 3)
    assert sweep[0.5]["recall"] == pytest.approx(0.5)
    assert sweep[0.5]["f1"] == pytest.approx(2 * (1 / 3) * 0.5 / (1 / 3 + 0.5))
    assert sweep[0.6]["precision"] == pytest.approx(0.5) and sweep[0.6]["found"] == 1
    assert sweep[0.8] == {
        "detections": 0.5,
        "false_positives": 0.0,
        "found": 1,
        "precision": 1.0,
        "recall": 0.5,
        "f1": pytest.approx(2 / 3),
    }
    assert sweep[0.95]["f1"] == 0.0 and sweep[0.95]["found"] == 0
    assert best_threshold(sweep) == 0.8
    # a tie goes to the lowest threshold
    tie = {"precision": 0.5, "recall": 0.5}
    assert best_threshold({0.7: tie, 0.6: tie}) == 0.6
    # pooled over classes: the pedestrian (80 px tall) counts as one more object to find
    pooled = threshold_sweep([GT], [dt], (0.8,), ("Car", "Pedestrian"))[0.8]
    assert pooled["recall"] == pytest.approx(0.5) and pooled["found"] == 1


def test_f_beta_by_hand_and_a_lower_beta_deploys_a_higher_threshold():
    assert f_beta(0.6, 0.9) == pytest.approx(2 * 0.54 / 1.5)
    assert f_beta(0.6, 0.9, 0.5) == pytest.approx(1.25 * 0.54 / (0.25 * 0.6 + 0.9))
    assert f_beta(0.95, 0.55, 2.0) == pytest.approx(5 * 0.95 * 0.55 / (4 * 0.95 + 0.55))
    assert f_beta(1.0, 1.0, 0.5) == 1.0 and f_beta(0.0, 0.0, 0.5) == 0.0
    # F1 0.720 at 0.5 against 0.697 at 0.8; F0.5 0.643 against 0.829: precision weighs more
    sweep = {
        "0.50": {"precision": 0.6, "recall": 0.9},
        "0.80": {"precision": 0.95, "recall": 0.55},
    }
    assert best_threshold(sweep) == "0.50" and best_threshold(sweep, 0.5) == "0.80"
    for bad in (0, -1, "x", None, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="eval.operating_point_beta must be a number > 0"):
            check_beta(bad)
    assert check_beta("0.5") == 0.5


def test_operating_point_records_its_beta_and_says_it():
    dt = objects(
        [
            label_line("Car", (100, 100, 200, 160), score=0.9),  # the tall car
            label_line("Car", (400, 100, 440, 120), score=0.7),  # the 20 px car: true, no recall
            label_line("Car", (1000, 100, 1050, 140), score=0.6),  # false
            label_line("Car", (1100, 100, 1150, 140), score=0.55),  # false
        ],
        True,
    )
    # one tall car: recall 1 from 0.5 to 0.9; precision 2/4, 2/3, 1, 1 at 0.5, 0.6, 0.65, 0.75
    f1 = operating_point([GT], [dt], ("Car",), 0.5)
    assert f1["threshold"] == 0.65 and f1["beta"] == 1.0 and "best F1 " in f1["rule"]
    half = operating_point([GT], [dt], ("Car",), 0.5, beta=0.5)
    assert half["threshold"] == 0.65 and half["beta"] == 0.5 and "best F0.5 " in half["rule"]
    assert "(best F0.5 1.00: precision 1.00, recall 1.00" in describe(half)
    assert "(best F1 1.00:" in describe({k: v for k, v in f1.items() if k != "beta"})
    with pytest.raises(ValueError, match="operating_point_beta"):
        operating_point([GT], [dt], ("Car",), 0.5, beta=0)


def test_a_bad_operating_point_beta_is_one_line_before_any_work(tmp_path, capsys):
    import train

    workdir = tmp_path / "run"
    args = ["--task", "detect3d", "--config", "configs/detect3d_default.py:tiny"]
    code = train._run(
        train.parse_args([*args, "--workdir", str(workdir), "eval.operating_point_beta=0"])
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err == ["error: eval.operating_point_beta must be a number > 0, got 0.0"]
    assert not (workdir / "config.json").exists() and not (workdir / "checkpoints").exists()


def test_threshold_grid_starts_at_the_evaluation_threshold():
    assert threshold_grid(0.5) == [0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95]
    assert threshold_grid(0.75) == [0.75, 0.8, 0.85, 0.9, 0.95]
    assert threshold_grid(0.52) == [0.52, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9, 0.95]
    assert threshold_grid(0.0)[:3] == [0.0, 0.05, 0.1] and len(threshold_grid(0.0)) == 20
    assert threshold_grid(0.97) == [0.97]


def test_operating_point_record_and_none_when_nothing_is_found():
    dt = objects(
        [
            label_line("Car", (100, 100, 200, 160), score=0.9),
            label_line("Car", (1000, 100, 1050, 140), score=0.6),
        ],
        True,
    )
    record = operating_point([GT], [dt], ("Car",), 0.5)
    assert record["threshold"] == 0.65  # the false box (0.6) dropped, the car kept
    assert record["frames"] == 1 and record["objects"] == 1 and record["classes"] == ["Car"]
    assert record["sweep"]["0.65"]["f1"] == 1.0 and record["sweep"]["0.50"]["f1"] < 1.0
    json.dumps(record)  # written as it is
    miss = objects([label_line("Car", (1000, 100, 1050, 140), score=0.9)], True)
    assert operating_point([GT], [miss], ("Car",), 0.5)["threshold"] is None


def _deployable_copy(workdir: Path, tmp_path: Path, mode: str = "operating_point") -> Path:
    copy = tmp_path / "run"
    shutil.copytree(workdir, copy)
    config = json.loads((copy / "config.json").read_text())
    config["eval"]["deploy_threshold"] = mode
    (copy / "config.json").write_text(json.dumps(config))
    return copy


def _set_threshold(path: Path, threshold: float, sha: str | None = None) -> None:
    record = json.loads(path.read_text())
    record["threshold"] = threshold
    if sha is not None:
        record["weights_sha256"] = sha
    path.write_text(json.dumps(record))


def test_trainer_records_the_operating_point_of_the_weights_it_saved(tiny_detect3d_workdir):
    from gac_jax.trained.detector import load_detector
    from gac_jax.trained.run_config import load_run_config

    results = tiny_detect3d_workdir / "results/step_2"
    record = json.loads((results / "operating_point.json").read_text())
    frames = json.loads((results / "metrics.json").read_text())["num_frames"]
    assert record["step"] == 2 and record["split"] == "labeled" and record["frames"] == frames
    assert list(record["sweep"])[:2] == ["0.00", "0.05"]  # the tiny run keeps scores >= 0
    detector = load_detector(tiny_detect3d_workdir, load_run_config(tiny_detect3d_workdir))
    assert record["weights_sha256"] == detector.weights_sha256


def test_api_runs_at_the_recorded_operating_point_of_these_weights_only(
    tiny_detect3d_workdir, tmp_path
):
    from gac_jax.api import Detector3D, InputError

    run = _deployable_copy(tiny_detect3d_workdir, tmp_path)
    recorded = run / "results/step_2/operating_point.json"
    _set_threshold(recorded, 0.35)
    detector = Detector3D.from_workdir(run)
    assert detector.score_threshold == 0.35
    assert "operating point: score >= 0.35" in detector.threshold_source
    assert str(recorded.parent) in detector.threshold_source
    # a threshold given wins
    assert Detector3D.from_workdir(run, score_threshold=0.2).score_threshold == 0.2
    # recorded for other weights: not used, the config's threshold (0.0 in this run) runs
    _set_threshold(recorded, 0.35, sha="0" * 64)
    other = Detector3D.from_workdir(run)
    assert other.score_threshold == 0.0
    assert "no operating point recorded for step 2" in other.threshold_source
    # the config asks for the fixed threshold: the record is not read
    fixed = _deployable_copy(tiny_detect3d_workdir, tmp_path / "fixed", "score_threshold")
    _set_threshold(fixed / "results/step_2/operating_point.json", 0.35)
    assert Detector3D.from_workdir(fixed).score_threshold == 0.0
    bad = _deployable_copy(tiny_detect3d_workdir, tmp_path / "bad", "best")
    with pytest.raises(InputError, match="eval.deploy_threshold must be one of"):
        Detector3D.from_workdir(bad)


def test_a_record_of_another_beta_is_chosen_again_from_its_sweep(tiny_detect3d_workdir, tmp_path):
    from gac_jax.api import Detector3D, InputError

    run = _deployable_copy(tiny_detect3d_workdir, tmp_path)
    path = run / "results/step_2/operating_point.json"
    record = json.loads(path.read_text())
    entry = {"detections": 1.0, "false_positives": 0.5, "found": 3}
    record["sweep"] = {
        "0.50": {**entry, "precision": 0.6, "recall": 0.9},
        "0.80": {**entry, "precision": 0.95, "recall": 0.55},
    }
    record.update(threshold=0.5, beta=1.0)  # F1's choice
    path.write_text(json.dumps(record))
    config = json.loads((run / "config.json").read_text())

    def deployed(beta):
        config["eval"]["operating_point_beta"] = beta
        (run / "config.json").write_text(json.dumps(config))
        return Detector3D.from_workdir(run)

    half = deployed(0.5)
    assert (
        half.score_threshold == 0.8 and "(best F0.5 0.83: precision 0.95" in half.threshold_source
    )
    one = deployed(1.0)
    assert one.score_threshold == 0.5 and "(best F1 0.72: precision 0.60" in one.threshold_source
    del config["eval"]["operating_point_beta"]  # a run config from before the key: F1
    (run / "config.json").write_text(json.dumps(config))
    assert Detector3D.from_workdir(run).score_threshold == 0.5
    with pytest.raises(InputError, match="eval.operating_point_beta must be a number > 0"):
        deployed(-1)


def test_predict_cli_runs_at_the_operating_point_and_says_so(
    tiny_detect3d_workdir, tmp_path, capsys
):
    """The predict CLI at a recorded operating point gives the trainer's result files (kept at
    score 0) less the detections below it: the threshold acts before NMS and the cap, which
    drop a box only for a higher-scoring one."""
    import numpy as np

    from gac_jax.cli import predict
    from gac_jax.data.kitti import read_label

    run = _deployable_copy(tiny_detect3d_workdir, tmp_path)
    reference = run / "results" / "step_2" / "data"
    scores = np.concatenate([read_label(p, with_score=True).score for p in reference.glob("*.txt")])
    ordered = np.unique(scores)  # between two scores of the files: no rounding at the edge
    threshold = float((ordered[len(ordered) // 2 - 1] + ordered[len(ordered) // 2]) / 2)
    _set_threshold(run / "results/step_2/operating_point.json", threshold)
    images = run / "predict_in"
    root = Path(json.loads((run / "config.json").read_text())["data"]["root"])
    ids = [p.stem for p in reference.glob("*.txt")]
    (images / "image_2").mkdir(parents=True)
    (images / "calib").mkdir()
    for fid in ids:
        shutil.copy(root / "training" / "image_2" / f"{fid}.png", images / "image_2")
        shutil.copy(root / "training" / "calib" / f"{fid}.txt", images / "calib")
    out = tmp_path / "out"
    code = predict.main(
        ["--workdir", str(run), str(images / "image_2"), "--out", str(out), "--no-images"]
    )
    stdout = capsys.readouterr().out
    assert code in (0, None)
    assert f"operating point: score >= {threshold:.2f}" in stdout
    kept = 0
    for fid in ids:
        want = [
            line
            for line in (reference / f"{fid}.txt").read_text().splitlines()
            if float(line.split()[-1]) >= threshold
        ]
        got = (out / "data" / f"{fid}.txt").read_text().splitlines()
        assert got == want, fid
        kept += len(got)
    assert 0 < kept < len(scores)


def test_unknown_deploy_mode_is_one_line_naming_the_config(tiny_detect3d_workdir, tmp_path, capsys):
    from gac_jax.cli import guard, predict

    run = _deployable_copy(tiny_detect3d_workdir, tmp_path, "best")
    root = Path(json.loads((run / "config.json").read_text())["data"]["root"])
    images = root / "training" / "image_2"  # with ../calib
    assert predict.main(["--workdir", str(run), str(images)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "config.json" in err[0]
    assert "eval.deploy_threshold must be one of" in err[0]
    assert guard.main(["--workdir", str(run), "--candidates", "onnxruntime:f32"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "config.json: eval.deploy_threshold must be one of" in err[0]
