"""KITTI's calibration files as KITTI ships them, read by one reader: the object, tracking
and raw formats with the files' own numbers (parsed here independently), raw drive folders
given to ``--sequence`` (or as image input) finding the day's calibration, and a missing or
malformed key reported in one line naming the file and the key (exit 2).

Real files: the vendored KITTI frames (object calibration; the raw day's
``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``) and ``../shared``'s raw clip (a
tracking-format calibration of the same day, ``calib_imu_to_velo.txt``, 78 raw frames); tests
of the latter skip without ``../shared``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from kitti_format_cases import (
    SHARED_DAY,
    TRACKING_CALIB,
    TRACKING_LINES,
    VENDORED_DAY,
    VENDORED_KITTI,
    damage,
    file_numbers,
    needs_shared,
    open_sequence,
    oxts_line,
    raw_drive,
    rigid,
    run_cli,
    tracking_root,
)

from gac_jax.cli import predict, stream_start
from gac_jax.data.files import KittiFormatError, write_png
from gac_jax.data.kitti_calib import read_calib

# --- calibration: every format, with the files' numbers ---------------------------------------


def test_object_calibration_has_the_files_numbers():
    path = VENDORED_KITTI / "object" / "training" / "calib" / "000001.txt"
    want = file_numbers(path)
    calib = read_calib(path)
    assert calib.kind == "object"
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        np.testing.assert_array_equal(getattr(calib, key).ravel(), want[key], err_msg=key)


def test_raw_day_calibration_has_the_files_numbers():
    """The vendored day (``calib_cam_to_cam.txt``, ``calib_velo_to_cam.txt``): ``P_rect_0N`` ->
    ``PN``, ``R_rect_00`` -> ``R0_rect``, ``S_rect_0N`` -> image sizes, R/T -> the velodyne
    transform; the folder reads as its ``calib_cam_to_cam.txt``."""
    cam = file_numbers(VENDORED_DAY / "calib_cam_to_cam.txt")
    velo = file_numbers(VENDORED_DAY / "calib_velo_to_cam.txt")
    for path in (VENDORED_DAY, VENDORED_DAY / "calib_cam_to_cam.txt"):
        calib = read_calib(path)
        assert calib.kind == "raw"
        for n in range(4):
            np.testing.assert_array_equal(getattr(calib, f"P{n}").ravel(), cam[f"P_rect_0{n}"])
            w, h = cam[f"S_rect_0{n}"]
            assert calib.image_sizes[n] == (h, w)
        np.testing.assert_array_equal(calib.R0_rect.ravel(), cam["R_rect_00"])
        np.testing.assert_array_equal(calib.Tr_velo_to_cam, rigid(velo))
        assert calib.Tr_imu_to_velo is None  # not vendored


def test_raw_imu_calibration_and_the_tracking_format_have_the_files_numbers():
    """``calib_imu_to_velo.txt`` of the day, and KITTI's tracking file of the same day
    (``P0:`` .. ``P3:``, then ``R_rect``, ``Tr_velo_cam``, ``Tr_imu_velo`` without a colon):
    the file's numbers, and the same calibration as the raw files."""
    needs_shared(SHARED_DAY / "calib_imu_to_velo.txt", TRACKING_CALIB)
    raw = read_calib(SHARED_DAY)
    np.testing.assert_array_equal(
        raw.Tr_imu_to_velo, rigid(file_numbers(SHARED_DAY / "calib_imu_to_velo.txt"))
    )
    want = file_numbers(TRACKING_CALIB)
    assert set(want) == {"P0", "P1", "P2", "P3", "R_rect", "Tr_velo_cam", "Tr_imu_velo"}
    tracking = read_calib(TRACKING_CALIB)
    assert tracking.kind == "tracking"
    names = {"R0_rect": "R_rect", "Tr_velo_to_cam": "Tr_velo_cam", "Tr_imu_to_velo": "Tr_imu_velo"}
    for key in ("P0", "P1", "P2", "P3", *names):
        value = getattr(tracking, key)
        np.testing.assert_array_equal(value.ravel(), want[names.get(key, key)], err_msg=key)
        np.testing.assert_array_equal(value, getattr(raw, key), err_msg=key)


def test_tracking_keys_read_with_or_without_a_colon(tmp_path):
    text = TRACKING_LINES.replace("R_rect ", "R_rect: ").replace("Tr_imu_velo ", "Tr_imu_velo:")
    path = tmp_path / "0000.txt"
    path.write_text(text)
    calib = read_calib(path)
    np.testing.assert_array_equal(calib.R0_rect, np.eye(3))
    np.testing.assert_array_equal(calib.Tr_imu_to_velo, np.eye(3, 4))


# --- missing or malformed keys: one line naming the file and the key, exit 2 ------------------


@pytest.mark.parametrize(
    "case, expected",
    [
        (
            "raw no P_rect_02",
            "DAY/calib_cam_to_cam.txt: calibration has no P_rect_02 "
            "(the left colour camera projection)",
        ),
        (
            "raw short P_rect_02",
            "DAY/calib_cam_to_cam.txt:LINE: P_rect_02 needs 12 numbers, found 11",
        ),
        ("raw no T", "DAY/calib_velo_to_cam.txt: calibration has no T (the translation)"),
        ("raw bad R", "DAY/calib_velo_to_cam.txt:2: R: non-numeric value 'x'"),
        (
            "raw no imu file",
            "DAY/calib_imu_to_velo.txt: not found; its R and T are needed for the OXTS poses",
        ),
    ],
)
def test_a_raw_calibration_key_missing_or_malformed_is_one_line(tmp_path, capsys, case, expected):
    """Checked before the detector loads (the workdir is empty)."""
    images = raw_drive(tmp_path / "raw", oxts=[oxts_line(), oxts_line(lon=8.40001)])
    day = tmp_path / "raw" / "2011_09_26"
    if case == "raw no P_rect_02":
        damage(day / "calib_cam_to_cam.txt", "P_rect_02:", "P_other_02:")
    elif case == "raw short P_rect_02":
        damage(day / "calib_cam_to_cam.txt", "P_rect_02: 7.215377e+02 ", "P_rect_02: ")
    elif case == "raw no T":
        damage(day / "calib_velo_to_cam.txt", "\nT:", "\nU:")
    elif case == "raw bad R":
        damage(day / "calib_velo_to_cam.txt", "R: 7.533745e-03", "R: x")
    else:
        (day / "calib_imu_to_velo.txt").unlink()
    (tmp_path / "w").mkdir()
    argv = ["--workdir", tmp_path / "w", "--sequence", images, "--track"]
    code, err = run_cli(argv, capsys)
    assert code == 2
    lines = (day / "calib_cam_to_cam.txt").read_text().splitlines()
    line = next((k + 1 for k, text in enumerate(lines) if text.startswith("P_rect_02")), None)
    assert err == [f"error: {expected.replace('DAY', str(day)).replace('LINE', str(line))}"]


@pytest.mark.parametrize(
    "old, new, expected",
    [
        ("P2: ", "P2x: ", "calibration has no P2 (the left colour camera projection)"),
        ("R_rect 1 0 0", "R_rect 1 0", ":5: R_rect needs 9 numbers, found 8"),
        ("Tr_velo_cam 0 -1", "Tr_velo_cam 0 x", ":6: Tr_velo_cam: non-numeric value 'x'"),
        (
            "Tr_imu_velo",
            "Tr_imu",
            ":7: expected 'KEY: v1 v2 ...', got 'Tr_imu 1 0 0 0 0 1 0 0 0 0 1 0'",
        ),
        ("R_rect 1 0 0 0 1 0 0 0 1\n", "", "calibration has no R_rect (needed for the OXTS poses)"),
        (
            "Tr_imu_velo 1 0 0 0 0 1 0 0 0 0 1 0\n",
            "",
            "calibration has no Tr_imu_velo (needed for the OXTS poses)",
        ),
    ],
)
def test_a_tracking_calibration_key_missing_or_malformed_is_one_line(
    tmp_path, capsys, old, new, expected
):
    images = tracking_root(
        tmp_path / "t", TRACKING_LINES.replace(old, new, 1), oxts=[oxts_line()] * 2
    )
    (tmp_path / "w").mkdir()
    code, err = run_cli(["--workdir", tmp_path / "w", "--sequence", images, "--track"], capsys)
    calib = tmp_path / "t" / "training" / "calib" / "0000.txt"
    assert code == 2
    sep = "" if expected.startswith(":") else ": "
    assert err == [f"error: {calib}{sep}{expected}"]


def test_a_given_calibration_of_any_format_names_its_key(tmp_path, capsys):
    """``--calib-camera 3``: on ``image_02`` it is refused, on a drive without ``image_03``
    the missing folder is named, and with a raw ``--calib`` lacking ``P_rect_03`` that key;
    a raw rigid-transform file alone is refused as such."""
    images = raw_drive(tmp_path / "raw")
    drive, day = images.parents[1], images.parents[2]
    damage(day / "calib_cam_to_cam.txt", "P_rect_03:", "P_other_03:")
    (tmp_path / "w").mkdir()
    right = ["--calib", day / "calib_cam_to_cam.txt", "--calib-camera", "3"]
    cases = [
        (
            [images.parent, *right],
            f"{images.parent}: frames of camera 2 (image_02) but P3 chosen: pass --calib-camera 2",
        ),
        ([drive, *right], f"{drive / 'image_03' / 'data'}: sequence folder not found"),
        (
            [drive, "--calib", day / "calib_velo_to_cam.txt"],
            f"{day / 'calib_velo_to_cam.txt'}: holds only R and T of a rigid transform; give "
            "the day's calib_cam_to_cam.txt",
        ),
        (
            "copy image_03",
            f"{day / 'calib_cam_to_cam.txt'}: calibration has no P_rect_03 (the right colour "
            "camera projection)",
        ),
    ]
    for extra, expected in cases:
        if extra == "copy image_03":
            shutil.copytree(images.parent, drive / "image_03")
            extra = [drive, *right]
        code, err = run_cli(["--workdir", tmp_path / "w", "--sequence", *extra], capsys)
        assert (code, err) == (2, [f"error: {expected}"])


# --- raw drive folders given to --sequence ---------------------------------------------------


def test_a_raw_drive_finds_the_days_calibration(tmp_path):
    """``image_02/data``, ``image_02`` or the drive folder: the frames of ``image_02/data`` with
    ``P2`` = the day's ``P_rect_02``; the results go to ``W/predict/<drive>``."""
    images = raw_drive(tmp_path / "raw", frames=3)
    P_rect_02 = file_numbers(VENDORED_DAY / "calib_cam_to_cam.txt")["P_rect_02"].reshape(3, 4)
    for folder in (images, images.parent, images.parents[1]):
        source = open_sequence(folder, tmp_path)
        np.testing.assert_array_equal(source.P2, P_rect_02)
        assert [p.parent for p in source.images] == [images] * 3
        assert source.found == [
            f"calibration: {images.parents[2] / 'calib_cam_to_cam.txt'} (KITTI raw layout)"
        ]
        assert source.times is None  # no timestamps.txt
        args = predict.build_parser().parse_args(["--workdir", "W", "--sequence", str(folder)])
        assert stream_start.output_folder(args) == Path("W/predict/2011_09_26_drive_0001_sync")


def test_the_real_raw_clip_finds_its_calibration(tmp_path):
    needs_shared(SHARED_DAY)
    images = SHARED_DAY / "2011_09_26_drive_unknown_sync" / "image_02" / "data"
    source = open_sequence(images, tmp_path)
    assert source.expected_frames == 78 and source.size == (375, 1242)
    want = file_numbers(SHARED_DAY / "calib_cam_to_cam.txt")["P_rect_02"].reshape(3, 4)
    np.testing.assert_array_equal(source.P2, want)


def test_an_extract_drive_is_refused(tmp_path):
    images = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_extract" / "image_02" / "data"
    write_png(images / "0000000000.png", np.zeros((375, 1242, 3), np.uint8))
    with pytest.raises(KittiFormatError, match="unrectified frames"):
        open_sequence(images, tmp_path)


def test_image_input_of_a_raw_drive_finds_the_days_calibration(tmp_path):
    images = raw_drive(tmp_path / "raw")
    found = predict.find_calibrations(predict.find_images(images), None)
    assert found == [images.parents[2] / "calib_cam_to_cam.txt"] * 2
