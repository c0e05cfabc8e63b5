"""Inputs shared by the tests of KITTI's own formats (test_kitti_calib, test_kitti_oxts):
the real files' paths, the test's own reading of a calibration file, and raw drive folders and
tracking roots made in a temporary folder."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import KITTI_SAMPLES, VENDORED_KITTI

from gac_jax.cli import predict, stream_start
from gac_jax.data.files import write_png
from gac_jax.streams.sources import SequenceSource

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


def open_sequence(folder: Path, workdir: Path, *extra) -> SequenceSource:
    args = predict.build_parser().parse_args(
        ["--workdir", str(workdir), "--sequence", str(folder), *map(str, extra)]
    )
    return stream_start.open_source(args)


def homogeneous(m: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[: m.shape[0], : m.shape[1]] = m
    return out


def source_args(workdir: Path, folder: Path, *extra):
    return predict.build_parser().parse_args(
        ["--workdir", str(workdir), "--sequence", str(folder), "--track", *map(str, extra)]
    )


# The devkit's axes alone: IMU = velodyne, velodyne -> camera an axis swap, no rectification.
AXES_CALIB = (
    f"P2: {P2_LINE}\nR0_rect: 1 0 0 0 1 0 0 0 1\n"
    f"Tr_velo_to_cam: {' '.join(map(str, VELO_TO_CAM_AXES.ravel()))}\n"
    "Tr_imu_to_velo: 1 0 0 0 0 1 0 0 0 0 1 0\n"
)

STAMPS = (
    "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.067700160\n2011-09-26 13:02:26.171034885\n"
)
