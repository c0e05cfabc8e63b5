"""Random convolutions as a training augmentation: pixels only, the filter against a float64
reference, each channel's mean and spread kept, deterministic per sample stream (the config
key and the CLI: tests/test_appearance_ops.py)."""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.data.random_convolution import RandomConvolution, random_filter
from tests.test_cast_shadows import random_sample

SIZE = (40, 96)


def _sample(seed: int = 0) -> dict:
    return random_sample(seed, SIZE)


def _reference(x: np.ndarray, w: np.ndarray) -> np.ndarray:
    """float64 correlation with reflected borders (numpy's 'reflect' leaves the edge pixel
    out, as OpenCV's BORDER_REFLECT_101), then each channel to the input's mean and std."""
    x = x.astype(np.float64)
    k = w.shape[-1]
    r = k // 2
    pad = np.pad(x, ((r, r), (r, r), (0, 0)), mode="reflect")
    H, W = x.shape[:2]
    y = np.zeros((H, W, w.shape[0]))
    for dv in range(k):
        for du in range(k):
            y += np.einsum("hwi,oi->hwo", pad[dv : dv + H, du : du + W], w[:, :, dv, du])
    y = (y - y.mean((0, 1))) / y.std((0, 1))
    return y * x.std((0, 1)) + x.mean((0, 1))


@pytest.mark.parametrize("k", [1, 3, 5])
def test_the_filter_matches_a_float64_reference(k):
    g = np.random.default_rng(k)
    x = g.uniform(0, 255, SIZE + (3,)).astype(np.float32)
    w = g.normal(0, 1 / np.sqrt(3 * k * k), (3, 3, k, k))
    out = random_filter(x, w)
    assert out.dtype == np.float32 and out.shape == x.shape
    np.testing.assert_allclose(out, _reference(x, w), rtol=1e-4, atol=2e-3)


def test_a_one_by_one_kernel_mixes_the_channels_of_each_pixel():
    x = np.zeros(SIZE + (3,), np.float32)
    x[..., 0], x[..., 1] = 10.0, 200.0
    x[:, : SIZE[1] // 2, 2] = 50.0  # channel 2 varies; 0 and 1 are constant
    w = np.zeros((3, 3, 1, 1))
    w[0, 2], w[1, 2], w[2, 2] = 1.0, -1.0, 0.5
    out = random_filter(x, w)
    # each output channel is (a copy of) channel 2 moved to its own input channel's spread:
    # a constant input channel keeps its value everywhere, so channels 0 and 1 stay flat
    np.testing.assert_allclose(out[..., 0], 10.0, atol=1e-3)
    np.testing.assert_allclose(out[..., 1], 200.0, atol=1e-3)
    left, right = out[:, : SIZE[1] // 2, 2], out[:, SIZE[1] // 2 :, 2]
    np.testing.assert_allclose(left, 50.0, atol=1e-3)  # the same spread, the same sign
    np.testing.assert_allclose(right, 0.0, atol=1e-3)


def test_only_the_pixels_change_within_range():
    sample = _sample()
    t = RandomConvolution(p=1.0, mix=(0.0, 0.0))
    out = t(sample)
    assert out["image"].shape == sample["image"].shape and out["image"].dtype == np.float32
    for key in ("P2", "depth", "objects"):
        assert out[key] is sample[key]
    assert out["image"].min() >= 0.0 and out["image"].max() <= 255.0
    assert not np.allclose(out["image"], sample["image"], atol=5.0)


def test_the_blend_weight_one_is_the_image():
    sample = _sample(1)
    out = RandomConvolution(p=1.0, mix=(1.0, 1.0))(sample)["image"]
    np.testing.assert_allclose(out, sample["image"], atol=1e-3)


def test_deterministic_per_stream_and_off_at_zero():
    t = RandomConvolution(p=1.0)
    a = t(_sample(3))["image"]
    np.testing.assert_array_equal(a, t(_sample(3))["image"])
    b = t(dict(_sample(3), rng=np.random.default_rng(4)))["image"]
    assert not np.array_equal(a, b)
    sample = _sample(3)
    np.testing.assert_array_equal(RandomConvolution(p=0.0)(sample)["image"], sample["image"])
    with pytest.raises(ValueError, match="not in"):
        RandomConvolution(p=1.5)
    with pytest.raises(ValueError, match="odd"):
        RandomConvolution(kernel_sizes=(1, 4))


def test_the_share_of_filtered_images_is_p():
    t = RandomConvolution(p=0.3, mix=(0.0, 0.0))
    g = np.random.default_rng(0)
    image = np.random.default_rng(1).uniform(0, 255, (12, 16, 3)).astype(np.float32)
    hit = [not np.array_equal(t({"image": image, "rng": g})["image"], image) for _ in range(400)]
    assert 0.24 < np.mean(hit) < 0.36
