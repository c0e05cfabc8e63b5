"""Tests of the synthetic KITTI-format generator (gac_jax.data.synthetic).

One small dataset (6 frames at 188x621, KITTI intrinsics scaled by 1/2 and
188/375) is generated once per module; the same frames are also rebuilt in
memory (the generator is deterministic) to get at their object-id maps.
Geometry checks use independent float64 re-derivations and shapely.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import shapely

from gac_jax.data import files, kitti
from gac_jax.data.synthetic import calibration, render, shapes, vehicles
from gac_jax.data.synthetic.__main__ import main as cli_main
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.data.synthetic.scene import CLASS_SIZES
from gac_jax.data.synthetic.writer import drive_name, frame_paths, generate_dataset
from gac_jax.geometry import box2d_from_corners, box3d_corners, ground_depth, project, unproject

SIZE = (188, 621)
SEED = 3
N = 6
ARGS = dict(height=SIZE[0], width=SIZE[1], val_fraction=0.5, workers=1)
CLASSES = {"Car", "Pedestrian", "Cyclist", "DontCare"}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synthetic") / "kitti"
    result = generate_dataset(root, N, SEED, **ARGS)
    assert result.generated == N
    return root


@pytest.fixture(scope="module")
def frames():
    return [make_frame(SEED, i, SIZE) for i in range(N)]


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


def _split_of(index: int) -> str:
    return "train" if index < N // 2 else "val"


def _labels(root: Path, index: int) -> kitti.KittiObjects:
    return kitti.read_label(root / "training" / "label_2" / f"{index:06d}.txt")


def _box_local(points: np.ndarray, objects: kitti.KittiObjects, k: int) -> np.ndarray:
    """Points (n, 3) in the frame of label k's box (x along l, y down, z along w)."""
    ry = objects.rotation_y[k]
    c, s = np.cos(ry), np.sin(ry)
    d = points - objects.location[k]
    # inverse of the rotation about y: local = R^T d
    return np.stack([c * d[:, 0] - s * d[:, 2], d[:, 1], s * d[:, 0] + c * d[:, 2]], axis=1)


def _inside_box(local: np.ndarray, dims: np.ndarray, tol: float) -> np.ndarray:
    h, w, l = dims
    return (
        (np.abs(local[:, 0]) <= l / 2 + tol)
        & (np.abs(local[:, 2]) <= w / 2 + tol)
        & (local[:, 1] <= tol)
        & (local[:, 1] >= -h - tol)
    )


def _read_cam_to_cam(path: Path) -> dict[str, np.ndarray]:
    out = {}
    for line in path.read_text().splitlines():
        key, _, rest = line.partition(":")
        try:
            out[key] = np.array([float(x) for x in rest.split()])
        except ValueError:
            continue
    return out


# ----------------------------------------------------------------------------- layout


def test_layout_complete_and_readable(dataset):
    layout = kitti.KittiObjectLayout(dataset)
    train, val = layout.frame_ids("train"), layout.frame_ids("val")
    assert train == [f"{i:06d}" for i in range(N // 2)]
    assert val == [f"{i:06d}" for i in range(N // 2, N)]
    assert layout.frame_ids("trainval") == train + val == layout.frame_ids()
    for fid in train + val:
        for cam in (2, 3):
            assert files.read_image(layout.image(fid, cam)).shape == (*SIZE, 3)
        calib = kitti.read_calib(layout.calib(fid))
        assert calib.P3 is not None and calib.Tr_velo_to_cam is not None
        np.testing.assert_allclose(calib.R0_rect, np.eye(3))
        baseline = (calib.P2[0, 3] - calib.P3[0, 3]) / calib.P2[0, 0]
        assert baseline == pytest.approx(0.54, abs=1e-9)
        # one of the real KITTI intrinsics, scaled to this image size
        fx_full = calib.P2[0, 0] * 1242 / SIZE[1]
        assert min(abs(fx_full - f) for f in (721.5377, 718.3351, 707.0493)) < 1e-6
        text = layout.label(fid).read_text()
        assert all(len(line.split()) == 15 for line in text.splitlines())
        objects = kitti.read_label(layout.label(fid))
        assert set(objects.type) <= CLASSES
        dc = objects.select(objects.type == "DontCare")
        np.testing.assert_array_equal(dc.location, -1000.0)
        np.testing.assert_array_equal(dc.alpha, -10.0)
    assert (dataset / "synthetic.json").exists()
    assert not (dataset / ".synthetic_in_progress.json").exists()
    assert not list(dataset.rglob(".*.tmp"))


def test_depth_layout_and_raw_calibration(dataset, frames):
    for i, frame in enumerate(frames):
        paths = frame_paths(dataset, i, frame.rig, _split_of(i))
        drive = drive_name(frame.rig, _split_of(i))
        assert drive.startswith(calibration.RIGS[frame.rig].date + "_drive_")
        assert f"/{_split_of(i)}/{drive}/proj_depth/groundtruth/image_02/{i:010d}.png" in str(
            paths["sparse_2"]
        )
        for cam in (2, 3):
            assert paths[f"raw_{cam}"].read_bytes() == paths[f"image_{cam}"].read_bytes()
            for key in ("sparse", "dense"):
                assert files.read_depth_png(paths[f"{key}_{cam}"]).shape == SIZE
        raw = _read_cam_to_cam(paths["raw_2"].parents[3] / "calib_cam_to_cam.txt")
        calib = kitti.read_calib(paths["calib"])
        np.testing.assert_allclose(raw["S_rect_02"], [SIZE[1], SIZE[0]])
        np.testing.assert_allclose(raw["R_rect_00"], np.eye(3).ravel())
        for cam in range(4):
            P = getattr(calib, f"P{cam}")
            np.testing.assert_allclose(raw[f"P_rect_0{cam}"].reshape(3, 4), P, rtol=1e-6, atol=1e-6)


# ----------------------------------------------------------------------------- labels


def test_labels_match_object_masks(dataset, frames):
    # A labelled object's 2D box is the clipped projection of its 3D box (KITTI's own
    # labels are: tests/test_kitti_label_boxes.py), which holds its visible
    # pixels; a DontCare box is the extent of the visible pixels.
    for i, frame in enumerate(frames):
        objects = _labels(dataset, i)
        ids = frame.views[2].object_ids
        np.testing.assert_array_equal(frame.objects.bbox, objects.bbox)  # file == memory
        visible = {k for k in range(len(frame.scene.objects)) if (ids == k).any()}
        assert sorted(frame.label_source.tolist()) == sorted(visible)  # each visible object once
        for line, k in enumerate(frame.label_source):
            rr, cc = np.nonzero(ids == k)
            extent = np.array([cc.min(), rr.min(), cc.max(), rr.max()], float)
            height = extent[3] - extent[1] + 1
            obj = frame.scene.objects[k]
            if objects.type[line] != "DontCare":
                assert objects.type[line] == obj.type
                assert height >= 20 * SIZE[0] / 375 and objects.location[line, 2] <= 70
                corners = box3d_corners(obj.location[None], obj.dimensions[None], [obj.rotation_y])
                projected = box2d_from_corners(corners, frame.calib.P2, SIZE)[0]
                np.testing.assert_allclose(objects.bbox[line], projected, atol=0.006)
                box = objects.bbox[line]
                assert (extent[:2] >= box[:2] - 1.0).all() and (extent[2:] <= box[2:] + 1.0).all()
                assert (box[:2] >= 0).all() and box[2] <= SIZE[1] - 1 and box[3] <= SIZE[0] - 1
            else:
                np.testing.assert_allclose(objects.bbox[line], extent, atol=1.0)
                assert height < 20 * SIZE[0] / 375 or obj.location[2] > 70


def test_dense_depth_on_labelled_boxes(dataset, frames):
    checked = 0
    for i, frame in enumerate(frames):
        objects = _labels(dataset, i)
        paths = frame_paths(dataset, i, frame.rig, _split_of(i))
        depth = files.read_depth_png(paths["dense_2"]).astype(np.float64)
        P2 = kitti.read_calib(paths["calib"]).P2
        for line, k in enumerate(frame.label_source):
            if objects.type[line] == "DontCare":
                continue
            rr, cc = np.nonzero(frame.views[2].object_ids == k)
            pts = unproject(np.stack([cc, rr], 1).astype(np.float64), depth[rr, cc], P2)
            local = _box_local(pts, objects, line)
            assert _inside_box(local, objects.dimensions[line], tol=0.03).all()
            checked += 1
    assert checked >= 10


def test_ground_depth_zero_pitch():
    frame = make_frame(SEED, 100, SIZE, pitch=0.0, camera_height=1.65)
    view, P2 = frame.views[2], frame.calib.P2
    rr, cc = np.nonzero((view.surface == render.GROUND) & (view.depth > 0))
    assert len(rr) > 1000
    expected = ground_depth(rr, P2, 1.65) + P2[2, 3]  # stored depth = z of camera 2
    np.testing.assert_allclose(view.depth[rr, cc], expected, rtol=2e-5)


def test_ground_depth_with_pitch(frames):
    for frame in frames:
        scene, view, P2 = frame.scene, frame.views[2], frame.calib.P2
        assert abs(np.rad2deg(scene.pitch)) <= 1.0 and abs(scene.camera_height - 1.65) <= 0.05
        n = np.array([0.0, np.cos(scene.pitch), np.sin(scene.pitch)])
        np.testing.assert_allclose(scene.ground_normal, n, atol=1e-12)
        rr, cc = np.nonzero((view.surface == render.GROUND) & (view.depth > 0))
        uv = np.stack([cc, rr], 1).astype(np.float64)
        c0 = unproject(uv, np.zeros(len(uv)), P2)  # the optical centre
        d1 = unproject(uv, np.ones(len(uv)), P2) - c0  # ray per unit depth
        w = (scene.camera_height - c0 @ n) / (d1 @ n)
        np.testing.assert_allclose(view.depth[rr, cc], w, rtol=2e-5)


def test_truncation_occlusion_alpha(dataset, frames):
    seen_levels = set()
    for i, frame in enumerate(frames):
        objects = _labels(dataset, i)
        for line, k in enumerate(frame.label_source):
            if objects.type[line] == "DontCare":
                continue
            obj = frame.scene.objects[k]
            corners = obj.corners()
            box = box2d_from_corners(corners[None], frame.calib.P2)[0]
            inside = (
                box[0] >= 0.5
                and box[1] >= 0.5
                and box[2] <= SIZE[1] - 1.5
                and box[3] <= SIZE[0] - 1.5
            )
            trunc = objects.truncated[line]
            if inside:
                assert trunc == 0.0
            if trunc > 0:
                assert not inside
            visible = (frame.views[2].object_ids == k).sum()
            fraction = visible / frame.views[2].silhouette_px[k]
            assert 0 < fraction <= 1
            level = 0 if fraction >= 0.95 else (1 if fraction >= 0.5 else 2)
            assert objects.occluded[line] == level
            seen_levels.add(level)
            x, _, z = objects.location[line]
            alpha = objects.rotation_y[line] - np.arctan2(x, z)
            alpha = (alpha + np.pi) % (2 * np.pi) - np.pi
            assert abs(np.angle(np.exp(1j * (objects.alpha[line] - alpha)))) < 1e-5
    assert 0 in seen_levels and len(seen_levels) >= 2


def test_silhouette_matches_solo_render_and_box_hull(frames):
    """An object's unoccluded silhouette = a render of it alone, and lies in its projected box."""
    frame = frames[0]
    scene = frame.scene
    for k, obj in enumerate(scene.objects):
        # alone: no other solids, and the ground plane moved far below (nothing occludes it)
        alone = {"background": [], "objects": [obj], "camera_height": 1000.0}
        solo = scene.__class__(**{**scene.__dict__, **alone})
        view = render.render_view(solo, frame.calib.P2, SIZE, np.random.default_rng(0))
        mask = view.object_ids == 0
        assert mask.sum() == frame.views[2].silhouette_px[k]
        if not mask.any():
            continue
        uv, w = project(obj.corners(), frame.calib.P2)
        assert (w > 0).all()
        hull = shapely.MultiPoint(uv).convex_hull.buffer(1e-6)
        rr, cc = np.nonzero(mask)
        assert shapely.contains_xy(hull, cc, rr).all()


def test_right_view_consistent(dataset, frames):
    checked = 0
    for i, frame in enumerate(frames):
        objects = _labels(dataset, i)
        paths = frame_paths(dataset, i, frame.rig, _split_of(i))
        P3 = kitti.read_calib(paths["calib"]).P3
        right = files.read_image(paths["image_3"])
        np.testing.assert_array_equal(right, frame.views[3].image)
        depth = files.read_depth_png(paths["dense_3"]).astype(np.float64)
        for line, k in enumerate(frame.label_source):
            if objects.type[line] == "DontCare":
                continue
            rr, cc = np.nonzero(frame.views[3].object_ids == k)
            if len(rr) == 0:
                continue
            corners = box3d_corners(
                objects.location[line : line + 1],
                objects.dimensions[line : line + 1],
                objects.rotation_y[line : line + 1],
            )[0]
            uv, _ = project(corners, P3)
            hull = shapely.MultiPoint(uv).convex_hull.buffer(1e-6)
            assert shapely.contains_xy(hull, cc, rr).all()
            pts = unproject(np.stack([cc, rr], 1).astype(np.float64), depth[rr, cc], P3)
            assert _inside_box(_box_local(pts, objects, line), objects.dimensions[line], 0.03).all()
            checked += 1
    assert checked >= 10


def test_sparse_depth_subset_of_dense(dataset, frames):
    for i, frame in enumerate(frames):
        paths = frame_paths(dataset, i, frame.rig, _split_of(i))
        for cam in (2, 3):
            dense = files.read_depth_png(paths[f"dense_{cam}"])
            sparse = files.read_depth_png(paths[f"sparse_{cam}"])
            valid = sparse > 0
            np.testing.assert_array_equal(sparse[valid], dense[valid])
            assert sparse.max() < 80.0
            below = int(np.ceil(frame.calib.P2[1, 2])) + 5
            fraction = valid[below:].mean()
            assert 0.03 < fraction < 0.45, fraction
            sky = frame.views[cam].surface == render.SKY
            assert (dense[sky] == 0).all() and (dense[~sky] > 0).mean() > 0.99


def test_ray_caster_matches_hand_computed_box():
    """A 2 m cube 10 m ahead: exact pixel coverage and depth of its front face."""
    P = np.array([[500.0, 0, 300, 20], [0, 500, 100, 1], [0, 0, 1, 0.01]])
    cube = shapes.box(-1.0, 1.0, -1.0, 1.0, 10.0, 12.0, (0.5, 0.5, 0.5))
    cam = render.Camera(P, (200, 600))
    hit, rho, face = render.cast(cube, cam, (0, 599, 0, 199))
    # front face z = 10: u = (500 x + 300 z + 20) / (z + 0.01), same for v
    w = 10.0 + 0.01
    u_lo, u_hi = (500 * -1 + 3000 + 20) / w, (500 * 1 + 3000 + 20) / w
    v_lo, v_hi = (500 * -1 + 1000 + 1) / w, (500 * 1 + 1000 + 1) / w
    uu, vv = np.meshgrid(np.arange(600), np.arange(200))
    expect = (uu >= u_lo) & (uu <= u_hi) & (vv >= v_lo) & (vv <= v_hi)
    np.testing.assert_array_equal(hit, expect)
    np.testing.assert_allclose(1.0 / rho[hit], w, rtol=1e-6)
    assert (cube.normals[face[hit]] @ [0, 0, -1] > 0.999).all()


@pytest.mark.parametrize("cls", ["Car", "Pedestrian", "Cyclist", "Van", "Truck"])
def test_part_models_inside_their_box(cls):
    rng = np.random.default_rng(0)
    build = {
        "Car": lambda h, w, l: shapes.car_parts(h, w, l, np.array([0.5, 0.1, 0.1]), rng),
        "Pedestrian": lambda h, w, l: shapes.pedestrian_parts(h, w, l, rng),
        "Cyclist": lambda h, w, l: shapes.cyclist_parts(h, w, l, rng),
        "Van": lambda h, w, l: vehicles.van_parts(h, w, l, np.array([0.9, 0.9, 0.9]), rng),
        "Truck": lambda h, w, l: vehicles.truck_parts(h, w, l, np.array([0.2, 0.3, 0.6]), rng),
    }[cls]
    for _ in range(30):
        sizes = {**CLASS_SIZES, **vehicles.SIZES}[cls]
        dims = [m + sd * np.clip(rng.standard_normal(), -2.5, 2.5) for m, sd in sizes]
        parts = build(*dims)
        h, w, l = dims
        verts = np.concatenate([p.vertices for p in parts])
        assert _inside_box(verts, np.array(dims), tol=1e-9).all()
        for p in parts:  # every stored half-space really bounds its vertices, no empty faces
            assert p.contains(p.vertices, tol=1e-9).all()
        fill = {"Car": 0.95, "Pedestrian": 0.35, "Cyclist": 0.9, "Van": 0.95, "Truck": 0.95}[
            cls
        ]  # share of l the model spans
        assert np.ptp(verts[:, 1]) > 0.95 * h and np.ptp(verts[:, 0]) > fill * l


# ------------------------------------------------------------------ determinism and resume


def test_same_seed_same_bytes_any_workers(dataset, tmp_path):
    other = tmp_path / "again"
    result = generate_dataset(other, N, SEED, **{**ARGS, "workers": 2})
    assert result.generated == N
    assert _tree_digest(other) == _tree_digest(dataset)


# sha256 of the sorted {path: sha256} of the ``dataset`` fixture's files. The frames'
# bytes must not change when the clips' code changes; change this only together with
# writer.FORMAT_VERSION.
FRAMES_DIGEST = "c0cabb1046c54cb0b0c465db81c708c2fe27cc068eada0fc9692b2e6fc3fad21"


def test_frame_dataset_bytes_unchanged(dataset):
    digest = _tree_digest(dataset)
    assert hashlib.sha256(json.dumps(digest, sort_keys=True).encode()).hexdigest() == FRAMES_DIGEST


def test_different_seed_differs(frames):
    other = make_frame(SEED + 1, 0, SIZE)
    assert not np.array_equal(other.views[2].image, frames[0].views[2].image)
    assert not np.array_equal(other.views[2].depth, frames[0].views[2].depth)
    again = make_frame(SEED, 0, SIZE)
    np.testing.assert_array_equal(again.views[3].image, frames[0].views[3].image)


def test_idempotent_and_resume(dataset, tmp_path):
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    before = _tree_digest(root)
    stamps = {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()}
    start = time.perf_counter()
    assert generate_dataset(root, N, SEED, **ARGS).generated == 0
    assert time.perf_counter() - start < 1.0
    assert {p: p.stat().st_mtime_ns for p in root.rglob("*") if p.is_file()} == stamps

    frame2 = make_frame(SEED, 2, SIZE)
    removed = frame_paths(root, 2, frame2.rig, _split_of(2))
    for p in removed.values():
        p.unlink()
    assert generate_dataset(root, N, SEED, **ARGS).generated == 1
    assert _tree_digest(root) == before
    rewritten = set(removed.values())
    for p, stamp in stamps.items():
        untouched = p not in rewritten and p.parent.name != "ImageSets"
        if untouched and p.name != "synthetic.json" and "calib_" not in p.name:
            assert p.stat().st_mtime_ns == stamp, p

    (root / "ImageSets" / "val.txt").unlink()  # a dataset-level file is restored too
    assert generate_dataset(root, N, SEED, **ARGS).generated == 0
    assert _tree_digest(root) == before

    # an interrupted run: marker present, description missing, a temporary file, a lost label
    (root / "synthetic.json").unlink()
    (root / ".synthetic_in_progress.json").write_text((dataset / "synthetic.json").read_text())
    (root / "training" / "label_2" / ".000001.txt.abc.tmp").write_text("half")
    (root / "training" / "label_2" / "000004.txt").unlink()
    assert generate_dataset(root, N, SEED, **ARGS).generated == 1
    assert _tree_digest(root) == before


def test_refuses_foreign_or_different_directories(dataset, tmp_path):
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match="not empty"):
        generate_dataset(foreign, 2, SEED, **ARGS)
    with pytest.raises(ValueError, match="other arguments.*seed"):
        generate_dataset(dataset, N, SEED + 1, **ARGS)
    with pytest.raises(ValueError, match="number of frames"):
        generate_dataset(tmp_path / "x", 0, SEED)
    with pytest.raises(ValueError, match="unknown class"):
        generate_dataset(tmp_path / "x", 1, SEED, classes={"Truck": (1, 2)})


# ----------------------------------------------------------------------------- CLI


def test_cli_bad_arguments_give_clear_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["--out", str(tmp_path / "a"), "--num", "0"])
    assert e.value.code == 2
    assert "--num: must be at least 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        cli_main(["--out", str(tmp_path / "a"), "--num", "2", "--classes", "Car:x"])
    assert "bad count range" in capsys.readouterr().err

    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    assert cli_main(["--out", str(blocker / "sub"), "--num", "1", "--quiet"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "file.txt" in err and "Traceback" not in err
    assert cli_main(["--out", str(blocker), "--num", "1", "--quiet"]) == 1
    assert "not a directory" in capsys.readouterr().err


def test_cli_end_to_end(tmp_path):
    out = tmp_path / "cli"
    cmd = [sys.executable, "-m", "gac_jax.data.synthetic", "--out", str(out), "--num", "2"]
    cmd += ["--seed", "1", "--height", "64", "--width", "256", "--workers", "1", "--quiet"]
    cmd += ["--classes", "Car:2-3"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert run.returncode == 0, run.stderr
    labels = [kitti.read_label(p) for p in sorted((out / "training" / "label_2").glob("*.txt"))]
    assert len(labels) == 2 and all(set(o.type) <= {"Car", "DontCare"} for o in labels)
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert again.returncode == 0 and "already there" in again.stdout
    bad = subprocess.run(cmd[:5] + ["--num", "-3"], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr and "--num" in bad.stderr


def test_a_view_without_road_surface_renders(frames):
    # a wall right in front of the camera hides every road pixel (the shading once failed on
    # the empty pixel set)
    frame = frames[0]
    wall = shapes.box(-60.0, 60.0, -60.0, 60.0, 1.0, 1.5, (0.5, 0.5, 0.5))
    scene = dataclasses.replace(frame.scene, background=[*frame.scene.background, wall])
    view = render.render_view(scene, frame.calib.P2, SIZE, np.random.default_rng(0))
    assert view.image.shape == (*SIZE, 3) and np.isfinite(view.depth).all()
    assert not (view.surface == render.GROUND).any()
    np.testing.assert_allclose(view.depth, 1.0, atol=0.01)  # (P2 moves z by its t_z)
