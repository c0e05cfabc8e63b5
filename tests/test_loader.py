"""Batch contract, padding, determinism, sharding, resume and worker processes of the loader."""

from __future__ import annotations

import dataclasses
import os
import pickle
import re
import shutil

import numpy as np
import pytest

from gac_jax.data import transforms as tr
from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti import KittiObjects, write_split
from gac_jax.data.loader import (
    DEPTH_KEYS,
    DETECTION_KEYS,
    DepthArrays,
    DetectionArrays,
    Loader,
    detection_arrays,
)
from gac_jax.data.sources import KittiDepthSource, KittiObjectSource

CLASSES = ("Car", "Pedestrian", "Cyclist")
M = 16
DTYPES = {
    "image": np.float32,
    "P2": np.float32,
    "plane": np.float32,
    "image_transform": np.float32,
    "original_size": np.int32,
    "gt_mask": np.bool_,
    "gt_class": np.int32,
    "gt_boxes": np.float32,
    "gt_center": np.float32,
    "gt_depth": np.float32,
    "gt_dims": np.float32,
    "gt_alpha": np.float32,
    "gt_location": np.float32,
    "gt_rotation_y": np.float32,
    "gt_truncated": np.float32,
    "gt_occluded": np.int32,
}


def train_transform():
    return tr.Compose(
        [
            tr.FilterObjects(CLASSES),
            tr.CropTop(100),
            tr.Resize(48),
            tr.PhotometricDistort(),  # after the resize only to keep the test fast
            tr.CropOrPadWidth(160),
            tr.RandomHorizontalFlip(0.5),
            tr.ReprojectBoxes(),
            tr.Normalize(),
        ]
    )


@pytest.fixture(scope="module")
def source(kitti_object_root, tmp_path_factory):
    """13 records: the vendored real frames repeated under the ids 000000-000012 (in split
    order: 000001 is the real 000001), so batches, shards and epochs have the sizes below."""
    real = KittiObjectSource(kitti_object_root, "labeled").frame_ids
    root = tmp_path_factory.mktemp("loader_kitti")
    ids = [f"{i:06d}" for i in range(13)]
    for sub, ext in (("image_2", "png"), ("calib", "txt"), ("label_2", "txt")):
        (root / "training" / sub).mkdir(parents=True)
        for i, frame_id in enumerate(ids):
            src = kitti_object_root / "training" / sub / f"{real[i % len(real)]}.{ext}"
            (root / "training" / sub / f"{frame_id}.{ext}").symlink_to(src)
    write_split(root / "ImageSets" / "labeled.txt", ids)
    return KittiObjectSource(root, "labeled")


def make_loader(source, **kw):
    args = dict(batch_size=4, seed=3)
    args.update(kw)
    return Loader(source, train_transform(), DetectionArrays(CLASSES, M), **args)


def assert_batches_equal(a: list[dict], b: list[dict]) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x.keys() == y.keys()
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)


def test_batch_contract(source):
    loader = make_loader(source)
    batch = next(loader.iterate())
    assert set(batch) == set(DETECTION_KEYS)
    B = 4
    shapes = {
        "image": (B, 48, 160, 3),
        "P2": (B, 3, 4),
        "plane": (B, 4),
        "image_transform": (B, 3, 3),
        "original_size": (B, 2),
        "gt_boxes": (B, M, 4),
        "gt_center": (B, M, 2),
        "gt_dims": (B, M, 3),
        "gt_location": (B, M, 3),
        "frame_id": (B,),
    }
    for key in DETECTION_KEYS:
        assert batch[key].shape == shapes.get(key, (B, M)), key
        if key in DTYPES:
            assert batch[key].dtype == DTYPES[key], key
    assert batch["frame_id"].dtype.kind == "U"
    # frames without planes/ files: the level plane of the converter's camera height
    np.testing.assert_array_equal(batch["plane"], np.tile(np.float32([0, -1, 0, 1.65]), (B, 1)))
    # padding: mask marks exactly the kept objects; padded classes are -1
    _, indices = loader.step_indices(0)
    for row, i in enumerate(indices):
        objs = source[int(i)]["objects"]
        n = int(np.isin(objs.type, CLASSES).sum())
        assert batch["frame_id"][row] == source.frame_ids[i]
        assert batch["gt_mask"][row].sum() == n and batch["gt_mask"][row, :n].all()
        assert (batch["gt_class"][row, n:] == -1).all() and (batch["gt_class"][row, :n] >= 0).all()
        assert not batch["gt_boxes"][row, n:].any()
        assert tuple(batch["original_size"][row]) == source[int(i)]["original_size"]


def test_plane_is_the_samples_else_the_converters_level_plane(source):
    sample = source[1]
    out = DetectionArrays(CLASSES, 8, camera_height=1.4)(sample)
    np.testing.assert_array_equal(out["plane"], np.float32([0, -1, 0, 1.4]))
    tilted = np.array([0.0, -0.94, -0.342, 1.7])
    out = DetectionArrays(CLASSES, 8, camera_height=1.4)(dict(sample, plane=tilted))
    np.testing.assert_array_equal(out["plane"], tilted.astype(np.float32))


def test_detection_arrays_values(source):
    s = tr.Resize(200)(source[1])  # 000001: Truck, Car, Cyclist, 4 DontCare
    out = detection_arrays(s, CLASSES, 4)
    assert out["gt_mask"].tolist() == [True, True, False, False]
    assert out["gt_class"].tolist() == [0, 2, -1, -1]  # Car, Cyclist (Truck, DontCare dropped)
    obj = s["objects"].select(np.isin(s["objects"].type, CLASSES))
    P = s["P2"]
    for k in range(2):
        x, y, z = obj.location[k]
        h = obj.dimensions[k, 0]
        hom = P @ np.array([x, y - h / 2, z, 1.0])  # independent float64 projection
        np.testing.assert_allclose(out["gt_center"][k], hom[:2] / hom[2], rtol=1e-6)
        np.testing.assert_allclose(out["gt_depth"][k], z + P[2, 3], rtol=1e-6)
    np.testing.assert_allclose(out["gt_dims"][:2], obj.dimensions, rtol=1e-6)
    np.testing.assert_allclose(out["gt_boxes"][:2], obj.bbox, rtol=1e-6)
    assert out["gt_occluded"][:2].tolist() == [0, 3]


def test_too_many_objects(source):
    s = source[7]  # 000007 (the real 000036: 7 cars)
    n = int(np.isin(s["objects"].type, CLASSES).sum())
    assert n > 2
    with pytest.raises(ValueError, match=f"frame 000007 .*has {n} objects.*max_objects=2"):
        detection_arrays(s, CLASSES, 2)
    out = detection_arrays(s, CLASSES, 2, truncate=True)
    obj = s["objects"].select(np.isin(s["objects"].type, CLASSES))
    nearest = np.sort(obj.location[:, 2])[:2]
    np.testing.assert_allclose(np.sort(out["gt_location"][:, 2]), nearest, rtol=1e-6)
    empty = detection_arrays({**s, "objects": KittiObjects.empty()}, CLASSES, 3)
    assert not empty["gt_mask"].any() and (empty["gt_class"] == -1).all()


def test_deterministic_for_a_seed(source):
    a = list(make_loader(source).iterate(0, 4))
    b = list(make_loader(source).iterate(0, 4))
    assert_batches_equal(a, b)
    c = list(make_loader(source, seed=4).iterate(0, 4))
    assert any(not np.array_equal(x["frame_id"], y["frame_id"]) for x, y in zip(a, c, strict=True))
    # epochs differ in order, and an epoch visits each record at most once
    loader = make_loader(source)
    assert loader.steps_per_epoch == 3
    ids = [list(b["frame_id"]) for b in a]
    assert len(set(sum(ids[:3], []))) == 12
    assert ids[3] != ids[0]
    ordered = make_loader(source, shuffle=False)
    assert list(next(ordered.iterate())["frame_id"]) == source.frame_ids[:4]


@pytest.mark.parametrize("drop_remainder", [True, False])
def test_shards_are_disjoint_and_cover(source, drop_remainder):
    num_shards, bs = 3, 2
    loaders = [
        make_loader(
            source,
            batch_size=bs,
            shard_index=k,
            num_shards=num_shards,
            drop_remainder=drop_remainder,
        )
        for k in range(num_shards)
    ]
    steps = loaders[0].steps_per_epoch
    assert steps == (2 if drop_remainder else 3)
    for epoch in range(2):
        order = loaders[0].epoch_order(epoch)
        seen = []
        for step in range(epoch * steps, (epoch + 1) * steps):
            parts = [ld.step_indices(step)[1] for ld in loaders]
            flat = np.concatenate(parts)
            assert len(set(flat.tolist())) == len(flat)  # disjoint within the global batch
            seen.extend(flat.tolist())
        assert len(set(seen)) == len(seen)  # disjoint across the epoch
        expect = order if not drop_remainder else order[: steps * bs * num_shards]
        assert sorted(seen) == sorted(expect.tolist())
    # the batches themselves hold those frames
    for k, ld in enumerate(loaders):
        got = [list(b["frame_id"]) for b in ld.epoch(0)]
        want = [[source.frame_ids[i] for i in ld.step_indices(s)[1]] for s in range(steps)]
        want = [w for w in want if w]
        assert got == want, k


def test_resume_matches_uninterrupted(source):
    full = list(make_loader(source).iterate(0, 7))  # crosses two epoch boundaries
    for k in (1, 3, 5):
        resumed = list(make_loader(source).iterate(k, 7 - k))
        assert_batches_equal(resumed, full[k:])
    finite = make_loader(source, num_epochs=2)
    assert len(list(finite)) == 6
    assert len(list(finite.iterate(4))) == 2


@dataclasses.dataclass(frozen=True)
class WithPid:
    """to_arrays wrapper that records which process built each sample."""

    inner: DetectionArrays

    def __call__(self, sample):
        out = self.inner(sample)
        out["pid"] = np.int64(os.getpid())
        return out


def test_worker_processes(source):
    base = make_loader(source)
    expected = list(base.iterate(0, 5))
    loader = Loader(
        source,
        train_transform(),
        WithPid(DetectionArrays(CLASSES, M)),
        batch_size=4,
        seed=3,
        worker_count=2,
    )
    got = list(loader.iterate(0, 5))
    pids = {int(p) for b in got for p in b.pop("pid")}
    assert os.getpid() not in pids and len(pids) == 2  # both workers did work
    assert_batches_equal(got, expected)
    threaded = list(make_loader(source, num_threads=3).iterate(0, 5))
    assert_batches_equal(threaded, expected)


def test_depth_batches(kitti_samples):
    src = KittiDepthSource(kitti_samples / "depth", "train")
    transform = tr.Compose(
        [
            tr.CropBottomTo(352),
            tr.RandomCropWidth(1216),
            tr.RandomHorizontalFlip(),
            tr.Resize(88),
            tr.Normalize(),
        ]
    )
    loader = Loader(src, transform, DepthArrays(), batch_size=2, seed=0, shuffle=False)
    batch = next(loader.iterate())
    assert set(batch) == set(DEPTH_KEYS)
    assert batch["image"].shape == (2, 88, 304, 3) and batch["depth"].shape == (2, 88, 304)
    assert batch["depth"].dtype == np.float32 and (batch["depth"] > 0).mean() > 0.1
    assert batch["original_size"].tolist() == [[375, 1242]] * 2
    with pytest.raises(ValueError, match="no depth map"):
        DepthArrays()({k: v for k, v in src[0].items() if k != "depth"})


def test_mismatched_shapes_and_bad_arguments(source):
    loader = Loader(source, None, DetectionArrays(CLASSES, M), batch_size=4, shuffle=False)
    with pytest.raises(ValueError, match="different 'image' shapes"):
        loader.load_batch(0)
    with pytest.raises(ValueError, match="fewer than one global batch"):
        make_loader(source, batch_size=5, num_shards=3)
    with pytest.raises(ValueError, match="shard_index"):
        make_loader(source, shard_index=2, num_shards=2)


def test_file_errors_cross_worker_processes(kitti_object_root, tmp_path):
    root = tmp_path / "kitti"
    shutil.copytree(kitti_object_root / "training", root / "training")
    shutil.copytree(kitti_object_root / "ImageSets", root / "ImageSets")
    image = root / "training" / "image_2" / "000001.png"
    image.write_bytes(image.read_bytes()[:300])
    err = pickle.loads(pickle.dumps(KittiFormatError(image, "broken", 3)))
    assert (err.path, err.problem, err.line, str(err)) == (
        str(image),
        "broken",
        3,
        f"{image}:3: broken",
    )
    src = KittiObjectSource(root, "labeled")
    loader = make_loader(src, batch_size=2, shuffle=False, worker_count=1)
    with pytest.raises(KittiFormatError, match="^" + re.escape(str(image)) + ": not a readable"):
        list(loader.iterate(0, 1))
