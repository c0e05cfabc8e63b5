"""Prepared TFDS datasets (ArrayRecord, no TensorFlow) give the folder readers' samples."""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from gac_jax.data import tfds_builders
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti import KittiObjects, read_split, write_plane, write_split
from gac_jax.data.sources import (
    KittiDepthSource,
    KittiObjectSource,
    TfdsDepthSource,
    TfdsObjectSource,
    find_prepared,
    open_depth_source,
    open_object_source,
)

VAL = ["000010", "000001", "000036"]  # not sorted: records must keep split-file order


def copy_object_root(src: Path, dst: Path, ids: list[str], right: bool = False) -> Path:
    """A KITTI object root with frames ``ids`` (split ``train``); ``right``: image_3 := image_2."""
    subs = {"image_2": "png", "calib": "txt", "label_2": "txt"}
    for sub, ext in subs.items():
        (dst / "training" / sub).mkdir(parents=True)
        for i in ids:
            shutil.copy(src / "training" / sub / f"{i}.{ext}", dst / "training" / sub)
    if right:
        shutil.copytree(dst / "training" / "image_2", dst / "training" / "image_3")
    write_split(dst / "ImageSets" / "train.txt", ids)
    return dst


def raises_naming(path: Path | str, line: int | None = None):
    where = str(path) + (f":{line}" if line is not None else "")
    return pytest.raises(KittiFormatError, match="^" + re.escape(where) + ":")


@pytest.fixture(scope="module")
def prepared(kitti_object_root, kitti_samples, tmp_path_factory):
    base = tmp_path_factory.mktemp("tfds")
    ids = read_split(kitti_object_root / "ImageSets" / "labeled.txt")
    root = copy_object_root(kitti_object_root, base / "kitti", ids, right=True)
    write_split(root / "ImageSets" / "val.txt", VAL)
    write_plane(root / "training" / "planes" / f"{VAL[0]}.txt", [0.007, -0.9998, -0.0198, 1.68])
    out = base / "prepared"
    obj = tfds_builders.prepare("object", root, out)
    depth = tfds_builders.prepare("depth", kitti_samples / "depth", out)
    return {"root": root, "out": out, "object": obj, "depth": depth}


def assert_same_sample(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        if key == "objects":
            for f in dataclasses.fields(KittiObjects):
                np.testing.assert_array_equal(getattr(a[key], f.name), getattr(b[key], f.name))
        elif isinstance(a[key], np.ndarray):
            assert a[key].dtype == b[key].dtype
            np.testing.assert_array_equal(a[key], b[key])
        else:
            assert a[key] == b[key], key


def test_tensorflow_is_not_needed(prepared):
    if importlib.util.find_spec("tensorflow") is None:
        with pytest.raises(ImportError):
            import tensorflow  # noqa: F401
    src = TfdsObjectSource(prepared["object"], "train")
    src[0]
    assert "tensorflow" not in sys.modules


@pytest.mark.parametrize("split", ["train", "val"])
def test_object_round_trip(prepared, split):
    folder = KittiObjectSource(prepared["root"], split, use_right_image=True)
    tfds_src = TfdsObjectSource(prepared["out"], split, use_right_image=True)
    assert (
        len(tfds_src)
        == len(folder)
        == 2 * len(read_split(prepared["root"] / f"ImageSets/{split}.txt"))
    )
    for i in range(len(folder)):
        assert_same_sample(tfds_src[i], folder[i])
    if split == "val":
        assert [tfds_src[i]["frame_id"] for i in range(3)] == VAL
        assert "plane" in tfds_src[0] and "plane" not in tfds_src[1]  # read where present


def test_depth_round_trip(prepared, kitti_samples):
    for cams in [(2, 3), (3,)]:
        folder = KittiDepthSource(kitti_samples / "depth", "train", cams)
        tfds_src = TfdsDepthSource(prepared["depth"], "train", cams)
        assert len(tfds_src) == len(folder) == len(cams)
        for i in range(len(folder)):
            assert_same_sample(tfds_src[i], folder[i])


def test_open_picks_prepared_reader(prepared):
    for path in (prepared["out"], prepared["object"], prepared["object"].parent):
        assert isinstance(open_object_source(path, "val"), TfdsObjectSource)
    assert isinstance(open_object_source(prepared["root"], "val"), KittiObjectSource)
    assert isinstance(open_depth_source(prepared["out"]), TfdsDepthSource)
    assert find_prepared(prepared["root"], "gac_kitti_object") is None
    with raises_naming(prepared["object"]):
        TfdsObjectSource(prepared["object"], "test")
    with raises_naming(prepared["root"]):
        TfdsObjectSource(prepared["root"], "val")
    with raises_naming(prepared["depth"]):
        TfdsObjectSource(prepared["depth"], "train")  # a depth dataset is not an object dataset


def test_unlabeled_and_testing_frames(prepared, tmp_path):
    root = prepared["root"]
    testing = tmp_path / "kitti"
    for sub in ("image_2", "calib"):
        (testing / "testing" / sub).mkdir(parents=True)
        for f in (root / "training" / sub).glob("00000[01].*"):
            (testing / "testing" / sub / f.name).write_bytes(f.read_bytes())
    out = tfds_builders.prepare("object", testing, tmp_path / "out", subset="testing")
    src = TfdsObjectSource(out, "frames", with_labels=False)
    folder = KittiObjectSource(testing, None, subset="testing", with_labels=False)
    assert len(src) == 2
    for i in range(2):
        assert_same_sample(src[i], folder[i])
    with pytest.raises(KittiFormatError, match="no label"):
        TfdsObjectSource(out, "frames")[0]
    with pytest.raises(KittiFormatError, match="no image"):
        TfdsObjectSource(out, "frames", use_right_image=True, with_labels=False)[2]


def test_builder_rejects_bad_files(prepared, tmp_path, capsys):
    root = copy_object_root(prepared["root"], tmp_path / "kitti", ["000001", "000036"])
    label = root / "training" / "label_2" / "000036.txt"
    label.write_text("Car 0.0 0 1.0 1 2 3 4 1.5 1.6 3.9 1.0 1.6 twenty 0.1\n")
    with raises_naming(label, 1):
        tfds_builders.prepare("object", root, tmp_path / "out")
    assert tfds_builders.main(["object", "--src", str(root), "--out", str(tmp_path / "o2")]) == 1
    assert str(label) in capsys.readouterr().err
    label.unlink()
    plane = root / "training" / "planes" / "000001.txt"
    plane.parent.mkdir()
    plane.write_text("1\n")  # one number: not a plane
    with raises_naming(plane, 1):
        tfds_builders.prepare("object", root, tmp_path / "out4")
    plane.unlink()
    (root / "training" / "image_2" / "000001.png").write_bytes(b"GIF89a")
    with raises_naming(root / "training" / "image_2" / "000001.png"):
        tfds_builders.prepare("object", root, tmp_path / "out3")


def test_cli_writes_and_refuses_to_overwrite(prepared, kitti_samples, tmp_path, capsys):
    args = [
        "depth",
        "--src",
        str(kitti_samples / "depth"),
        "--out",
        str(tmp_path),
        "--cameras",
        "2",
    ]
    assert tfds_builders.main(args) == 0
    path = capsys.readouterr().out.strip().splitlines()[-1]
    assert len(TfdsDepthSource(path, "train", cameras=(2,))) == 1
    with pytest.raises(KittiFormatError, match="train_image_03"):
        TfdsDepthSource(path, "train")
    assert tfds_builders.main(args) == 1
    assert "already exists" in capsys.readouterr().err
    assert tfds_builders.main(args + ["--overwrite"]) == 0
