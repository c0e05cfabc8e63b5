"""KITTI tracking evaluation: equal to the official TrackEval, 3D MOT and velocity by hand, CLI.

The official figures (tests/data/tracking/trackeval_figures.json) come from running the
official TrackEval code on the cases of tests/tracking_cases.py
(``python benchmarks/trackeval_oracle.py --trackeval CHECKOUT``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gac_jax.cli import evaluate as cli
from gac_jax.data.kitti_tracking import format_poses
from gac_jax.evaluation.tracking.evaluator import (
    evaluate_tracking,
    format_tracking_table,
    load_tracking_folders,
)
from gac_jax.evaluation.tracking.mot3d import mot3d_metrics, row_velocities, smota
from gac_jax.evaluation.tracking.tracking_files import read_tracking_file
from tests import tracking_cases

FIXTURE = Path(__file__).parent / "data" / "tracking" / "trackeval_figures.json"
OFFICIAL_NAMES = {"CLR_TP": "TP", "CLR_FN": "FN", "CLR_FP": "FP"}


def _evaluate_case(name, root, **kw):
    tracking_cases.write_case(name, root)
    return evaluate_tracking(load_tracking_folders(root / "label_02", root / "results"), **kw)


@pytest.mark.parametrize("case", tracking_cases.CASES)
def test_equals_official_trackeval(case, tmp_path):
    official = json.loads(FIXTURE.read_text())[case]
    result = _evaluate_case(case, tmp_path, with_3d=False)
    for cls in ("car", "pedestrian"):
        for key, value in official[cls].items():
            if key == "sequences":
                continue
            mine = result[cls][OFFICIAL_NAMES.get(key, key)]
            assert mine == pytest.approx(value, rel=1e-12, abs=1e-12), (case, cls, key)
        assert set(result[cls]["sequences"]) == set(official[cls]["sequences"])
        for seq, figures in official[cls]["sequences"].items():
            for key, value in figures.items():
                mine = result[cls]["sequences"][seq][key]
                if mine is None:  # MOTA without ground truth: undefined (the official prints 0)
                    assert key == "MOTA" and value == 0 and figures["ML"] + figures["MT"] == 0
                    continue
                assert mine == pytest.approx(value, rel=1e-12, abs=1e-12), (case, cls, seq, key)


def test_hand_case_counts_by_hand(tmp_path):
    """tracking_cases.HAND_*: the counts follow from the scenario as written there."""
    car = _evaluate_case("hand", tmp_path, with_3d=False)["car"]
    # car 1: 6 of 7 frames (miss in 3); car 2: 5 of 6 (loose box in 2); 0002's car: 0 of 3
    assert (car["TP"], car["FN"]) == (11, 5)
    # loose box (frame 2), the real FP (frame 3), the FP of the empty sequence 0001; the
    # Van, DontCare, 20 px, truncated- and occluded-car boxes are removed
    assert car["FP"] == 3
    assert car["IDSW"] == 1  # car 1: id 10 -> 11
    # car 1 restarts in frame 4, car 2 in frame 3; frame 6 has no object, so car 1 in frame 7
    # continues frame 5
    assert car["Frag"] == 2
    assert (car["MT"], car["PT"], car["ML"]) == (2, 0, 1)
    assert car["MOTA"] == pytest.approx((11 - 3 - 1) / 16)


def _box_line(frame, tid, z, x=0.0, score=None, typ="Car"):
    u = 600 + 700 * x / z
    half, top, bottom = 700 * 0.8 / z, 170 - 700 * 0.0 / z, 170 + 700 * 1.5 / z
    line = (
        f"{frame} {tid} {typ} 0 0 0 {u - half:.4f} {top:.4f} {u + half:.4f} {bottom:.4f} "
        f"1.5 1.6 3.9 {x:.6f} 1.5 {z:.6f} 0"
    )
    return line + (f" {score}\n" if score is not None else "\n")


def test_samota_amota_amotp_by_hand(tmp_path):
    """One car over 4 frames. Track A (score 0.9) has it in frames 0-1, track B (0.5) in 2-3
    (an id switch), track C (0.2) is a false positive. TP scores 0.9, 0.9, 0.5, 0.5 give the
    thresholds 0.9, 0.5, 0.5 at recalls 1/40, 2/40, 3/40 (the first, recall 0, is dropped).
    At 0.9: TP 2, FN 2 -> MOTA 0.5, sMOTA_1/40 = clip(1 - (2 - 39/40*4) / (4/40)) = 1.
    At 0.5: TP 4, IDSW 1 -> MOTA 0.75, sMOTA = 1 (twice). MOTP 1 (exact boxes).
    sAMOTA = 3/40, AMOTA = (0.5 + 0.75 + 0.75)/40, AMOTP = 3/40."""
    (tmp_path / "label_02").mkdir()
    (tmp_path / "results").mkdir()
    z = [20.0, 21.0, 22.0, 23.0]
    (tmp_path / "label_02/0000.txt").write_text("".join(_box_line(f, 0, z[f]) for f in range(4)))
    res = [_box_line(f, 1 if f < 2 else 2, z[f], score=0.9 if f < 2 else 0.5) for f in range(4)]
    res += [_box_line(f, 3, 40.0, x=8.0, score=0.2) for f in range(4)]
    (tmp_path / "results/0000.txt").write_text("".join(res))
    seqs = load_tracking_folders(tmp_path / "label_02", tmp_path / "results")
    for iou in (0.25, 0.5):
        m = mot3d_metrics(seqs, "car", iou)
        assert m["thresholds"] == 3
        assert m["sAMOTA"] == pytest.approx(3 / 40)
        assert m["AMOTA"] == pytest.approx((0.5 + 0.75 + 0.75) / 40)
        assert m["AMOTP"] == pytest.approx(3 / 40)
        assert m["MOTA"] == pytest.approx((4 - 4 - 1) / 4)  # all tracks: C's 4 boxes are FPs
    # sMOTA at recall 1 is MOTA clipped to [0, 1]; at recall r it forgives (1 - r) N misses
    assert smota(fn=10, fp=5, idsw=1, n_gt=100, recall=1.0) == pytest.approx(0.84)
    assert smota(fn=60, fp=0, idsw=0, n_gt=100, recall=0.5) == pytest.approx(0.8)


def test_3d_mot_equals_ab3dmot_script_on_a_clean_case(tmp_path):
    """tests/data/tracking/ab3dmot_figures.json: AB3DMOT's scripts/KITTI/evaluate.py on
    tracking_cases.clean_3d_lines (benchmarks/ab3dmot_oracle.py), where the TrackEval-based
    rule counts as the script does (tests/test_ab3dmot_rules.py: the script's rule on sets
    where they differ). MOTA differs by definition: every track here, the best threshold's
    there."""
    figures = json.loads((FIXTURE.parent / "ab3dmot_figures.json").read_text())["clean_3d"]
    labels, results = tracking_cases.clean_3d_lines()
    for name, lines in (("label_02", labels), ("results", results)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "0000.txt").write_text("".join(lines["0000"]))
    seqs = load_tracking_folders(tmp_path / "label_02", tmp_path / "results")
    for iou, by_class in figures.items():
        mine = mot3d_metrics(seqs, "car", float(iou))
        for key in ("sAMOTA", "AMOTA", "AMOTP", "thresholds"):
            assert mine[key] == pytest.approx(by_class["car"][key], rel=1e-12), (iou, key)
    assert figures["0.25"]["car"]["sAMOTA"] != pytest.approx(figures["0.50"]["car"]["sAMOTA"])


def _moving_car(root: Path, out: Path, n: int = 6) -> np.ndarray:
    """A clip set ``root/training`` (labels, poses) and tracker output ``out/tracking``: the
    ego drives 0.5 m/frame forward, the car 1 m/frame (10 m/s over the ground at 10 Hz); the
    tracker's depth drifts 0.2 m/frame more, i.e. 2 m/s too fast. Returns the poses."""
    for d in (root / "training/label_02", root / "training/poses", out / "tracking"):
        d.mkdir(parents=True)
    poses = np.zeros((n, 3, 4))
    poses[:, :, :3] = np.eye(3)
    poses[:, 2, 3] = 0.5 * np.arange(n)
    (root / "training/poses/0000.txt").write_text(format_poses(poses))
    cam_z = [15.0 + 1.0 * k - 0.5 * k for k in range(n)]
    labels = "".join(_box_line(k, 0, cam_z[k]) for k in range(n))
    (root / "training/label_02/0000.txt").write_text(labels)
    results = "".join(_box_line(k, 7, cam_z[k] + 0.2 * k, score=0.9) for k in range(n))
    (out / "tracking/0000.txt").write_text(results)
    return poses


def test_velocity_error_by_hand(tmp_path):
    poses = _moving_car(tmp_path / "clips", tmp_path / "out")
    labels, results = tmp_path / "clips/training/label_02", tmp_path / "out/tracking"
    seqs = load_tracking_folders(labels, results, None, tmp_path / "clips/training/poses")
    gt_rows = read_tracking_file(labels / "0000.txt")
    np.testing.assert_allclose(row_velocities(gt_rows, 10.0, poses), [[0.0, 10.0]] * 6, atol=1e-9)
    vel = evaluate_tracking(seqs, ("car",))["car"]["velocity"]
    assert vel["frame"] == "world"
    assert vel["pairs"] == 6
    assert vel["mean"] == pytest.approx(2.0) and vel["median"] == pytest.approx(2.0)
    # without poses: relative velocities (5 and 7 m/s), the same 2 m/s error
    vel = evaluate_tracking(load_tracking_folders(labels, results), ("car",))["car"]["velocity"]
    assert vel["frame"] == "camera" and vel["mean"] == pytest.approx(2.0)
    # a class with 3D boxes but no matched pair with a velocity prints '-' (no mean / median)
    both = evaluate_tracking(seqs, ("car", "pedestrian"))
    both["pedestrian"]["velocity"] = {"frame": "world", "pairs": 0, "mean": None, "median": None}
    assert "Pedestrian   world       0         -       -" in format_tracking_table(both)


def _run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_prints_table_and_writes_json(tmp_path, capsys):
    tracking_cases.write_case("hand", tmp_path)
    out_json = tmp_path / "out.json"
    argv = ["--task", "track", "--label-dir", tmp_path / "label_02"]
    argv += ["--result-dir", tmp_path / "results", "--json", out_json]
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    header = next(line for line in out.splitlines() if line.startswith("class"))
    assert " ".join(header.split()[1:]) == "HOTA DetA AssA LocA MOTA MOTP IDF1 IDSW Frag MT ML"
    assert any(line.startswith("Car ") for line in out.splitlines())
    assert "sAMOTA" in out and "velocity" in out
    result = json.loads(out_json.read_text())
    official = json.loads(FIXTURE.read_text())["hand"]
    assert result["car"]["HOTA"] == pytest.approx(official["car"]["HOTA"], rel=1e-12)
    assert set(result["car"]["mot3d"]) == {"0.25", "0.50"}
    assert result["_meta"]["sequences"] == ["0000", "0001", "0002"]
    code, out, _ = _run([*argv[:-2], "--classes", "pedestrian"], capsys)
    assert code == 0 and "Car " not in out and "Pedestrian " in out


def test_cli_clip_set_and_stream_output_folder(tmp_path, capsys):
    """--data finds label_02 and poses; a predict --track output folder is read as it is."""
    _moving_car(tmp_path / "clips", tmp_path / "out")
    out_json = tmp_path / "r.json"
    argv = ["--task", "track", "--data", tmp_path / "clips", "--result-dir", tmp_path / "out"]
    code, out, err = _run([*argv, "--classes", "car", "--json", out_json], capsys)
    assert code == 0, err
    assert "poses for 1" in out
    result = json.loads(out_json.read_text())
    assert result["car"]["velocity"]["frame"] == "world"
    assert result["car"]["IDF1"] == 1.0 and result["_meta"]["result_dir"].endswith("tracking")
    with pytest.raises(SystemExit) as exit_info:
        _run([*argv, "--frame-rate", "0"], capsys)
    assert exit_info.value.code == 2 and "--frame-rate" in capsys.readouterr().err


def test_cli_2d_only_results_and_empty_sequence(tmp_path, capsys):
    """Results without 3D boxes: no 3D block; a sequence with neither labels nor results."""
    tracking_cases.write_case("hand", tmp_path)
    for path in (tmp_path / "results").glob("*.txt"):
        lines = [f.split() for f in path.read_text().splitlines()]
        flat = [f[:10] + ["-1", "-1", "-1", "-1000", "-1000", "-1000", "-10", f[17]] for f in lines]
        path.write_text("".join(" ".join(f) + "\n" for f in flat))
    (tmp_path / "label_02" / "0003.txt").write_text("")
    with (tmp_path / "evaluate_tracking.seqmap.training").open("a") as f:
        f.write("0003 empty 000000 000004\n")
    out_json = tmp_path / "out.json"
    argv = ["--task", "track", "--label-dir", tmp_path / "label_02"]
    code, out, err = _run([*argv, "--result-dir", tmp_path / "results", "--json", out_json], capsys)
    assert code == 0, err
    assert "sAMOTA" not in out and "1 sequences without a result file" in out
    result = json.loads(out_json.read_text())
    assert result["car"]["mot3d"] is None and result["car"]["velocity"] is None
    official = json.loads(FIXTURE.read_text())["hand"]["car"]
    assert result["car"]["HOTA"] == pytest.approx(official["HOTA"], rel=1e-12)
    assert result["car"]["sequences"]["0003"]["MOTA"] is None


def _assert_one_line(code, err, *needles):
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_cli_bad_input_one_line_exit_2(tmp_path, capsys):
    tracking_cases.write_case("hand", tmp_path)
    labels, results = tmp_path / "label_02", tmp_path / "results"
    base = ["--task", "track", "--label-dir", labels, "--result-dir", results]
    bad = results / "0000.txt"
    good = bad.read_text()
    bad.write_text(good + "3 9 Car 0 0 0 1 2 3 4 1 1 1 1 1\n")  # 15 columns
    n_lines = len(good.splitlines()) + 1
    _assert_one_line(*_run(base, capsys)[::2], f"0000.txt:{n_lines}", "columns")
    bad.write_text(good + good.splitlines()[0] + "\n")  # the same id twice in frame 0
    _assert_one_line(*_run(base, capsys)[::2], "0000.txt", "twice in frame 0")
    bad.write_text(good)
    (results / "0042.txt").write_text("")
    _assert_one_line(*_run(base, capsys)[::2], "0042.txt", "no labels")
    (results / "0042.txt").unlink()
    _assert_one_line(*_run([*base, "--sequences", "0000,0009"], capsys)[::2], "0009")
    (labels / "0002.txt").write_text("0 0 Car 0 0 0 1 2 x 4 1 1 1 1 1 1 0\n")
    _assert_one_line(*_run(base, capsys)[::2], "0002.txt:1", "non-numeric")
