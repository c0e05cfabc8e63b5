"""Cast shadows as a training augmentation: pixels only, darker and bluer inside the shadow,
nothing above the ground rows, deterministic per sample stream (the config key and the CLI:
tests/test_appearance_ops.py)."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.cast_shadows import CastShadows, dapple_mask, polygon_mask

SIZE = (96, 320)


def random_sample(seed: int = 0, size: tuple[int, int] = SIZE) -> dict:
    """A training sample of random pixels and depths (pixel augmentations' tests)."""
    g = np.random.default_rng(100 + seed)
    return {
        "image": g.uniform(30, 230, size + (3,)).astype(np.float32),
        "P2": np.array(
            [[700.0, 0, size[1] / 2, 40], [0, 700.0, size[0] / 2, 0.2], [0, 0, 1, 0.004]]
        ),
        "depth": g.uniform(1, 80, size).astype(np.float32),
        "objects": object(),
        "rng": np.random.default_rng(seed),
    }


def test_only_the_pixels_change_and_only_darker():
    sample = random_sample()
    out = CastShadows(p=1.0)(dict(sample, rng=np.random.default_rng(1)))
    assert out["image"].shape == sample["image"].shape and out["image"].dtype == np.float32
    for key in ("P2", "depth", "objects"):
        assert out[key] is sample[key]
    assert np.all(out["image"] <= sample["image"] + 1e-4)
    assert (out["image"] < sample["image"] - 1.0).any()


def test_a_shadow_removes_the_drawn_share_of_the_light_bluer_than_red():
    t = CastShadows(p=1.0, darkness=(0.5, 0.5), blue=(0.2, 0.2), edge_sigma=(0.3, 0.3))
    image = np.full(SIZE + (3,), 200.0, np.float32)
    for seed in range(5):
        out = t({"image": image, "rng": np.random.default_rng(seed)})["image"]
        inside = out[..., 0] < 150.0
        assert inside.any()
        core = inside & (np.abs(out[..., 0] - 100.0) < 1e-3)  # fully in shadow: 1 - d of red
        assert core.sum() > 0.5 * inside.sum()
        # green keeps (1 - d)(1 + b / 2), blue (1 - d)(1 + b): the skylight's tint
        np.testing.assert_allclose(out[core][:, 1], 200 * 0.5 * 1.1, rtol=1e-5)
        np.testing.assert_allclose(out[core][:, 2], 200 * 0.5 * 1.2, rtol=1e-5)
        np.testing.assert_array_equal(out[~inside & (out[..., 2] >= 200)], 200.0)


def test_the_rows_above_top_are_never_touched():
    t = CastShadows(p=1.0, max_shadows=6, edge_sigma=(2.0, 2.0), top=0.4)
    top = int(np.ceil(0.4 * SIZE[0]))
    for seed in range(20):
        sample = random_sample(seed)
        out = t(sample)["image"]
        np.testing.assert_array_equal(out[:top], sample["image"][:top])


def test_deterministic_per_stream_and_off_at_zero():
    t = CastShadows(p=1.0)
    a = t(random_sample(3))["image"]
    np.testing.assert_array_equal(a, t(random_sample(3))["image"])
    b = t(dict(random_sample(3), rng=np.random.default_rng(4)))["image"]
    assert not np.array_equal(a, b)
    sample = random_sample(3)
    np.testing.assert_array_equal(CastShadows(p=0.0)(sample)["image"], sample["image"])
    with pytest.raises(ValueError, match="not in"):
        CastShadows(p=1.5)


def test_the_share_of_shadowed_images_is_p():
    t = CastShadows(p=0.3)
    g = np.random.default_rng(0)
    image = np.full((24, 40, 3), 128.0, np.float32)
    hit = [not np.array_equal(t({"image": image, "rng": g})["image"], image) for _ in range(400)]
    assert 0.24 < np.mean(hit) < 0.36


def test_shapes_lie_below_top_and_dapples_have_sunlit_holes():
    g = np.random.default_rng(0)
    for _ in range(30):
        m = polygon_mask(g, SIZE, 0.3)
        rows = np.nonzero(m.max(axis=1) > 0)[0]
        assert rows.size and rows.min() >= int(0.3 * SIZE[0]) - 1
    covers = []
    for _ in range(30):
        m = dapple_mask(g, SIZE, 0.3)
        ellipse_rows = np.nonzero(m.max(axis=1) > 0)[0]
        assert ellipse_rows.size
        covers.append(m.mean())
    assert 0.0 < np.median(covers) < 0.5  # crowns of part of the image, with holes
