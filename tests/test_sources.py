"""Folder readers on the real KITTI frames, and their errors on bad input."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.data import kitti_depth
from gac_jax.data.files import KittiFormatError, read_depth_png, write_depth_png, write_png
from gac_jax.data.kitti import read_calib, read_label, read_split, write_split
from gac_jax.data.sources import (
    KittiDepthSelectionSource,
    KittiDepthSource,
    KittiObjectSource,
    open_depth_source,
    open_object_source,
)

DRIVE = "2011_09_26_drive_0001_sync"
FRAME = "0000000005"


def copy_object_root(src: Path, dst: Path, ids: list[str], right: bool = False) -> Path:
    """A KITTI object root with ``ids`` (split ``train``); ``right`` copies image_2 as image_3."""
    for sub in ("image_2", "calib", "label_2") + (("image_3",) if right else ()):
        (dst / "training" / sub).mkdir(parents=True, exist_ok=True)
    for i in ids:
        shutil.copy(src / "training" / "image_2" / f"{i}.png", dst / "training" / "image_2")
        shutil.copy(src / "training" / "calib" / f"{i}.txt", dst / "training" / "calib")
        shutil.copy(src / "training" / "label_2" / f"{i}.txt", dst / "training" / "label_2")
        if right:
            shutil.copy(
                src / "training" / "image_2" / f"{i}.png",
                dst / "training" / "image_3" / f"{i}.png",
            )
    write_split(dst / "ImageSets" / "train.txt", ids)
    return dst


def copy_depth_root(src: Path, dst: Path) -> Path:
    shutil.copytree(src / "data_depth_annotated", dst / "data_depth_annotated")
    day = dst / "raw" / "2011_09_26"
    for cam in (2, 3):
        d = day / DRIVE / f"image_0{cam}" / "data"
        d.mkdir(parents=True)
        shutil.copy(
            src / "raw" / "2011_09_26" / DRIVE / f"image_0{cam}" / "data" / f"{FRAME}.png", d
        )
    shutil.copy(src / "raw" / "2011_09_26" / "calib_cam_to_cam.txt", day)
    return dst


def raises_naming(path: Path | str, line: int | None = None):
    """pytest.raises(KittiFormatError) whose message starts with ``path`` (and ``:line``)."""
    where = str(path) + (f":{line}" if line is not None else "")
    return pytest.raises(KittiFormatError, match="^" + re.escape(where) + ":")


# ----------------------------------------------------------------------------- real frames


def test_labels_parse_and_match_projected_3d_boxes(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    assert len(src) == 4  # the vendored frames 000000, 000001, 000010, 000036
    errors, counts = [], {}
    for i in range(len(src)):
        s = src[i]
        obj = s["objects"]
        for t in obj.type:
            counts[t] = counts.get(t, 0) + 1
        clean = obj.select((obj.type != "DontCare") & (obj.truncated == 0) & (obj.occluded == 0))
        corners = geometry.box3d_corners(clean.location, clean.dimensions, clean.rotation_y)
        boxes = geometry.box2d_from_corners(corners, s["P2"], image_size=s["image"].shape[:2])
        errors.append(np.abs(boxes - clean.bbox).ravel())
    err = np.concatenate(errors)
    print(
        f"\nprojected 3D box vs labelled 2D box over {err.size // 4} clean objects: "
        f"median {np.median(err):.3f} px, max {err.max():.2f} px"
    )
    assert counts == {
        "Car": 16,
        "DontCare": 10,
        "Pedestrian": 2,
        "Cyclist": 1,
        "Truck": 1,
    }
    assert np.median(err) < 2.0


def test_object_sample_fields(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    s = src[0]
    assert s["frame_id"] == "000000" and s["camera"] == 2
    assert s["image"].shape == (370, 1224, 3) and s["image"].dtype == np.uint8
    assert s["original_size"] == (370, 1224)
    np.testing.assert_array_equal(s["image_transform"], np.eye(3))
    calib = read_calib(kitti_object_root / "training" / "calib" / "000000.txt")
    np.testing.assert_array_equal(s["P2"], calib.P2)
    assert list(s["objects"].type) == ["Pedestrian"]
    assert src.frame_ids == read_split(kitti_object_root / "ImageSets" / "labeled.txt")
    with pytest.raises(IndexError):
        src[len(src)]
    assert isinstance(open_object_source(kitti_object_root, "labeled"), KittiObjectSource)


def test_right_image_views(kitti_object_root, tmp_path):
    root = copy_object_root(kitti_object_root, tmp_path, ["000001", "000036"], right=True)
    src = KittiObjectSource(root, "train", use_right_image=True)
    assert len(src) == 4
    left, right = src[0], src[2]
    assert (left["camera"], right["camera"]) == (2, 3)
    assert left["frame_id"] == right["frame_id"] == "000001"
    calib = read_calib(root / "training" / "calib" / "000001.txt")
    np.testing.assert_array_equal(right["P2"], calib.P3)
    obj = right["objects"]
    labels = read_label(root / "training" / "label_2" / "000001.txt")
    real = labels.select(labels.type != "DontCare")
    assert list(obj.type) == list(real.type)  # DontCare has no 3D box: dropped
    np.testing.assert_array_equal(obj.location, real.location)
    corners = geometry.box3d_corners(real.location, real.dimensions, real.rotation_y)
    expect = geometry.box2d_from_corners(corners, calib.P3, image_size=right["image"].shape[:2])
    np.testing.assert_allclose(obj.bbox, expect)
    # The right camera sits 0.54 m to the right: boxes shift left by about fx * B / z.
    shift = (real.bbox[:, 0] - obj.bbox[:, 0])[real.truncated == 0]
    np.testing.assert_allclose(
        shift, 707.05 * 0.537 / real.location[real.truncated == 0, 2], rtol=0.3
    )
    np.testing.assert_allclose(
        obj.alpha, geometry.alpha_from_rotation_y(real.rotation_y, real.location, calib.P3)
    )


def test_real_right_image_unlabeled(kitti_samples_full, tmp_path):
    """000107 is the one sample frame with a real image_3 (unlabeled subset of ../shared)."""
    src_root = kitti_samples_full / "object"
    with raises_naming(src_root / "ImageSets" / "unlabeled.txt", 1):
        KittiObjectSource(src_root, "unlabeled", True, subset="unlabeled", with_labels=False)
    for sub in ("image_2", "image_3", "calib"):
        (tmp_path / "unlabeled" / sub).mkdir(parents=True)
        ext = "txt" if sub == "calib" else "png"
        shutil.copy(src_root / "unlabeled" / sub / f"000107.{ext}", tmp_path / "unlabeled" / sub)
    write_split(tmp_path / "ImageSets" / "one.txt", ["000107"])
    src = KittiObjectSource(tmp_path, "one", True, subset="unlabeled", with_labels=False)
    left, right = src[0], src[1]
    assert "objects" not in right and right["camera"] == 3
    assert left["image"].shape == right["image"].shape
    np.testing.assert_array_equal(
        right["P2"], read_calib(tmp_path / "unlabeled/calib/000107.txt").P3
    )


def test_depth_source(kitti_samples):
    root = kitti_samples / "depth"
    src = KittiDepthSource(root, "train")
    assert len(src) == 2 and isinstance(open_depth_source(root), KittiDepthSource)
    calib = read_calib(root / "raw" / "2011_09_26" / "calib_cam_to_cam.txt")
    assert calib.image_sizes[2] == (375, 1242)
    for i, cam in enumerate((2, 3)):
        s = src[i]
        assert s["frame_id"] == f"{DRIVE}/{FRAME}" and s["camera"] == cam
        np.testing.assert_array_equal(s["P2"], calib.projection(cam))
        assert s["depth"].shape == s["image"].shape[:2] == (375, 1242)
        valid = s["depth"] > 0
        assert 0.15 < valid.mean() < 0.25 and 80 < s["depth"].max() < 86
    # P_rect_02 by hand from the file.
    np.testing.assert_allclose(
        calib.P2[0], [7.215377e02, 0.0, 6.095593e02, 4.485728e01], rtol=0, atol=1e-9
    )
    assert len(KittiDepthSource(root, "train", cameras=(3,))) == 1


def test_depth_frame_list(kitti_samples, tmp_path):
    root = kitti_samples / "depth"
    frames = [kitti_depth.DepthFrame(DRIVE, FRAME, 3)]
    kitti_depth.write_frame_list(tmp_path / "list.txt", frames)
    assert [f for f, _ in kitti_depth.read_frame_list(tmp_path / "list.txt")] == frames
    src = KittiDepthSource(root, "train", frame_list=tmp_path / "list.txt")
    assert len(src) == 1 and src[0]["camera"] == 3
    (tmp_path / "bad.txt").write_text(f"{DRIVE} {FRAME} 2\n{DRIVE} 0000000006 2\n")
    with raises_naming(tmp_path / "bad.txt", 2):
        KittiDepthSource(root, "train", frame_list=tmp_path / "bad.txt")
    (tmp_path / "bad2.txt").write_text(f"{DRIVE} 5 2\n")
    with raises_naming(tmp_path / "bad2.txt", 1):
        kitti_depth.read_frame_list(tmp_path / "bad2.txt")


def make_selection(depth_root: Path, dst: Path) -> Path:
    """A ``val_selection_cropped`` folder made from the real frame (352 x 1216 crop)."""
    sample = KittiDepthSource(depth_root, "train", cameras=(2,))[0]
    h = sample["image"].shape[0]
    name = f"{DRIVE}_image_{FRAME}_image_02"
    write_png(dst / "image" / f"{name}.png", sample["image"][h - 352 :, :1216])
    gt = f"{DRIVE}_groundtruth_depth_{FRAME}_image_02.png"
    write_depth_png(dst / "groundtruth_depth" / gt, sample["depth"][h - 352 :, :1216])
    K = sample["P2"][:, :3].copy()
    K[1, 2] -= h - 352
    (dst / "intrinsics").mkdir(parents=True)
    (dst / "intrinsics" / f"{name}.txt").write_text(" ".join(f"{v:.6f}" for v in K.ravel()) + "\n")
    return dst


def test_depth_selection_source(kitti_samples, tmp_path):
    sel = make_selection(kitti_samples / "depth", tmp_path / "val_selection_cropped")
    src = KittiDepthSelectionSource(sel)
    assert len(src) == 1
    s = src[0]
    assert s["image"].shape == (352, 1216, 3) and s["camera"] == 2
    full = KittiDepthSource(kitti_samples / "depth", "train", cameras=(2,))[0]
    np.testing.assert_array_equal(s["depth"], full["depth"][375 - 352 :, :1216])
    np.testing.assert_allclose(
        s["P2"][:, :3], full["P2"][:, :3] - [[0, 0, 0], [0, 0, 23], [0, 0, 0]]
    )
    np.testing.assert_array_equal(s["P2"][:, 3], 0.0)


# ----------------------------------------------------------------------------- bad input


@pytest.fixture
def object_root(kitti_object_root, tmp_path):
    return copy_object_root(kitti_object_root, tmp_path / "obj", ["000001", "000036"])


def test_bad_label_lines(object_root):
    label = object_root / "training" / "label_2" / "000001.txt"
    lines = label.read_text().splitlines()
    label.write_text("\n".join([lines[0], " ".join(lines[1].split()[:14])] + lines[2:]) + "\n")
    src = KittiObjectSource(object_root, "train")
    with raises_naming(label, 2) as e:
        src[0]
    assert "columns" in str(e.value)
    fields = lines[2].split()
    fields[11] = "4.5x"
    label.write_text("\n".join(lines[:2] + [" ".join(fields)] + lines[3:]) + "\n")
    with raises_naming(label, 3) as e:
        src[0]
    assert "non-numeric" in str(e.value) and "4.5x" in str(e.value)


def test_calib_without_p2(object_root):
    calib = object_root / "training" / "calib" / "000036.txt"
    calib.write_text("\n".join(x for x in calib.read_text().splitlines() if not x.startswith("P2")))
    with raises_naming(calib) as e:
        KittiObjectSource(object_root, "train")[1]
    assert "P2" in str(e.value)


def test_missing_image(object_root):
    image = object_root / "training" / "image_2" / "000036.png"
    src = KittiObjectSource(object_root, "train")
    image.unlink()
    with raises_naming(image) as e:  # vanished after listing
        src[1]
    assert "not found" in str(e.value)
    with raises_naming(object_root / "ImageSets" / "train.txt", 2) as e:
        KittiObjectSource(object_root, "train")
    assert "000036" in str(e.value) and str(image) in str(e.value)


def test_corrupt_png(object_root):
    image = object_root / "training" / "image_2" / "000001.png"
    image.write_bytes(image.read_bytes()[:200])
    with raises_naming(image):
        KittiObjectSource(object_root, "train")[0]


def test_split_naming_missing_frame(object_root):
    split = object_root / "ImageSets" / "train.txt"
    split.write_text("000001\n\n000999\n")
    with raises_naming(split, 3) as e:
        KittiObjectSource(object_root, "train")
    assert "000999" in str(e.value)
    split.write_text("000001\nframe2\n")
    with raises_naming(split, 2):
        KittiObjectSource(object_root, "train")


@pytest.fixture
def depth_root(kitti_samples, tmp_path):
    return copy_depth_root(kitti_samples / "depth", tmp_path / "depth")


def test_wrong_size_and_corrupt_depth_png(depth_root):
    lay = kitti_depth.KittiDepthLayout(depth_root)
    frame = kitti_depth.DepthFrame(DRIVE, FRAME, 2)
    gt = lay.groundtruth("train", frame)
    depth = read_depth_png(gt)
    write_depth_png(gt, depth[:, :-2])
    with raises_naming(gt) as e:
        KittiDepthSource(depth_root, "train")[0]
    assert "375x1240" in str(e.value) and "375x1242" in str(e.value)
    write_png(gt, np.zeros((375, 1242), np.uint8))
    with raises_naming(gt) as e:
        KittiDepthSource(depth_root, "train")[0]
    assert "16-bit" in str(e.value)
    gt.write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with raises_naming(gt):
        KittiDepthSource(depth_root, "train")[0]


def test_bad_raw_calib(depth_root):
    calib = depth_root / "raw" / "2011_09_26" / "calib_cam_to_cam.txt"
    lines = calib.read_text().splitlines()
    calib.write_text("\n".join(x for x in lines if not x.startswith("P_rect_02")) + "\n")
    src = KittiDepthSource(depth_root, "train")
    with raises_naming(calib) as e:
        src[0]
    assert "P_rect_02" in str(e.value)
    assert src[1]["camera"] == 3  # camera 3 is still readable
    n = next(i for i, x in enumerate(lines, 1) if x.startswith("P_rect_03"))
    lines[n - 1] = lines[n - 1].replace("7.215377e+02", "seven", 1)
    calib.write_text("\n".join(lines) + "\n")
    with raises_naming(calib, n) as e:
        KittiDepthSource(depth_root, "train")[1]
    assert "seven" in str(e.value)
    calib.unlink()
    with raises_naming(calib):
        KittiDepthSource(depth_root, "train")[0]


def test_bad_selection(kitti_samples, tmp_path):
    sel = make_selection(kitti_samples / "depth", tmp_path / "sel")
    intr = next((sel / "intrinsics").iterdir())
    intr.write_text("721.5 0 609.6 0 721.5\n")
    with raises_naming(intr, 1):
        KittiDepthSelectionSource(sel)[0]
    intr.unlink()
    with raises_naming(intr):
        KittiDepthSelectionSource(sel)
    with raises_naming(tmp_path / "nothing" / "image"):
        KittiDepthSelectionSource(tmp_path / "nothing")


def test_missing_depth_split(depth_root):
    with raises_naming(depth_root / "data_depth_annotated" / "val"):
        KittiDepthSource(depth_root, "val")
