"""Vans and trucks among the road users (``large_vehicles``): labelled ``Van`` / ``Truck`` with
KITTI's sizes, projected onto their own pixels, drawn from their own stream (the rest of the
scene is unchanged), deterministic per seed, and background to a Car detector."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.loader import detection_arrays
from gac_jax.data.synthetic import vehicles
from gac_jax.data.synthetic.__main__ import main as cli_main
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.geometry import box2d_from_corners, box3d_corners
from tests.share_options import check_described_and_named, check_deterministic_and_zero

SIZE = (188, 621)
FRAMES = (0, 2, 3)  # frames of seed 0 whose vans and trucks are labelled (not all DontCare)


@pytest.fixture(scope="module")
def pairs():
    return [(make_frame(0, i, SIZE), make_frame(0, i, SIZE, large_vehicles=1.0)) for i in FRAMES]


def test_vans_and_trucks_are_labelled_with_kitti_sizes_on_their_pixels(pairs):
    seen = set()
    for _, frame in pairs:
        objects = frame.objects
        ids = frame.views[2].object_ids
        for line, k in enumerate(frame.label_source):
            kind = objects.type[line]
            if kind not in vehicles.SIZES:
                continue
            seen.add(kind)
            obj = frame.scene.objects[k]
            assert obj.type == kind
            for value, (mean, sd) in zip(
                objects.dimensions[line], vehicles.SIZES[kind], strict=True
            ):
                assert abs(value - mean) <= 2.5 * sd + 0.005  # KITTI's statistics, clipped
            # the label's 2D box is the clipped projection of its 3D box, around its pixels
            corners = box3d_corners(obj.location[None], obj.dimensions[None], [obj.rotation_y])
            projected = box2d_from_corners(corners, frame.calib.P2, SIZE)[0]
            np.testing.assert_allclose(objects.bbox[line], projected, atol=0.006)
            rr, cc = np.nonzero(ids == k)
            assert len(rr) > 0
            box = objects.bbox[line]
            assert cc.min() >= box[0] - 1 and cc.max() <= box[2] + 1
            assert rr.min() >= box[1] - 1 and rr.max() <= box[3] + 1
    assert seen == {"Van", "Truck"}


def test_the_rest_of_the_scene_is_the_frame_without_them(pairs):
    for plain, frame in pairs:
        others = [o for o in frame.scene.objects if o.type not in vehicles.SIZES]
        assert len(others) == len(plain.scene.objects)
        assert len(frame.scene.objects) > len(plain.scene.objects)
        for a, b in zip(plain.scene.objects, others, strict=True):
            assert a.type == b.type and a.rotation_y == b.rotation_y
            np.testing.assert_array_equal(a.location, b.location)
            np.testing.assert_array_equal(a.dimensions, b.dimensions)
        np.testing.assert_array_equal(plain.scene.sun, frame.scene.sun)  # the same light
        np.testing.assert_array_equal(plain.calib.P2, frame.calib.P2)


def test_deterministic_per_seed_and_zero_is_the_frame_without_them(pairs):
    plain, frame = pairs[0]
    check_deterministic_and_zero("large_vehicles", FRAMES[0], SIZE, plain, frame)
    drawn = [
        any(
            o.type in vehicles.SIZES
            for o in make_frame(3, i, (94, 311), large_vehicles=0.5).scene.objects
        )
        for i in range(8)
    ]
    assert 1 <= sum(drawn) <= 7  # about half of the frames


def test_a_car_detector_learns_them_as_background(pairs):
    _, frame = pairs[0]
    sample = dict(
        objects=frame.objects, P2=frame.calib.P2, frame_id="000000", image=frame.views[2].image,
        image_transform=np.eye(3), original_size=SIZE,
    )  # fmt: skip
    arrays = detection_arrays(sample, ["Car"], max_objects=32)  # (KITTI's classes: Car only)
    cars = int(np.sum(frame.objects.type == "Car"))
    vehicles_too = int(np.isin(frame.objects.type, ["Car", "Van", "Truck"]).sum())
    assert int(np.sum(arrays["gt_mask"])) == cars < vehicles_too


def test_dataset_description_cache_folder_and_cli():
    check_described_and_named("large_vehicles", 0.3, invalid=1.5)


def test_cli_refuses_it_for_clips(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli_main(["--out", str(tmp_path / "c"), "--sequences", "1", "--frames-per-sequence", "2",
                  "--large-vehicles", "0.5"])  # fmt: skip
    assert e.value.code == 2
    assert "--large-vehicles: for frames only" in capsys.readouterr().err
