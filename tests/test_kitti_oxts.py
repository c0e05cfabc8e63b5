"""KITTI's OXTS packets and timestamps: OXTS packets turned into camera poses as the KITTI
devkit's ``convertOxtsToPose`` does it (against an independent float64 transcription, on the
real packet of ``../shared``'s raw frame and on hand-made straight drives of 1 m per frame),
for raw drives and tracking sequences; ``timestamps.txt`` as the tracker's frame times; and
``--sequence DRIVE --track`` on a raw drive finding all of it by itself.
"""

from __future__ import annotations

import math
import os
import shutil

import numpy as np
import pytest
from kitti_format_cases import (
    AXES_CALIB,
    REAL_OXTS,
    SHARED_DAY,
    STAMPS,
    TRACKING_LINES,
    VELO_TO_CAM_AXES,
    file_numbers,
    homogeneous,
    needs_shared,
    open_sequence,
    oxts_line,
    raw_drive,
    rigid,
    source_args,
    tracking_root,
)

from gac_jax.cli import predict, predict_track
from gac_jax.data import kitti_oxts, kitti_raw
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti_calib import parse_calib
from gac_jax.data.kitti_tracking import KittiTrackingLayout
from gac_jax.streams.sources import Frame
from gac_jax.streams.tracking import TrackingStage

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
    where, poses = predict_track.stream_poses(source_args(tmp_path, images), source, lines.append)
    assert where == os.fspath(oxts)
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
    calib = parse_calib(AXES_CALIB, "axes.txt")
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
    calib = parse_calib(AXES_CALIB, "axes.txt")
    t = kitti_oxts.camera_poses(packets, calib)[:, :, 3]
    k = np.arange(len(packets))
    np.testing.assert_allclose(t, np.stack([0 * k, -k, k], 1), atol=1e-6)  # y is down


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
    _, poses = predict_track.stream_poses(source_args(tmp_path, images), source, log.append)
    np.testing.assert_allclose(poses, want, rtol=0, atol=1e-9)
    assert log == [predict_track.oxts_line(layout.oxts("0000"))]
    (tmp_path / "t" / "training" / "poses").mkdir()
    (layout.poses("0000")).write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    log.clear()
    _, poses = predict_track.stream_poses(source_args(tmp_path, images), source, log.append)
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
