"""python -m gac_jax.cli.predict: arbitrary KITTI-format images -> result files and pictures."""

from __future__ import annotations

import dataclasses
import shutil

import cv2
import numpy as np
import pytest

from gac_jax.cli import predict
from gac_jax.data.files import read_image, write_png
from gac_jax.data.kitti import read_calib, read_label, write_calib
from gac_jax.data.transforms import resize_affine


def run(argv, capsys):
    code = predict.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_labeled_images_give_the_trainer_results(
    tiny_detect3d_workdir, kitti_object_root, tmp_path, capsys
):
    """The KITTI training images (calibration found in ../calib) through the predict CLI give
    the same result files as the trainer's evaluation of the same checkpoint."""
    out = tmp_path / "out"
    images = kitti_object_root / "training" / "image_2"
    argv = ["--workdir", tiny_detect3d_workdir, images, "--out", out, "--batch-size", 2]
    code, stdout, err = run([*argv, "--no-images"], capsys)
    assert code == 0, err
    reference = tiny_detect3d_workdir / "results" / "step_2" / "data"
    expected = {p.name: p.read_text() for p in reference.glob("*.txt")}
    assert {p.name: p.read_text() for p in (out / "data").glob("*.txt")} == expected
    assert not (out / "pictures").exists()
    assert f"{len(expected)} images" in stdout
    assert "precision: jax float32, the guard's reference" in stdout
    assert "score threshold 0.00 (eval.score_threshold)" in stdout


def test_unlabeled_frames_and_other_image_sizes(
    tiny_detect3d_workdir, kitti_samples_full, tmp_path, capsys
):
    unlabeled = kitti_samples_full / "object" / "unlabeled"
    out = tmp_path / "out"
    code, _, err = run(
        [
            "--workdir",
            tiny_detect3d_workdir,
            unlabeled / "image_2",
            "--out",
            out,
            "--score-threshold",
            0.2,
        ],
        capsys,
    )
    assert code == 0, err
    stems = sorted(p.stem for p in (unlabeled / "image_2").glob("*.png"))
    assert sorted(p.stem for p in (out / "data").glob("*.txt")) == stems
    for stem in stems:
        h, w = read_image(unlabeled / "image_2" / f"{stem}.png").shape[:2]
        det = read_label(out / "data" / f"{stem}.txt", with_score=True)
        assert np.all(det.score > 0.2)
        assert np.all(det.bbox >= 0) and np.all(det.bbox[:, [2, 3]] <= [w - 1, h - 1])
        picture = read_image(out / "pictures" / f"{stem}.png")
        assert picture.shape[0] == h and picture.shape[1] > w  # camera view + bird's-eye view
    assert (out / "pictures" / "grid.png").exists()

    # One image at another size (a crop, then 1.5x larger) with its calibration adjusted;
    # one calibration file for the folder. Boxes come back in that image's pixels.
    stem = stems[0]
    image = read_image(unlabeled / "image_2" / f"{stem}.png")[40:, 100:1000]
    big = cv2.resize(image, (1350, round(image.shape[0] * 1.5)), interpolation=cv2.INTER_LINEAR)
    calib = read_calib(unlabeled / "calib" / f"{stem}.txt")
    A = resize_affine(image.shape[:2], big.shape[:2]) @ np.array(
        [[1.0, 0, -100], [0, 1, -40], [0, 0, 1]]
    )
    folder = tmp_path / "custom"
    write_png(folder / "frame.png", big)
    write_png(folder / "wide.png", np.concatenate([big, big], axis=1))  # cut by the transform
    write_calib(tmp_path / "one_calib.txt", dataclasses.replace(calib, P2=A @ calib.P2))
    out2 = tmp_path / "out2"
    argv = ["--workdir", tiny_detect3d_workdir, folder, "--calib", tmp_path / "one_calib.txt"]
    code, stdout, err = run([*argv, "--out", out2, "--score-threshold", 0.0], capsys)
    assert code == 0, err
    assert "note: 1 images are wider than the model input" in stdout and "(wide)" in stdout
    det = read_label(out2 / "data" / "frame.txt", with_score=True)
    assert len(det) > 0
    assert np.all(det.bbox[:, [2, 3]] <= [big.shape[1] - 1, big.shape[0] - 1])
    assert read_image(out2 / "pictures" / "frame.png").shape[0] == big.shape[0]


def test_missing_calibration_and_inputs(
    tiny_detect3d_workdir, kitti_samples_full, tmp_path, capsys
):
    unlabeled = kitti_samples_full / "object" / "unlabeled"
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(unlabeled / "image_2" / "000038.png", alone / "000038.png")
    shutil.copy(unlabeled / "image_2" / "000043.png", alone / "000043.png")
    wd = tiny_detect3d_workdir

    def error(argv, *needles):
        code, _, err = run(["--workdir", wd, *argv], capsys)
        lines = err.strip().splitlines()
        assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
        for needle in needles:
            assert needle in lines[0], (needle, lines[0])

    error([alone], "000038.png", "no calibration found", "--calib FILE")
    calibs = tmp_path / "calibs"
    calibs.mkdir()
    shutil.copy(unlabeled / "calib" / "000038.txt", calibs)
    error([alone, "--calib", calibs], "calibs/000043.txt", "calibration of")
    error([alone, "--calib", tmp_path / "nope.txt"], "nope.txt", "not found")
    error([tmp_path / "calibs"], "no images")
    error([tmp_path / "missing.png"], "missing.png", "not found")
    bad = tmp_path / "bad.txt"
    bad.write_text("P0: 1 2 3\n")
    error([alone, "--calib", bad], "bad.txt:1", "P0 needs 12 numbers")
    code, _, err = run(["--workdir", tmp_path / "nowd", alone], capsys)
    assert code == 2 and "workdir not found" in err
    with pytest.raises(SystemExit):
        predict.main(["--workdir", str(wd), str(alone), "--threads", "0"])
