"""Photo textures (``data.synthetic.photo``): the photographs, their mip pyramid and lookup,
and frames that change in their background's look only."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

from gac_jax.data.synthetic import photo_textures, render, shapes
from gac_jax.data.synthetic.frame import make_frame
from tests.share_options import check_described_and_named


def test_textures_are_the_vendored_photographs_and_their_pyramid_averages_2x2():
    for name, digest in photo_textures.TEXTURES.items():
        data = (photo_textures.TEXTURE_DIR / f"{name}.png").read_bytes()
        assert hashlib.sha256(data).hexdigest() == digest
    for levels in photo_textures.pyramids():
        top = levels[0].astype(np.float64)
        assert top.shape == (1024, 1024)
        assert abs(top.mean()) < 1e-4 and abs(top.std() - 1.0) < 1e-4
        # mirrored: the tile wraps around without a seam
        np.testing.assert_array_equal(top[:, 511], top[:, 512])
        np.testing.assert_array_equal(top[0], top[-1])
        for fine, coarse in zip(levels[:-1], levels[1:], strict=True):
            n = coarse.shape[0]
            mean = fine.astype(np.float64).reshape(n, 2, n, 2).mean(axis=(1, 3))
            np.testing.assert_allclose(coarse, mean, atol=1e-5)
        assert levels[-1].shape == (4, 4)
        # far away the averaged photograph is smooth: detail shrinks with the mip level
        assert levels[6].std() < 0.5 * levels[0].std()


def test_sample_reads_the_level_of_the_pixels_footprint():
    levels = photo_textures.pyramids()[photo_textures.GRASS]
    metres = 2.0  # one photograph spans 2 m: 1024 texels per 4 m of the mirrored tile
    a = np.array([0.0, 1.0, 3.99, -0.001, 1.0, 1.0])
    b = np.array([0.0, 0.5, 3.99, 0.0, 0.5, 0.5])
    footprint = np.array([0.001, 0.001, 0.001, 0.001, 4.0 / 256, 1e3])
    got = photo_textures.sample(photo_textures.GRASS, a, b, metres, footprint)
    tpm = 256.0  # texels per metre at level 0
    assert got[0] == levels[0][0, 0]
    assert got[1] == levels[0][int(0.5 * tpm), int(1.0 * tpm)]
    assert got[2] == levels[0][1021, 1021]
    assert got[3] == levels[0][0, 1023]  # wraps around
    # a pixel 4 texels wide reads level 2; a huge one the coarsest level
    assert got[4] == levels[2][int(0.5 * tpm / 4), int(1.0 * tpm / 4)]
    assert got[5] == levels[-1][int(0.5 * 4 / 4.0), int(1.0 * 4 / 4.0)]


def test_a_changed_texture_file_is_refused(tmp_path, monkeypatch):
    for name in photo_textures.TEXTURES:
        data = (photo_textures.TEXTURE_DIR / f"{name}.png").read_bytes()
        (tmp_path / f"{name}.png").write_bytes(data)
    image = cv2.imread(str(tmp_path / "gravel.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(tmp_path / "gravel.png"), 255 - image)
    monkeypatch.setattr(photo_textures, "TEXTURE_DIR", tmp_path)
    photo_textures.pyramids.cache_clear()
    try:
        with pytest.raises(ValueError, match=r"gravel\.png: not the texture"):
            photo_textures.pyramids()
    finally:
        monkeypatch.undo()
        photo_textures.pyramids.cache_clear()


def test_photo_frames_change_the_backgrounds_look_only():
    plain = make_frame(0, 17, (188, 621))
    photo = make_frame(0, 17, (188, 621), photo=1.0)
    again = make_frame(0, 17, (188, 621), photo=1.0)
    np.testing.assert_array_equal(photo.views[2].image, again.views[2].image)  # per seed
    assert photo.scene.road.verge_photo is not None and plain.scene.road.verge_photo is None
    assert any(np.any(s.materials == shapes.PHOTO) for s in photo.scene.background)
    for cam in (2, 3):
        a, b = plain.views[cam], photo.views[cam]
        np.testing.assert_array_equal(a.depth, b.depth)  # geometry unchanged
        np.testing.assert_array_equal(a.object_ids, b.object_ids)
        diff = np.abs(a.image.astype(np.int16) - b.image.astype(np.int16)).sum(-1)
        cars = a.object_ids >= 0
        ground = a.surface == render.GROUND
        solids = (a.surface == render.SURFACE) & ~cars
        assert np.mean(diff[ground] > 0) > 0.1  # the verges
        assert np.mean(diff[solids] > 0) > 0.1  # foliage, fences, boxes
        # (road users keep their look; only blur from the camera mixes in their borders)
        assert diff[cars].mean() < 0.2 * diff[solids].mean()
    for field in ("bbox", "location", "dimensions", "rotation_y", "truncated", "occluded"):
        np.testing.assert_array_equal(getattr(plain.objects, field), getattr(photo.objects, field))
    np.testing.assert_array_equal(plain.calib.P2, photo.calib.P2)


def test_photo_zero_and_undrawn_frames_are_the_frames_without_it():
    drawn = []
    for index in range(3, 7):
        plain = make_frame(3, index, (94, 311))
        half = make_frame(3, index, (94, 311), photo=0.5)
        drawn.append(not np.array_equal(plain.views[2].image, half.views[2].image))
        assert np.array_equal(plain.views[2].depth, half.views[2].depth)
    assert 1 <= sum(drawn) <= 3  # about half of the frames have photo textures
    zero = make_frame(3, 6, (94, 311), photo=0.0)
    np.testing.assert_array_equal(zero.views[2].image, plain.views[2].image)
    check_described_and_named("photo", 0.5, invalid=-0.1)
    check_described_and_named("photo", 1.0, invalid=-0.1)  # (folder "_ph1")
