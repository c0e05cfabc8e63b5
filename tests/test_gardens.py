"""Front gardens (``gardens``): an urban roadside's buildings set back by the garden's depth
behind lawns, hedges and trees; drawn from their own stream (the rest of the scene is the
frame without them), deterministic per seed, labels still on their pixels."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.synthetic import gardens, shapes
from gac_jax.data.synthetic.__main__ import main as cli_main
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.data.synthetic.roadside import ROAD_END
from tests.share_options import check_described_and_named, check_deterministic_and_zero

SIZE = (188, 621)
FRAMES = (3, 11)  # frames of seed 0 with urban roadsides


@pytest.fixture(scope="module")
def pairs():
    return [(make_frame(0, i, SIZE), make_frame(0, i, SIZE, gardens=1.0)) for i in FRAMES]


def _road(scene, solid) -> np.ndarray:
    """(8, 3) road coordinates ``(t, y, s)`` of a background solid's vertices."""
    return (solid.vertices - scene.road_translation) @ scene.road_rotation


def _facades(scene) -> list:
    """The buildings along the road (not the skyline beyond its end)."""
    return [
        s
        for s in scene.background
        if shapes.FACADE in s.materials.tolist() and _road(scene, s)[:, 2].min() < ROAD_END
    ]


def test_buildings_stand_back_by_the_gardens_depth(pairs):
    shifted_sides = 0
    for plain, frame in pairs:
        a, b = _facades(plain.scene), _facades(frame.scene)
        assert len(a) == len(b) > 0  # the same buildings (their own draws)
        shifts = {-1: set(), 1: set()}
        for sa, sb in zip(a, b, strict=True):
            ta, tb = _road(plain.scene, sa)[:, 0], _road(frame.scene, sb)[:, 0]
            np.testing.assert_allclose(tb - ta, (tb - ta)[0], atol=1e-6)  # moved, not changed
            side = 1 if ta.mean() > 0 else -1
            shifts[side].add(round(float(side * (tb - ta)[0]), 6))
        for values in shifts.values():
            assert len(values) <= 1  # one depth per side
            for depth in values - {0.0}:
                assert gardens.DEPTH_RANGE[0] <= depth <= gardens.DEPTH_RANGE[1]
                shifted_sides += 1
    assert shifted_sides >= 2


def test_the_rest_of_the_scene_is_the_frame_without_them(pairs):
    for plain, frame in pairs:
        assert len(frame.scene.background) > len(plain.scene.background)  # lawns, hedges, trees
        assert len(frame.scene.objects) == len(plain.scene.objects)
        for a, b in zip(plain.scene.objects, frame.scene.objects, strict=True):
            assert a.type == b.type and a.rotation_y == b.rotation_y
            np.testing.assert_array_equal(a.location, b.location)
            np.testing.assert_array_equal(a.dimensions, b.dimensions)
        np.testing.assert_array_equal(plain.scene.sun, frame.scene.sun)  # the same light
        np.testing.assert_array_equal(plain.calib.P2, frame.calib.P2)
        # what lies behind the back of the sidewalk moved farther away: deeper depth maps
        valid = (plain.views[2].depth > 0) & (frame.views[2].depth > 0)
        assert np.median(frame.views[2].depth[valid] - plain.views[2].depth[valid]) >= 0.0
        assert np.mean(frame.views[2].depth[valid] > plain.views[2].depth[valid] + 1.0) > 0.02


def test_labels_still_lie_on_their_pixels(pairs):
    for _, frame in pairs:
        ids = frame.views[2].object_ids
        for line, k in enumerate(frame.label_source):
            if frame.objects.type[line] == "DontCare":
                continue
            rr, cc = np.nonzero(ids == k)
            if len(rr) == 0:
                continue
            box = frame.objects.bbox[line]
            assert cc.min() >= box[0] - 1 and cc.max() <= box[2] + 1
            assert rr.min() >= box[1] - 1 and rr.max() <= box[3] + 1


def test_deterministic_per_seed_and_zero_is_the_frame_without_them(pairs):
    plain, frame = pairs[0]
    check_deterministic_and_zero("gardens", FRAMES[0], SIZE, plain, frame, depth=True)


def test_plan_gives_an_urban_side_gardens_with_the_share():
    rng = np.random.default_rng(0)
    urban = {-1: "urban", 1: "urban"}
    depths = np.array([list(gardens.plan(rng, 0.5, urban).values()) for _ in range(400)])
    assert 0.4 < np.mean(depths > 0) < 0.6
    drawn = depths[depths > 0]
    assert drawn.min() >= gardens.DEPTH_RANGE[0] and drawn.max() <= gardens.DEPTH_RANGE[1]
    # an open roadside never has them; the stream advances the same way whatever the sides
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    assert gardens.plan(a, 1.0, {-1: "open", 1: "urban"})[-1] == 0.0
    gardens.plan(b, 1.0, urban)
    assert a.random() == b.random()


def test_dataset_description_cache_folder_and_cli(tmp_path, capsys):
    check_described_and_named("gardens", 0.3, invalid=-0.1)
    with pytest.raises(SystemExit) as e:
        cli_main(["--out", str(tmp_path / "c"), "--sequences", "1", "--frames-per-sequence", "2",
                  "--gardens", "0.5"])  # fmt: skip
    assert e.value.code == 2
    assert "--gardens: for frames only" in capsys.readouterr().err
