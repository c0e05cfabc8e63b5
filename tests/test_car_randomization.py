"""Domain randomization of the cars (``randomize_cars``): random paint, pattern, window tint
and tyre shades on part of the cars, in a share of frames; shape, boxes and labels unchanged."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from gac_jax.data.synthetic import domain_randomization, render, shapes
from gac_jax.data.synthetic.frame import make_frame
from gac_jax.data.synthetic.scene import SceneObject
from gac_jax.data.synthetic.writer import DatasetSpec

SIZE = (188, 621)


def _car(seed: int) -> SceneObject:
    rng = np.random.default_rng(seed)
    parts = shapes.car_parts(1.5, 1.6, 3.9, np.array([0.6, 0.1, 0.1]), rng)
    return SceneObject("Car", np.array([1.5, 1.6, 3.9]), np.zeros(3), 0.0, parts, 0.0)


def test_a_repainted_car_keeps_its_shape_and_gets_one_random_look():
    car = _car(0)
    walker = SceneObject("Pedestrian", np.array([1.7, 0.6, 0.8]), np.zeros(3), 0.0, [], 0.0)
    rng = np.random.default_rng(1)
    out = None
    for _ in range(20):  # (a car is repainted with probability CAR_SHARE)
        out = domain_randomization.randomize_cars([car, walker], rng, 1.0)
        if out[0] is not car:
            break
    assert out is not None and out[0] is not car
    assert out[1] is walker  # other road users are untouched
    new = out[0]
    assert len(new.parts) == len(car.parts) == 8
    for a, b in zip(car.parts, new.parts, strict=True):  # the same solids: geometry unchanged
        np.testing.assert_array_equal(a.vertices, b.vertices)
        np.testing.assert_array_equal(a.normals, b.normals)
        np.testing.assert_array_equal(a.offsets, b.offsets)
    body, cabin, m0, m1 = new.parts[:4]
    assert np.all(body.materials == shapes.RANDOM)  # no lights, plate, arches or seams
    assert len(body.params) == 8 and 0.05 <= body.params[1] <= 1.5  # pattern period (m)
    np.testing.assert_array_equal(cabin.materials, car.parts[1].materials)
    glass = cabin.colors[cabin.materials == shapes.GLASS]
    assert np.all(glass == glass[0]) and glass[0].max() <= 0.6  # one tint, no brighter
    roof = cabin.colors[cabin.materials == shapes.FLAT][0]
    np.testing.assert_allclose(m0.colors, np.tile(roof, (len(m0.offsets), 1)))  # mirrors: paint
    np.testing.assert_allclose(m1.colors, m0.colors)
    assert cabin.params[1:] == car.parts[1].params[1:]  # the window's extent stays
    assert not np.allclose(body.colors.mean(0), car.parts[0].colors.mean(0))
    wheels = new.parts[4:]
    assert all(np.array_equal(w.colors, wheels[0].colors) for w in wheels)
    # the input is not modified
    assert np.all(car.parts[0].materials != shapes.RANDOM)


def test_randomized_cars_change_the_cars_pixels_only():
    plain = make_frame(0, 11, SIZE)
    again = make_frame(0, 11, SIZE, randomize_cars=1.0)
    other = make_frame(0, 11, SIZE, randomize_cars=1.0)
    np.testing.assert_array_equal(again.views[2].image, other.views[2].image)  # per seed
    changed = 0
    for cam in (2, 3):
        a, b = plain.views[cam], again.views[cam]
        np.testing.assert_array_equal(a.depth, b.depth)  # geometry unchanged
        np.testing.assert_array_equal(a.object_ids, b.object_ids)
        diff = np.abs(a.image.astype(np.int16) - b.image.astype(np.int16)).sum(-1)
        cars = a.object_ids >= 0
        far = ~cars & (a.surface == render.SURFACE)
        # (the camera's blur mixes the repainted cars into their borders, its motion blur
        # along the rows a few pixels more; farther away nothing changes)
        grown = np.zeros_like(cars)
        ys, xs = np.nonzero(cars)
        for dy in range(-3, 4):
            for dx in range(-6, 7):
                grown[np.clip(ys + dy, 0, SIZE[0] - 1), np.clip(xs + dx, 0, SIZE[1] - 1)] = True
        assert diff[far & ~grown].max(initial=0) == 0
        changed += int(diff[cars].mean() > 5)
    assert changed == 2
    for field in ("bbox", "location", "dimensions", "rotation_y", "occluded", "truncated"):
        np.testing.assert_array_equal(getattr(plain.objects, field), getattr(again.objects, field))


def test_randomize_cars_zero_and_undrawn_frames_are_the_frames_without_it():
    drawn = []
    for index in range(6):
        plain = make_frame(3, index, (94, 311))
        half = make_frame(3, index, (94, 311), randomize_cars=0.5)
        drawn.append(not np.array_equal(plain.views[2].image, half.views[2].image))
    assert 1 <= sum(drawn) <= 5  # about half of the frames, the others unchanged
    zero = make_frame(3, 5, (94, 311), randomize_cars=0.0)
    np.testing.assert_array_equal(zero.views[2].image, plain.views[2].image)
    # (a dataset without it is described as before, so existing caches stay valid)
    assert "randomize_cars" not in DatasetSpec(num_frames=4, seed=3).to_json()
    spec = DatasetSpec(num_frames=4, seed=3, randomize_cars=0.5)
    assert spec.to_json()["randomize_cars"] == 0.5
    with pytest.raises(ValueError, match="randomize_cars"):
        DatasetSpec(num_frames=4, seed=3, randomize_cars=-0.1).validate()


def test_background_randomization_draws_as_before():
    # the frame of test_randomized_background_repaints_the_background_only, both views, as
    # the background randomization drew it before the cars could be randomized too
    frame = make_frame(0, 11, SIZE, randomize=1.0)
    digest = hashlib.sha256(frame.views[2].image.tobytes() + frame.views[3].image.tobytes())
    assert digest.hexdigest() == "26c30a82d5baf66c485c2b6e5b218444ee584f31524c2aa098d46ad1a7750a6e"
