"""The generated world's newer parts: shadows of the roadside, parked rows, car bodies, the
camera's effects, sharded generation, and the camera-effects training augmentation."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
import shapely

from gac_jax.data.camera_effects import CameraEffects
from gac_jax.data.synthetic import render, shapes
from gac_jax.data.synthetic.calibration import KITTI_SIZE
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.data.synthetic.scene import CLASS_SIZES, sample_scene
from gac_jax.data.synthetic.writer import DONE, DatasetSpec, generate_dataset
from gac_jax.geometry import box3d_corners, project

P2 = np.array([[721.5, 0.0, 609.6, 44.9], [0.0, 721.5, 172.9, 0.2], [0.0, 0.0, 1.0, 0.003]])
DOWN = np.array([0.0, 1.0, 0.0])  # level ground, camera frame (y down)
HEIGHT = 1.65


def _polygon(hull4: np.ndarray) -> shapely.Polygon:
    return shapely.Polygon(hull4.reshape(-1, 2) / 4.0)


def test_shadow_of_a_box_is_its_footprint_stretched_away_from_the_sun():
    # a 2 m tall box on the ground; the sun 45 degrees up towards +x: the shadow on the ground
    # is the footprint stretched 2 m towards -x (hand-computed), projected by P2
    box = shapes.box(-1.0, 1.0, HEIGHT - 2.0, HEIGHT, 10.0, 12.0, (0.5, 0.5, 0.5))
    sun = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    hull = render.ground_shadow(box.vertices, sun, DOWN, HEIGHT, P2)
    corners = np.array([[-3.0, HEIGHT, 10.0], [1.0, HEIGHT, 10.0], [1.0, HEIGHT, 12.0]])
    corners = np.vstack([corners, [[-3.0, HEIGHT, 12.0]]])
    want = shapely.Polygon(project(corners, P2)[0])
    got = _polygon(hull)
    assert got.symmetric_difference(want).area < 0.01 * want.area  # (rounded to 1/4 px)
    assert want.area > 500


def test_shadow_of_a_box_partly_behind_the_camera_is_clipped_at_the_near_plane():
    # a long wall beside the camera from 5 m behind it to 30 m ahead, sun from the left
    wall = shapes.box(3.0, 3.5, HEIGHT - 4.0, HEIGHT, -5.0, 30.0, (0.5, 0.5, 0.5))
    sun = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    hull = render.ground_shadow(wall.vertices, sun, DOWN, HEIGHT, P2)
    assert hull is not None
    uv = hull.reshape(-1, 2) / 4.0
    assert np.isfinite(uv).all()
    # every point of the shadow in front of the camera projects inside the hull
    pts = np.array([[x, HEIGHT, z] for x in (-0.5, 1.0, 3.2) for z in (1.0, 8.0, 25.0)])
    inside = [_polygon(hull).buffer(0.5).contains(shapely.Point(*project(p[None], P2)[0][0]))
              for p in pts]  # fmt: skip
    assert all(inside)


def test_clip_near_hand_computed():
    square = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    clipped = render._clip_near(square, 0.5)
    np.testing.assert_allclose(
        clipped, [[1.0, 0.0, 0.5], [1.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.5]]
    )
    assert len(render._clip_near(square, 2.0)) == 0


def test_low_solids_and_a_sun_at_the_horizon_cast_no_shadow():
    kerb = shapes.box(-1.0, 1.0, HEIGHT - 0.15, HEIGHT + 0.3, 5.0, 9.0, (0.5, 0.5, 0.5))
    sun = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)
    assert render.ground_shadow(kerb.vertices, sun, DOWN, HEIGHT, P2) is None
    pole = shapes.box(-0.1, 0.1, HEIGHT - 5.0, HEIGHT, 5.0, 5.2, (0.5, 0.5, 0.5))
    assert render.ground_shadow(pole.vertices, np.array([1.0, 0.0, 0.0]), DOWN, HEIGHT, P2) is None


@pytest.mark.parametrize("kind", shapes.CAR_BODIES)
def test_every_car_body_is_convex_parts_inside_its_box(kind):
    rng = np.random.default_rng(11)
    for _ in range(150):
        dims = [m + sd * np.clip(rng.standard_normal(), -2.5, 2.5) for m, sd in CLASS_SIZES["Car"]]
        parts = shapes.car_parts(*dims, np.array([0.5, 0.1, 0.1]), rng, kind=kind)
        h, w, l = dims
        for p in parts:
            assert p.contains(p.vertices, tol=1e-9).all()  # planar faces of a convex solid
            v = p.vertices
            assert (np.abs(v[:, 0]) <= l / 2 + 1e-9).all() and (
                np.abs(v[:, 2]) <= w / 2 + 1e-9
            ).all()
            assert (v[:, 1] >= -h - 1e-9).all() and (v[:, 1] <= 1e-9).all()


def _footprint(obj) -> shapely.Polygon:
    c = box3d_corners(np.asarray(obj.location)[None], np.asarray(obj.dimensions)[None],
                      [obj.rotation_y])[0]  # fmt: skip
    return shapely.MultiPoint(c[:, [0, 2]]).convex_hull


def test_parked_rows_line_cars_up_along_the_kerb_without_overlaps():
    rows = 0
    for seed in range(40):
        scene = sample_scene(np.random.default_rng(seed), P2, KITTI_SIZE)
        feet = [_footprint(o) for o in scene.objects]
        for i in range(len(feet)):
            for j in range(i + 1, len(feet)):
                assert feet[i].intersection(feet[j]).area < 1e-6, (seed, i, j)
        cars = [o for o in scene.objects if o.type == "Car"]
        lateral = np.array([o.location[0] for o in cars])
        for x in lateral:
            same = np.sort([o.location[2] for o in cars if abs(o.location[0] - x) < 0.5])
            if len(same) >= 4 and np.median(np.diff(same)) < 7.0:  # nose to tail, >= 4 cars
                rows += 1
                break
    assert rows >= 8  # most scenes with a parking lane have a row


def test_camera_effects_of_the_renderer_are_drawn_per_view_and_reproducible():
    a = make_frame(5, 3, (188, 621))
    b = make_frame(5, 3, (188, 621))
    assert np.array_equal(a.views[2].image, b.views[2].image)
    assert np.array_equal(a.views[3].image, b.views[3].image)
    gains = render._vignette(9, 11, 0.3)
    assert gains[4, 5] == pytest.approx(1.0) and gains[0, 0] == pytest.approx(0.7)


def _tree_digest(root) -> str:
    digest = {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }
    return hashlib.sha256(json.dumps(digest, sort_keys=True).encode()).hexdigest()


def test_shards_into_one_folder_write_the_bytes_of_one_run(tmp_path):
    args = dict(height=94, width=311, val_fraction=0.5, workers=1)
    whole = generate_dataset(tmp_path / "whole", 5, 9, **args)
    parts = [generate_dataset(tmp_path / "sharded", 5, 9, shard=(k, 3), **args) for k in (2, 0)]
    assert whole.complete and not parts[0].complete and not parts[1].complete
    assert not (tmp_path / "sharded" / DONE).exists()  # not complete before the last shard
    last = generate_dataset(tmp_path / "sharded", 5, 9, shard=(1, 3), **args)
    assert last.complete and [p.generated for p in parts] + [last.generated] == [2, 1, 2]
    assert (tmp_path / "sharded" / DONE).exists()
    assert _tree_digest(tmp_path / "sharded") == _tree_digest(tmp_path / "whole")


def test_camera_effects_augmentation_changes_pixels_only():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (32, 48, 3)).astype(np.uint8)
    P2_in = P2.copy()
    labels = object()
    sample = {"image": image, "P2": P2_in, "objects": labels}
    aug = CameraEffects(p_gamma=1, p_white_balance=1, p_blur=1, p_noise=1, p_jpeg=1)
    out1 = aug({**sample, "rng": np.random.default_rng(4)})
    out2 = aug({**sample, "rng": np.random.default_rng(4)})
    assert out1["P2"] is P2_in and out1["objects"] is labels and set(out1) == set(sample) | {"rng"}
    np.testing.assert_array_equal(P2_in, P2)
    assert out1["image"].shape == image.shape and out1["image"].dtype == np.float32
    assert out1["image"].min() >= 0.0 and out1["image"].max() <= 255.0
    np.testing.assert_array_equal(out1["image"], out2["image"])  # per-sample stream
    assert np.abs(out1["image"] - image).mean() > 1.0
    off = CameraEffects(p_gamma=0, p_white_balance=0, p_blur=0, p_noise=0, p_jpeg=0)
    np.testing.assert_array_equal(off({**sample, "rng": np.random.default_rng(4)})["image"], image)


def test_randomized_background_repaints_the_background_only():
    plain = make_frame(0, 11, (188, 621))
    again = make_frame(0, 11, (188, 621), randomize=1.0)
    other = make_frame(0, 11, (188, 621), randomize=1.0)
    np.testing.assert_array_equal(again.views[2].image, other.views[2].image)  # per seed
    for cam in (2, 3):
        a, b = plain.views[cam], again.views[cam]
        np.testing.assert_array_equal(a.depth, b.depth)  # geometry unchanged
        np.testing.assert_array_equal(a.object_ids, b.object_ids)
        diff = np.abs(a.image.astype(np.int16) - b.image.astype(np.int16)).sum(-1)
        cars = a.object_ids >= 0
        background = (a.surface == render.SURFACE) & ~cars
        assert np.mean(diff[background] > 0) > 0.3  # repainted
        # (road users keep their colours; only blur from the camera mixes in their borders)
        assert diff[cars].mean() < 0.2 * diff[background].mean()
    np.testing.assert_array_equal(plain.objects.bbox, again.objects.bbox)
    np.testing.assert_array_equal(plain.objects.location, again.objects.location)


def test_randomize_zero_and_undrawn_frames_are_the_frames_without_it():
    drawn = []
    for index in range(5):
        plain = make_frame(3, index, (94, 311))
        half = make_frame(3, index, (94, 311), randomize=0.5)
        drawn.append(not np.array_equal(plain.views[2].image, half.views[2].image))
        assert np.array_equal(plain.views[2].depth, half.views[2].depth)
    assert 1 <= sum(drawn) <= 4  # about half of the frames are randomized, the rest unchanged
    zero = make_frame(3, 4, (94, 311), randomize=0.0)
    np.testing.assert_array_equal(zero.views[2].image, plain.views[2].image)
    # (a dataset without it is described as before, so existing caches stay valid)
    assert "randomize" not in DatasetSpec(num_frames=4, seed=3).to_json()
    assert DatasetSpec(num_frames=4, seed=3, randomize=0.5).to_json()["randomize"] == 0.5
    with pytest.raises(ValueError, match="randomize"):
        DatasetSpec(num_frames=4, seed=3, randomize=1.5).validate()
