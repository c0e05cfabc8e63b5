"""The multi-rig embedded dataset (``rig_set="multi"``): rigs, planes, splits, layout.

One small dataset (10 frames, KITTI-equivalent 188x621) is generated once per module.
The ground planes written to ``training/planes/`` are checked against the labels (bottom
centres lie on them) and against the render itself (the ray through a road pixel meets the
plane at the rendered depth), both independent of how the generator computed the plane.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gac_jax.builders.datasets import synthetic_dataset_dir
from gac_jax.config import load_config
from gac_jax.data import files, kitti, kitti_depth
from gac_jax.data.synthetic import rigs
from gac_jax.data.synthetic.frame import frame_rig
from gac_jax.data.synthetic.writer import drive_name, generate_dataset

REPO = Path(__file__).resolve().parents[1]
SIZE = (188, 621)
SEED = 5
N = 10


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("multirig") / "kitti"
    result = generate_dataset(
        root, N, SEED, height=SIZE[0], width=SIZE[1], val_fraction=0.3, rig_set="multi", workers=2
    )
    assert result.generated == N
    return root


def read_plane(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    assert lines[:3] == ["# Plane", "Width 4", "Height 1"], lines
    return np.array(lines[3].split(), float)


def frame_rigs() -> list[rigs.MountedRig]:
    return [rigs.MULTI_RIGS[frame_rig(SEED, i, "multi")] for i in range(N)]


def test_rig_set_covers_the_asked_range():
    heights = [r.height for r in rigs.MULTI_RIGS]
    pitches = [r.pitch for r in rigs.MULTI_RIGS]
    focals = {r.camera.K[0, 0] for r in rigs.MULTI_RIGS}
    sizes = {r.camera.size for r in rigs.MULTI_RIGS}
    assert min(heights) <= 1.2 and max(heights) >= 2.4
    assert min(pitches) <= -5 and max(pitches) >= 6
    assert len(focals) == len(sizes) == len(rigs.MULTI_RIGS)
    assert [r.name for r in rigs.MULTI_RIGS if r.heldout] == ["crossover", "minibus"]
    assert len({r.camera.date for r in rigs.MULTI_RIGS}) == len(rigs.MULTI_RIGS)


def test_each_frame_has_its_rigs_size_intrinsics_and_plane(dataset):
    for i, mount in enumerate(frame_rigs()):
        fid = f"{i:06d}"
        size = rigs.image_size(mount.camera, SIZE)
        assert files.read_image(dataset / "training" / "image_2" / f"{fid}.png").shape[:2] == size
        calib = kitti.read_calib(dataset / "training" / "calib" / f"{fid}.txt")
        scale = np.array([size[1] / mount.camera.size[1], size[0] / mount.camera.size[0], 1.0])
        np.testing.assert_allclose(calib.P2[:, :3], mount.camera.K * scale[:, None], rtol=1e-6)
        a, b, c, d = read_plane(dataset / "training" / "planes" / f"{fid}.txt")
        assert abs(np.linalg.norm([a, b, c]) - 1) < 1e-5 and b < 0 and abs(a) < 1e-6  # no roll
        assert abs(d - mount.height) <= rigs.POSE_JITTER_HEIGHT + 1e-6
        pitch = np.rad2deg(np.arctan2(-c, -b))  # normal (0, -cos p, -sin p): tilted down p > 0
        assert abs(pitch - mount.pitch) <= 2 * rigs.POSE_JITTER_PITCH + 1e-3, (i, pitch)


def test_labelled_objects_stand_on_the_plane(dataset):
    """Bottom centres (KITTI ``location``) of the labelled road users are on the plane: cars
    on the road to the labels' centimetre rounding, the rest on the road or a kerb."""
    cars, others = [], []
    for i in range(N):
        fid = f"{i:06d}"
        plane = read_plane(dataset / "training" / "planes" / f"{fid}.txt")
        objects = kitti.read_label(dataset / "training" / "label_2" / f"{fid}.txt")
        for k, name in enumerate(objects.type):
            if name == "DontCare":
                continue
            dist = float(objects.location[k] @ plane[:3] + plane[3])
            (cars if name == "Car" else others).append(dist)
    assert len(cars) >= 10
    assert np.max(np.abs(cars)) < 0.02, cars
    assert np.max(np.abs(others), initial=0.0) < 0.25, others


def test_the_plane_meets_the_rendered_road(dataset):
    """Rays of camera 2 through bottom-centre pixels hit the plane at the rendered depth."""
    checked = 0
    for i in range(N):
        fid, long_id = f"{i:06d}", f"{i:010d}"
        plane = read_plane(dataset / "training" / "planes" / f"{fid}.txt")
        P2 = kitti.read_calib(dataset / "training" / "calib" / f"{fid}.txt").P2
        rig = frame_rig(SEED, i, "multi")
        split = next(
            s
            for s in ("train", "val", "val_heldout")
            if f"{fid}\n" in (dataset / "ImageSets" / f"{s}.txt").read_text() + "\n"
        )
        dense = files.read_depth_png(
            dataset / "depth" / "data_depth_dense" / split / drive_name(rig, split, "multi")
            / "proj_depth" / "groundtruth" / "image_02" / f"{long_id}.png"
        )  # fmt: skip
        K, t = P2[:, :3], np.linalg.solve(P2[:, :3], P2[:, 3])
        h, w = dense.shape
        us, vs = np.meshgrid(np.arange(w // 2 - 20, w // 2 + 20), np.arange(h - 8, h - 2))
        rays = np.linalg.solve(K, np.stack([us.ravel(), vs.ravel(), np.ones(us.size)]))
        centre = -t  # camera 2's centre in the reference frame
        s = -(plane[:3] @ centre + plane[3]) / (plane[:3] @ rays)  # ray-plane intersection
        z = (centre[:, None] + s * rays)[2] + t[2]  # depth in camera 2 = z_ref + t_z
        rendered = dense[vs, us].ravel()
        road = rendered > 0
        err = np.abs(rendered[road] - z[road]) / z[road]
        if road.mean() > 0.5 and np.median(err) < 0.01:  # a car right in front hides the road
            checked += 1
        # the road where it shows; where something stands on it, nearer than the road
        hidden = rendered[road] < z[road] * 0.99
        assert np.all(err[~hidden] < 0.01) and np.all(hidden | (err < 0.01)), (i, np.median(err))
    assert checked >= N // 2


def test_splits_hold_out_two_rigs(dataset):
    lists = {
        p.stem: [int(x) for x in p.read_text().split()]
        for p in (dataset / "ImageSets").glob("*.txt")
    }
    assert set(lists) == {
        "train", "val", "val_heldout", "trainval", "train_kitti_rig", "val_kitti_rig"
    }  # fmt: skip
    mounts = frame_rigs()
    assert sorted(lists["train"] + lists["val"] + lists["val_heldout"]) == list(range(N))
    assert lists["val_heldout"] == [i for i in range(N) if mounts[i].heldout]
    assert not any(mounts[i].heldout for i in lists["train"] + lists["val"])
    for part in ("train", "val"):
        want = [i for i in lists[part] if mounts[i].name == "kitti"]
        assert lists[f"{part}_kitti_rig"] == want
    layout = kitti_depth.KittiDepthLayout(dataset / "depth")
    heldout_drives = {f.drive for f in layout.frames("val_heldout")}
    assert heldout_drives == {
        drive_name(frame_rig(SEED, i, "multi"), "val_heldout", "multi")
        for i in lists["val_heldout"]
    }
    description = json.loads((dataset / "synthetic.json").read_text())
    assert description["rigs"] == "multi"


def test_raw_calibration_per_rig(dataset):
    for mount in rigs.MULTI_RIGS:
        raw = kitti.read_calib(
            dataset / "depth" / "raw" / mount.camera.date / "calib_cam_to_cam.txt"
        )
        size = rigs.image_size(mount.camera, SIZE)
        assert tuple(raw.image_sizes[2]) == size


def test_configs_select_the_multi_rig_dataset(monkeypatch, tmp_path):
    monkeypatch.setenv("GAC_JAX_CACHE", str(tmp_path))
    c = load_config(str(REPO / "configs" / "detect3d_default.py:multirig,kittirig"))
    assert c.data.synthetic.rigs == "multi" and c.data.train_split == "train_kitti_rig"
    assert synthetic_dataset_dir(c.data).name.endswith("_multirig")
    d = load_config(str(REPO / "configs" / "depth_default.py:multirig"))
    assert synthetic_dataset_dir(d.data) == synthetic_dataset_dir(c.data)
    default = load_config(str(REPO / "configs" / "detect3d_default.py"))
    assert synthetic_dataset_dir(default.data).name == "synthetic_n1000_s0_375x1242_val0.3_v3_dc0.5"
    steps2x = load_config(str(REPO / "configs" / "detect3d_default.py:steps2x"))
    assert synthetic_dataset_dir(steps2x.data) == synthetic_dataset_dir(default.data)
    # 175 steps of 8 per epoch (700 frames, both views): the default's 2,100 and :steps2x's 3,500
    assert (default.train.num_epochs, steps2x.train.num_epochs) == (12, 20)
    # the depth default: the same frames without the randomized car paint; the tiny configs
    # (the tests') share one cache
    depth = load_config(str(REPO / "configs" / "depth_default.py"))
    assert synthetic_dataset_dir(depth.data).name == "synthetic_n1000_s0_375x1242_val0.3_v3"
    tiny = [
        load_config(str(REPO / "configs" / f"{t}_default.py:tiny")) for t in ("detect3d", "depth")
    ]
    assert synthetic_dataset_dir(tiny[0].data) == synthetic_dataset_dir(tiny[1].data)
    with pytest.raises(ValueError, match="needs 'multirig'"):
        load_config(str(REPO / "configs" / "detect3d_default.py:kittirig"))
