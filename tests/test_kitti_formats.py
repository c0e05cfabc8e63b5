"""KITTI's own formats as KITTI ships them: calibration files of the object, tracking and raw
releases read by one reader with the files' numbers, raw drive folders found by ``--sequence``,
OXTS packets turned into camera poses as the KITTI devkit does it (against an independent
float64 reference of ``convertOxtsToPose``), ``timestamps.txt`` as frame times, and a missing
or malformed key reported in one line naming the file and the key (exit 2).

The real files: the vendored KITTI frames (object calibration; the raw day's
``calib_cam_to_cam.txt`` and ``calib_velo_to_cam.txt``) and ``../shared``'s raw clip (a tracking
format calibration, the day's ``calib_imu_to_velo.txt``, 78 raw frames) and raw frame with its
OXTS packet; tests of the latter skip without ``../shared``.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import KITTI_SAMPLES, VENDORED_KITTI

from gac_jax.cli import predict, predict_stream, predict_track
from gac_jax.data import kitti_oxts, kitti_raw
from gac_jax.data.files import KittiFormatError, write_png
from gac_jax.data.kitti_calib import read_calib
from gac_jax.data.kitti_tracking import KittiTrackingLayout
from gac_jax.streams.sources import Frame, SequenceSource
from gac_jax.streams.tracking import TrackingStage

VENDORED_DAY = VENDORED_KITTI / "depth" / "raw" / "2011_09_26"
RAW_CLIP = KITTI_SAMPLES / "raw_clip"
SHARED_DAY = RAW_CLIP / "2011_09_26"
TRACKING_CALIB = RAW_CLIP / "tracking_format" / "calib" / "0000.txt"
DEPTH_DRIVE = KITTI_SAMPLES / "depth" / "raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
REAL_OXTS = DEPTH_DRIVE / "oxts" / "data" / "0000000005.txt"
# The devkit's frames: velodyne (x forward, y left, z up) -> camera (x right, y down, z forward)
VELO_TO_CAM_AXES = np.array([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])


def needs_shared(*paths: Path) -> None:
    missing = [p for p in paths if not p.exists()]
    if missing:
        pytest.skip(f"needs ../shared's KITTI raw samples (not found: {missing[0]})")


def file_numbers(path: Path) -> dict[str, np.ndarray]:
    """Every ``KEY[:] numbers`` line of a file -> float64 numbers (the test's own reading)."""
    out = {}
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        key, _, rest = line.replace(":", " ", 1).partition(" ")
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()])
        except ValueError:
            continue  # calib_time: 09-Jan-2012 13:57:47
    return out


def rigid(numbers: dict[str, np.ndarray]) -> np.ndarray:
    return np.concatenate([numbers["R"].reshape(3, 3), numbers["T"].reshape(3, 1)], axis=1)


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

P2_LINE = "721.5377 0 609.5593 44.85728 0 721.5377 172.854 0.2163791 0 0 1 0.002745884"
TRACKING_LINES = (
    f"P0: {P2_LINE}\nP1: {P2_LINE}\nP2: {P2_LINE}\nP3: {P2_LINE}\n"
    "R_rect 1 0 0 0 1 0 0 0 1\n"
    "Tr_velo_cam 0 -1 0 0 0 0 -1 0 1 0 0 0\n"
    "Tr_imu_velo 1 0 0 0 0 1 0 0 0 0 1 0\n"
)


def raw_drive(root: Path, frames: int = 2, oxts: list[str] | None = None) -> Path:
    """A KITTI raw day ``root/2011_09_26`` (the vendored calibration, an identity IMU ->
    velodyne) with a drive of ``frames`` grey 1242x375 frames; its ``image_02/data``."""
    day = root / "2011_09_26"
    day.mkdir(parents=True)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt"):
        shutil.copy(VENDORED_DAY / name, day / name)
    (day / "calib_imu_to_velo.txt").write_text("R: 1 0 0 0 1 0 0 0 1\nT: 0 0 0\n")
    drive = day / "2011_09_26_drive_0001_sync"
    for k in range(frames):
        write_png(
            drive / "image_02" / "data" / f"{k:010d}.png", np.full((375, 1242, 3), 90, np.uint8)
        )
    for k, line in enumerate(oxts or []):
        (drive / "oxts" / "data").mkdir(parents=True, exist_ok=True)
        (drive / "oxts" / "data" / f"{k:010d}.txt").write_text(line + "\n")
    return drive / "image_02" / "data"


def tracking_root(root: Path, calib: str, frames: int = 2, oxts: list[str] | None = None) -> Path:
    """A KITTI tracking root with sequence 0000 of ``frames`` frames; its image folder."""
    images = root / "training" / "image_02" / "0000"
    for k in range(frames):
        write_png(images / f"{k:06d}.png", np.full((375, 1242, 3), 90, np.uint8))
    (root / "training" / "calib").mkdir(parents=True)
    (root / "training" / "calib" / "0000.txt").write_text(calib)
    if oxts is not None:
        (root / "training" / "oxts").mkdir(parents=True)
        (root / "training" / "oxts" / "0000.txt").write_text("".join(f"{x}\n" for x in oxts))
    return images


def run_cli(argv, capsys) -> tuple[int, list[str]]:
    code = predict.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip().splitlines()


def damage(path: Path, old: str, new: str) -> None:
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))


def oxts_line(lat=49.0, lon=8.4, alt=110.0, roll=0.0, pitch=0.0, yaw=0.0) -> str:
    return " ".join(str(v) for v in [lat, lon, alt, roll, pitch, yaw] + [0.0] * 19 + [4] * 5)


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


def open_sequence(folder: Path, workdir: Path, *extra) -> SequenceSource:
    args = predict.build_parser().parse_args(
        ["--workdir", str(workdir), "--sequence", str(folder), *map(str, extra)]
    )
    return predict_stream.open_source(args)


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
        assert predict_stream.output_folder(args) == Path("W/predict/2011_09_26_drive_0001_sync")


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


# --- OXTS -> camera poses: the devkit's convertOxtsToPose, then IMU -> velodyne -> camera -----


def devkit_poses(packets: list[list[float]], T_cam_imu: np.ndarray) -> np.ndarray:
    """The devkit's MATLAB ``convertOxtsToPose`` transcribed packet by packet in float64, then
    each pose conjugated into the camera: ``T pose T^-1``."""
    er = 6378137.0
    scale = math.cos(packets[0][0] * math.pi / 180.0)
    out, Tr_0_inv = [], None
    for p in packets:
        lat, lon, alt, rx, ry, rz = p[:6]
        t = [
            scale * lon * math.pi * er / 180.0,
            scale * er * math.log(math.tan((90.0 + lat) * math.pi / 360.0)),
            alt,
        ]
        Rx = np.array(
            [[1, 0, 0], [0, math.cos(rx), -math.sin(rx)], [0, math.sin(rx), math.cos(rx)]]
        )
        Ry = np.array(
            [[math.cos(ry), 0, math.sin(ry)], [0, 1, 0], [-math.sin(ry), 0, math.cos(ry)]]
        )
        Rz = np.array(
            [[math.cos(rz), -math.sin(rz), 0], [math.sin(rz), math.cos(rz), 0], [0, 0, 1]]
        )
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rz @ Ry @ Rx, t
        if Tr_0_inv is None:
            Tr_0_inv = np.linalg.inv(T)
        out.append(T_cam_imu @ (Tr_0_inv @ T) @ np.linalg.inv(T_cam_imu))
    return np.array(out)[:, :3]


def homogeneous(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


def test_oxts_poses_of_the_real_packet_match_the_devkit(tmp_path):
    """The real packet of drive 0001 frame 5 and two made from it (moved, turned, tilted):
    the poses of a raw drive folder through the day's real calibration equal the devkit's."""
    needs_shared(REAL_OXTS, SHARED_DAY / "calib_imu_to_velo.txt")
    real = [float(v) for v in REAL_OXTS.read_text().split()]
    assert len(real) == 30
    second = [
        real[0] + 2e-5,
        real[1] - 3e-5,
        real[2] + 0.4,
        real[3] + 0.01,
        real[4] - 0.02,
        real[5] + 0.3,
        *real[6:],
    ]
    third = [
        real[0] + 5e-5,
        real[1] + 1e-5,
        real[2] - 0.2,
        real[3],
        real[4] + 0.03,
        real[5] - 0.5,
        *real[6:],
    ]
    packets = [real, second, third]
    cam = file_numbers(SHARED_DAY / "calib_cam_to_cam.txt")
    T = (
        homogeneous(cam["R_rect_00"].reshape(3, 3))
        @ homogeneous(rigid(file_numbers(SHARED_DAY / "calib_velo_to_cam.txt")))
        @ homogeneous(rigid(file_numbers(SHARED_DAY / "calib_imu_to_velo.txt")))
    )
    want = devkit_poses(packets, T)
    images = raw_drive(tmp_path / "raw", frames=3)
    for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt"):
        shutil.copy(SHARED_DAY / name, images.parents[2] / name)
    oxts = images.parents[1] / "oxts" / "data"
    oxts.mkdir(parents=True)
    shutil.copy(REAL_OXTS, oxts / "0000000000.txt")
    for k, p in ((1, second), (2, third)):
        (oxts / f"{k:010d}.txt").write_text(" ".join(repr(v) for v in p) + "\n")
    source = open_sequence(images, tmp_path, "--track")
    lines = []
    poses = predict_track.stream_poses(source_args(tmp_path, images), source, lines.append)
    np.testing.assert_allclose(poses, want, rtol=0, atol=1e-9)
    assert np.abs(poses[1:, :, 3]).max() > 1  # metres: the test moves
    assert lines == [predict_track.oxts_line(oxts)]
    # The devkit's absolute Mercator position of the real packet, to the nanometre.
    world = kitti_oxts.imu_world_poses(np.array([real]))[0]
    s = math.cos(real[0] * math.pi / 180)
    np.testing.assert_allclose(
        world[:3, 3],
        [
            s * 6378137 * real[1] * math.pi / 180,
            s * 6378137 * math.log(math.tan((90 + real[0]) * math.pi / 360)),
            real[2],
        ],
        rtol=0,
        atol=1e-9,
    )


def source_args(workdir: Path, folder: Path, *extra):
    return predict.build_parser().parse_args(
        ["--workdir", str(workdir), "--sequence", str(folder), "--track", *map(str, extra)]
    )


def straight_drive(heading: float, course: float, frames: int = 4, lat0: float = 49.0):
    """Packets of a drive that moves 1 m per frame on the ground along ``course`` (radians,
    0 east, pi/2 north) heading ``heading``: positions placed by the inverse Mercator map."""
    er, s = 6378137.0, math.cos(lat0 * math.pi / 180)
    y0 = s * er * math.log(math.tan((90 + lat0) * math.pi / 360))
    out = []
    for k in range(frames):
        x, y = k * math.cos(course), y0 + k * math.sin(course)
        lon = x / (s * er) * 180 / math.pi + 8.4
        lat = 360 / math.pi * math.atan(math.exp(y / (s * er))) - 90
        out.append([float(v) for v in oxts_line(lat, lon, 110.0, 0, 0, heading).split()])
    return np.array(out)


@pytest.mark.parametrize(
    "heading, course, step",
    [
        (0.0, 0.0, [0, 0, 1]),  # facing east, driving east: forward (camera z)
        (math.pi / 2, math.pi / 2, [0, 0, 1]),  # facing north, driving north: forward
        (math.pi / 2, 0.0, [1, 0, 0]),  # facing north, moving east: to the right (camera x)
        (0.0, math.pi, [0, 0, -1]),  # facing east, moving west: backwards
    ],
)
def test_a_straight_drive_moves_one_metre_per_frame_along_the_right_axis(heading, course, step):
    """With the devkit's axes (IMU = velodyne, velodyne -> camera an axis swap, no
    rectification) camera k sits k metres along ``step`` in camera 0's frame, unturned."""
    calib = read_calib_text(
        f"P2: {P2_LINE}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
        f"Tr_velo_to_cam: {' '.join(map(str, VELO_TO_CAM_AXES.ravel()))}\n"
        "Tr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n"
    )
    packets = straight_drive(heading, course)
    poses = kitti_oxts.camera_poses(packets, calib)
    k = np.arange(len(packets))[:, None]
    np.testing.assert_allclose(poses[:, :, 3], k * np.array(step, float), atol=1e-6)
    np.testing.assert_allclose(
        poses[:, :, :3], np.broadcast_to(np.eye(3), (len(k), 3, 3)), atol=1e-12
    )
    T = homogeneous(VELO_TO_CAM_AXES)
    np.testing.assert_allclose(poses, devkit_poses(packets.tolist(), T), rtol=0, atol=1e-9)


def test_climbing_one_metre_per_frame_moves_the_camera_up():
    packets = straight_drive(0.0, 0.0)
    packets[:, 2] += np.arange(len(packets))  # altitude +1 m per frame
    calib = read_calib_text(
        f"P2: {P2_LINE}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
        f"Tr_velo_to_cam: {' '.join(map(str, VELO_TO_CAM_AXES.ravel()))}\n"
        "Tr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n"
    )
    t = kitti_oxts.camera_poses(packets, calib)[:, :, 3]
    k = np.arange(len(packets))
    np.testing.assert_allclose(t, np.stack([0 * k, -k, k], 1), atol=1e-6)  # y is down


def read_calib_text(text: str):
    from gac_jax.data.kitti_calib import parse_calib

    return parse_calib(text, "hand.txt")


def test_tracking_layout_oxts_become_the_sequences_poses(tmp_path):
    """``oxts/SSSS.txt`` (line k: frame k) through the sequence's tracking calibration: the
    layout's frames carry the devkit's poses, and ``--track`` finds them (poses/ wins)."""
    packets = straight_drive(math.pi / 2, 0.0, frames=3)
    lines = [" ".join(repr(float(v)) for v in p) for p in packets]
    images = tracking_root(tmp_path / "t", TRACKING_LINES, frames=3, oxts=lines)
    layout = KittiTrackingLayout(tmp_path / "t")
    want = devkit_poses(packets.tolist(), homogeneous(VELO_TO_CAM_AXES))
    got = np.array([f.pose for f in layout.frames("0000")])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[2, :, 3], [2, 0, 0], atol=1e-6)  # facing north, moved east
    source = open_sequence(images, tmp_path, "--track")
    log = []
    poses = predict_track.stream_poses(source_args(tmp_path, images), source, log.append)
    np.testing.assert_allclose(poses, want, rtol=0, atol=1e-9)
    assert log == [predict_track.oxts_line(layout.oxts("0000"))]
    (tmp_path / "t" / "training" / "poses").mkdir()
    (layout.poses("0000")).write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    log.clear()
    poses = predict_track.stream_poses(source_args(tmp_path, images), source, log.append)
    assert log == [f"poses: {layout.poses('0000')}"] and np.all(poses[:, :, 3] == 0)


@pytest.mark.parametrize(
    "line, problem",
    [
        ("49.0 8.4 110", ":1: an OXTS packet has 30 numbers, found 3"),
        (oxts_line().replace("110.0", "x", 1), ":1: alt: non-numeric value 'x'"),
        (oxts_line(lat=95.0), ":1: lat: 95 is not a latitude"),
        (oxts_line(roll=math.nan), ":1: roll: non-finite value"),
        ("", ": no OXTS packet in this file"),
    ],
)
def test_a_bad_oxts_packet_is_named(tmp_path, line, problem):
    path = tmp_path / "0000000000.txt"
    path.write_text(line + "\n")
    with pytest.raises(KittiFormatError) as e:
        kitti_oxts.read_oxts(path)
    assert str(e.value) == f"{path}{problem}"


# --- timestamps.txt: the frames' times ---------------------------------------------------------

STAMPS = (
    "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.067700160\n2011-09-26 13:02:26.171034885\n"
)


def test_timestamps_parse_to_nanoseconds():
    ns = kitti_raw.parse_timestamps(STAMPS + "\n")
    assert ns.dtype == np.int64 and len(ns) == 3
    assert ns[0] % 10**9 == 964389445
    assert ns[0] // 10**9 == 1317042145  # 2011-09-26 13:02:25 UTC
    assert list(np.diff(ns)) == [103310715, 103334725]
    np.testing.assert_allclose(
        kitti_raw.frame_times(ns, [1, 2]), [0.0, 0.103334725], rtol=0, atol=1e-12
    )


@pytest.mark.parametrize(
    "text, problem",
    [
        (STAMPS.replace("13:02:26.0677", "13:02:26,0677"), ":2: expected 'YYYY-MM-DD HH:MM:SS"),
        (
            STAMPS.replace("13:02:26.171", "13:02:25.171"),
            ":3: frame 2's time is not after frame 1's",
        ),
        (STAMPS.replace("-09-26 13:02:26.067", "-13-26 13:02:26.067"), ":2: not a date and time"),
    ],
)
def test_bad_timestamps_are_named(tmp_path, text, problem):
    path = tmp_path / "timestamps.txt"
    path.write_text(text)
    with pytest.raises(KittiFormatError) as e:
        kitti_raw.frame_times(kitti_raw.read_timestamps(path), [0, 1, 2], path)
    assert str(e.value).startswith(f"{path}{problem}")


def test_a_raw_drives_timestamps_are_the_trackers_frame_times(tmp_path):
    """``image_02/timestamps.txt`` gives each frame its time; the tracking stage hands the
    tracker those (not index / fps)."""
    images = raw_drive(tmp_path / "raw", frames=3)
    (images.parent / "timestamps.txt").write_text(STAMPS)
    source = open_sequence(images, tmp_path)
    assert source.found[-1] == f"frame times: {images.parent / 'timestamps.txt'}"
    frames = [source.read() for _ in range(3)]
    np.testing.assert_allclose([f.time for f in frames], [0, 0.103310715, 0.20664544], atol=1e-12)

    class Recorder:
        def __init__(self):
            self.times = []

        def update(self, detections, pose=None, timestamp=None, plane=None):
            self.times.append(timestamp)

    recorder = Recorder()
    stage = TrackingStage(recorder, fps=10.0)
    for f in frames:
        stage.update(f, [])
    stage.update(Frame(3, "x", frames[0].image, source.P2, None, 0.0), [])  # no time: index/fps
    np.testing.assert_allclose(recorder.times, [0, 0.103310715, 0.20664544, 0.3], atol=1e-12)


# --- the whole command on a raw drive --------------------------------------------------------


def test_track_on_a_raw_drive_uses_its_calibration_oxts_and_times(
    tiny_detect3d_workdir, tmp_path, capsys
):
    """``--sequence DRIVE --track`` with nothing else: the day's calibration, the drive's OXTS
    poses and its timestamps are found, each said in a line, and the run writes its tracks."""
    images = raw_drive(tmp_path / "raw", frames=2, oxts=[oxts_line(), oxts_line(lon=8.40001)])
    (images.parent / "timestamps.txt").write_text(STAMPS)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--sequence", images.parents[1], "--track"]
    code = predict.main([str(a) for a in [*argv, "--out", out, "--no-video"]])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    day = images.parents[2]
    for line in (
        f"calibration: {day / 'calib_cam_to_cam.txt'} (KITTI raw layout)",
        f"frame times: {images.parent / 'timestamps.txt'}",
        predict_track.oxts_line(images.parents[1] / "oxts" / "data"),
    ):
        assert line in stdout.splitlines(), stdout
    assert (out / "tracking" / "0000.txt").is_file()
