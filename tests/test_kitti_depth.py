"""KITTI-depth layout helpers: raw calibration parsing, frame listing order, selection naming."""

from __future__ import annotations

import re

import numpy as np
import pytest

from gac_jax.data import kitti_depth
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti_calib import parse_calib

CALIB = """calib_time: 09-Jan-2012 13:57:47
S_rect_02: 1.242000e+03 3.750000e+02
P_rect_02: 7.2e+02 0 6.0e+02 4.4e+01 0 7.2e+02 1.7e+02 2.1e-01 0 0 1 2.7e-03
K_02: 1 0 0 0 1 0 0 0 1
P_rect_03: 7.2e+02 0 6.0e+02 -3.3e+02 0 7.2e+02 1.7e+02 2.1e+00 0 0 1 2.7e-03
"""


def test_parse_cam_to_cam_by_hand():
    calib = parse_calib(CALIB)
    np.testing.assert_array_equal(
        calib.P2, [[720, 0, 600, 44], [0, 720, 170, 0.21], [0, 0, 1, 2.7e-3]]
    )
    assert calib.P3[0, 3] == -330 and calib.image_sizes == {2: (375, 1242)}
    assert calib.kind == "raw" and calib.P0 is None


@pytest.mark.parametrize(
    "text, line, problem",
    [
        (CALIB.replace("4.4e+01 ", ""), 3, "P_rect_02 needs 12 numbers, found 11"),
        (CALIB.replace("1.7e+02 2.1e+00", "1.7e+02 x"), 5, "non-numeric value 'x'"),
        (CALIB.replace("3.750000e+02", "-3"), 2, "two positive integers"),
        ("calib_time 09-Jan-2012\n", 1, "expected 'KEY: v1 v2 ...'"),
        ("S_rect_02: 1242 375\n", None, "calibration has no P_rect_02"),
        (CALIB.replace("7.2e+02 0 6.0e+02 4.4e+01", "0 0 0 4.4e+01"), 3, "singular"),
    ],
)
def test_parse_cam_to_cam_errors(text, line, problem):
    where = "calib.txt" + (f":{line}" if line else "")
    with pytest.raises(KittiFormatError, match=re.escape(where) + ": .*" + re.escape(problem)):
        parse_calib(text, "calib.txt")


def test_projection_for_missing_camera():
    calib = parse_calib(CALIB.replace("P_rect_03", "P_other_03"), "x.txt")
    with pytest.raises(KittiFormatError, match="^x.txt: calibration has no P_rect_03"):
        calib.projection(3)


def test_drive_date():
    assert kitti_depth.drive_date("2011_09_26_drive_0001_sync") == "2011_09_26"
    with pytest.raises(ValueError, match="not a KITTI raw drive name"):
        kitti_depth.drive_date("2011_09_26_drive_1_sync")


def _touch(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")


def test_frames_are_camera_major_and_need_gt_and_raw(tmp_path):
    lay = kitti_depth.KittiDepthLayout(tmp_path)
    drives = ["2011_09_26_drive_0002_sync", "2011_09_28_drive_0001_sync"]
    for drive in drives:
        for cam in (2, 3):
            for frame in ("0000000007", "0000000005"):
                f = kitti_depth.DepthFrame(drive, frame, cam)
                _touch(lay.groundtruth("train", f))
                if not (cam == 3 and frame == "0000000007"):
                    _touch(lay.raw_image(f))  # no raw image: frame does not count
    _touch(lay.split_dir("train") / drives[0] / "proj_depth/groundtruth/image_02/notes.png")
    (lay.split_dir("train") / "README").mkdir()
    frames = lay.frames("train")
    got = [(f.camera, f.drive[:10], f.frame[-1]) for f in frames]
    assert got == [
        (2, "2011_09_26", "5"),
        (2, "2011_09_26", "7"),
        (2, "2011_09_28", "5"),
        (2, "2011_09_28", "7"),
        (3, "2011_09_26", "5"),
        (3, "2011_09_28", "5"),
    ]
    assert frames[0].frame_id == "2011_09_26_drive_0002_sync/0000000005"
    assert lay.calib(drives[1]) == tmp_path / "raw" / "2011_09_28" / "calib_cam_to_cam.txt"
    with pytest.raises(ValueError, match="camera must be 2 or 3"):
        lay.frames("train", (1,))


def test_selection_listing(tmp_path):
    name = "2011_09_26_drive_0002_sync_image_0000000005_image_03"
    _touch(tmp_path / "image" / f"{name}.png")
    (tmp_path / "intrinsics").mkdir()
    (tmp_path / "intrinsics" / f"{name}.txt").write_text("721 0 609 0 721 172 0 0 1 0 0 0\n")
    items = kitti_depth.list_selection(tmp_path)  # test set: no groundtruth_depth/ folder
    assert [(i.name, i.groundtruth) for i in items] == [(name, None)]
    np.testing.assert_array_equal(
        kitti_depth.read_selection_intrinsics(items[0].intrinsics),
        [[721, 0, 609], [0, 721, 172], [0, 0, 1]],
    )
    (tmp_path / "groundtruth_depth").mkdir()
    gt = tmp_path / "groundtruth_depth" / f"{name.replace('_image_', '_groundtruth_depth_', 1)}.png"
    with pytest.raises(KittiFormatError, match="^" + re.escape(str(gt))):
        kitti_depth.list_selection(tmp_path)
    _touch(gt)
    assert kitti_depth.list_selection(tmp_path)[0].groundtruth == gt
    assert gt.name == "2011_09_26_drive_0002_sync_groundtruth_depth_0000000005_image_03.png"
