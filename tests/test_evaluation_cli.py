"""evaluate.py offline mode: JSON schema, exit codes and one-line errors naming the file."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gac_jax.cli import evaluate as cli
from gac_jax.data.files import read_depth_png, write_depth_png
from gac_jax.data.kitti import KittiObjectLayout, read_label, write_label, write_split
from gac_jax.evaluation.depth_metrics import DEPTH_METRICS
from gac_jax.evaluation.kitti_object import evaluate_detections

REPO = Path(__file__).resolve().parents[1]
DEPTH_GT_DIR = "depth/data_depth_annotated/train/2011_09_26_drive_0001_sync/proj_depth/groundtruth"


@pytest.fixture()
def detection_dirs(kitti_object_root, tmp_path):
    """(label dir, result dir with perfect results for all frames but the first, frame ids)."""
    layout = KittiObjectLayout(kitti_object_root)
    ids = layout.frame_ids("labeled")
    results = tmp_path / "results"
    results.mkdir()
    for frame_id in ids[1:]:
        gt = read_label(layout.label(frame_id))
        det = gt.select(gt.type != "DontCare")
        write_label(
            results / f"{frame_id}.txt", det.replace(score=np.linspace(1, 0.5, len(det))), True
        )
    return layout.frames_dir / "label_2", results, ids


def run_main(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, *needles):
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_missing_result_files_are_counted_and_require_all_refuses(detection_dirs, capsys):
    labels, results, ids = detection_dirs
    (results / f"{ids[1]}.txt").unlink()
    argv = ["--task", "detect3d", "--label-dir", labels, "--result-dir", results]
    code, out, err = run_main(argv, capsys)
    assert code == 0, err
    assert f"2 of {len(ids)} frames have no result file" in out
    assert cli.missing_result_ids(results, ids) == ids[:2]
    code, out, err = run_main([*argv, "--require-all"], capsys)
    assert_one_line_error(code, err, str(results), f"2 of {len(ids)} frames", "--require-all")
    assert "AP|R40" not in out
    # Every result file present: --require-all scores as usual.
    for i in ids[:2]:
        (results / f"{i}.txt").write_text("")
    code, out, err = run_main([*argv, "--require-all"], capsys)
    assert code == 0 and f"0 of {len(ids)} frames have no result file" in out, err


def test_detect3d_json_schema_and_values(detection_dirs, tmp_path, capsys):
    labels, results, ids = detection_dirs
    out_json = tmp_path / "out" / "ap.json"
    code, out, err = run_main(
        ["--task", "detect3d", "--label-dir", labels, "--result-dir", results, "--json", out_json],
        capsys,
    )
    assert code == 0, err
    assert "AP|R40" in out and f"{len(ids)} frames" in out
    assert f"1 of {len(ids)} frames have no result file" in out and f"{ids[0]}.txt" in out
    data = json.loads(out_json.read_text())
    assert set(data) == {"ap11", "ap40", "_meta"}
    # Which overlaps each entry used: the loose setting keeps bbox/AOS at the strict value.
    car = {"bbox": 0.7, "aos": 0.7}
    small = {"bbox": 0.5, "aos": 0.5}
    assert data.pop("_meta") == {
        "min_overlap": {
            "Car": {
                "0.70": {"setting": "strict", **car, "bev": 0.7, "3d": 0.7},
                "0.50": {"setting": "loose", **car, "bev": 0.5, "3d": 0.5},
            },
            **{
                cls: {
                    "0.50": {"setting": "strict", **small, "bev": 0.5, "3d": 0.5},
                    "0.25": {"setting": "loose", **small, "bev": 0.25, "3d": 0.25},
                }
                for cls in ("Pedestrian", "Cyclist")
            },
        }
    }
    for ap in data.values():
        assert set(ap) == {"Car", "Pedestrian", "Cyclist"}
        assert set(ap["Car"]) == {"0.70", "0.50"}
        assert set(ap["Pedestrian"]) == set(ap["Cyclist"]) == {"0.50", "0.25"}
        for per_class in ap.values():
            for entry in per_class.values():
                assert set(entry) == {"bbox", "bev", "3d", "aos"}
                for values in entry.values():
                    assert len(values) == 3 and all(isinstance(v, float) for v in values)
    # Same numbers as the library on the same frames (frame 0 has no result file: no detections).
    gts = [read_label(labels / f"{i}.txt") for i in ids]
    dts = [read_label(results / f"{i}.txt", with_score=True) for i in ids[1:]]
    dts.insert(0, gts[0].select(np.zeros(len(gts[0]), bool)))
    assert data == json.loads(json.dumps(evaluate_detections(gts, dts)))
    assert data["ap40"]["Car"]["0.70"]["3d"][1] > 0


def test_detect3d_split_file_and_classes(detection_dirs, tmp_path, capsys):
    labels, results, ids = detection_dirs
    split = tmp_path / "sub.txt"
    write_split(split, ids[1:3])
    out_json = tmp_path / "ap.json"
    code, out, _ = run_main(
        [
            "--task",
            "detect3d",
            "--label-dir",
            labels,
            "--result-dir",
            results,
            "--split-file",
            split,
            "--classes",
            "Car",
            "--json",
            out_json,
        ],
        capsys,
    )
    assert code == 0 and "2 frames" in out
    data = json.loads(out_json.read_text())
    assert set(data["ap40"]) == set(data["_meta"]["min_overlap"]) == {"Car"}


def _copy_results(results, tmp_path):
    bad = tmp_path / "bad_results"
    shutil.copytree(results, bad)
    return bad


def _edit_line(path: Path, line_no: int, edit):
    lines = path.read_text().splitlines()
    lines[line_no - 1] = edit(lines[line_no - 1].split())
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "edit, needle",
    [
        (lambda f: " ".join(f[:15]), "expected 16 columns, found 15"),
        (lambda f: " ".join(f[:5] + ["nan"] + f[6:]), "not finite"),
        (lambda f: " ".join(f[:9] + ["-1.5"] + f[10:]), "negative 3D size"),
    ],
    ids=["columns", "nan", "negative-size"],
)
def test_detect3d_invalid_result_line(detection_dirs, tmp_path, capsys, edit, needle):
    labels, results, ids = detection_dirs
    bad = _copy_results(results, tmp_path)
    target = bad / f"{ids[2]}.txt"
    _edit_line(target, 2, edit)
    code, _, err = run_main(
        ["--task", "detect3d", "--label-dir", labels, "--result-dir", bad], capsys
    )
    assert_one_line_error(code, err, f"{target}:2", needle)


def test_detect3d_missing_label_and_folders(detection_dirs, tmp_path, capsys):
    labels, results, ids = detection_dirs
    split = tmp_path / "split.txt"
    write_split(split, [ids[0], "999999"])
    code, _, err = run_main(
        [
            "--task",
            "detect3d",
            "--label-dir",
            labels,
            "--result-dir",
            results,
            "--split-file",
            split,
        ],
        capsys,
    )
    assert_one_line_error(code, err, str(labels / "999999.txt"), "not found")
    code, _, err = run_main(
        ["--task", "detect3d", "--label-dir", labels, "--result-dir", tmp_path / "nope"], capsys
    )
    assert_one_line_error(code, err, "nope", "result folder not found")
    empty = tmp_path / "empty_labels"
    empty.mkdir()
    code, _, err = run_main(
        ["--task", "detect3d", "--label-dir", empty, "--result-dir", results], capsys
    )
    assert_one_line_error(code, err, "empty_labels", "no label files")


@pytest.fixture()
def depth_dirs(kitti_samples, tmp_path):
    """Ground truth (2 nested PNGs) and predictions = ground truth x 2 (exact in 16 bit)."""
    src = kitti_samples / DEPTH_GT_DIR
    gt_dir = tmp_path / "gt"
    shutil.copytree(src, gt_dir)
    pred_dir = tmp_path / "pred"
    for png in sorted(gt_dir.rglob("*.png")):
        rel = png.relative_to(gt_dir)
        gt = read_depth_png(png)
        write_depth_png(pred_dir / rel, np.where(gt > 0, 2.0 * gt, 1.0))
    return gt_dir, pred_dir


def test_depth_json(depth_dirs, tmp_path, capsys):
    gt_dir, pred_dir = depth_dirs
    out_json = tmp_path / "depth.json"
    code, out, err = run_main(
        [
            "--task",
            "depth",
            "--groundtruth-dir",
            gt_dir,
            "--prediction-dir",
            pred_dir,
            "--json",
            out_json,
        ],
        capsys,
    )
    assert code == 0, err
    assert "(2 images)" in out
    data = json.loads(out_json.read_text())
    assert list(data) == list(DEPTH_METRICS)
    assert data["silog"] == pytest.approx(0.0, abs=1e-6)
    assert data["abs_rel"] == pytest.approx(100.0, rel=1e-12)
    assert data["sq_rel"] == pytest.approx(100.0, rel=1e-12)
    assert data["delta3"] == 0.0


def test_depth_invalid_inputs(depth_dirs, tmp_path, capsys):
    gt_dir, pred_dir = depth_dirs
    pngs = sorted(p.relative_to(pred_dir) for p in pred_dir.rglob("*.png"))
    args = ["--task", "depth", "--groundtruth-dir", gt_dir, "--prediction-dir", pred_dir]

    # wrong size
    full = read_depth_png(pred_dir / pngs[0])
    write_depth_png(pred_dir / pngs[0], full[:, :-8])
    code, _, err = run_main(args, capsys)
    assert_one_line_error(code, err, str(pred_dir / pngs[0]), "but the ground truth is")
    # zero where the ground truth is valid
    gt0 = read_depth_png(gt_dir / pngs[0])
    write_depth_png(pred_dir / pngs[0], np.zeros_like(gt0))
    code, _, err = run_main(args, capsys)
    assert_one_line_error(code, err, str(pred_dir / pngs[0]), "finite and > 0")
    # missing
    (pred_dir / pngs[1]).unlink()
    write_depth_png(pred_dir / pngs[0], np.where(gt0 > 0, gt0, 1.0))
    code, _, err = run_main(args, capsys)
    assert_one_line_error(code, err, str(pred_dir / pngs[1]), "prediction missing")
    # ground-truth folder without PNGs
    empty = tmp_path / "empty_gt"
    empty.mkdir()
    code, _, err = run_main(
        ["--task", "depth", "--groundtruth-dir", empty, "--prediction-dir", pred_dir], capsys
    )
    assert_one_line_error(code, err, str(empty), "no ground-truth PNG")


def test_entry_point_subprocess(tmp_path):
    empty = tmp_path / "g"
    empty.mkdir()
    proc = subprocess.run(
        [
            sys.executable,
            "evaluate.py",
            "--task",
            "depth",
            "--groundtruth-dir",
            str(empty),
            "--prediction-dir",
            str(empty),
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: {empty}: no ground-truth PNG files found"
    proc = subprocess.run(
        [sys.executable, "evaluate.py", "--task", "detect3d"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "needs --label-dir and --result-dir" in proc.stderr
    assert "Traceback" not in proc.stderr
