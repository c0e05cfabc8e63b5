"""Contrast and sharpening in the camera effects: hand-computed, off by default, and the other
effects' random draws unchanged by them."""

from __future__ import annotations

import cv2
import numpy as np

from gac_jax.data.camera_effects import CameraEffects

OFF = dict(p_gamma=0, p_white_balance=0, p_blur=0, p_noise=0, p_jpeg=0)


def _image(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(40, 200, (24, 40, 3)).astype(np.float32)


def _draws(seed: int):
    """The draws CameraEffects makes from a sample's stream, in order (float64 reference)."""
    rng = np.random.default_rng(seed)
    rng.random(5), rng.uniform(0.7, 1.4), rng.uniform(0.85, 1.15, size=3)
    rng.uniform(0.3, 1.2), rng.uniform(1.0, 6.0), rng.integers(30, 91)
    return rng.random(2), rng.uniform(1.0, 1.8), rng.uniform(0.5, 2.0), rng.uniform(0.7, 1.5)


def test_contrast_is_a_gain_about_the_image_mean():
    image = _image()
    out = CameraEffects(**OFF, p_contrast=1.0)({"image": image, "rng": np.random.default_rng(3)})
    _, c, _, _ = _draws(3)
    mean = image.astype(np.float64).mean()
    want = np.clip(mean + c * (image.astype(np.float64) - mean), 0, 255)
    np.testing.assert_allclose(out["image"], want, atol=1e-3)
    assert out["image"].std() > image.std()


def test_sharpening_is_an_unsharp_mask_and_adds_fine_detail():
    image = cv2.GaussianBlur(_image(1), (0, 0), 1.5)
    out = CameraEffects(**OFF, p_sharpen=1.0)({"image": image, "rng": np.random.default_rng(5)})
    _, _, amount, sigma = _draws(5)
    soft = cv2.GaussianBlur(image, (0, 0), sigma)
    want = np.clip(image + amount * (image - soft), 0, 255)
    np.testing.assert_allclose(out["image"], want, atol=1e-3)

    def detail(x):
        return np.abs(x - cv2.GaussianBlur(x, (0, 0), 1.0)).mean()

    assert detail(out["image"]) > 1.4 * detail(image)


def test_off_by_default_and_the_other_effects_draw_as_before():
    image = _image(2)
    sample = {"image": image, "rng": None, "P2": np.eye(3, 4)}
    default = CameraEffects(p_gamma=1, p_white_balance=1, p_blur=1, p_noise=0, p_jpeg=1)
    plain = default({**sample, "rng": np.random.default_rng(7)})
    # the same effects with contrast and sharpening drawn but never applied: the same image
    # (the noise, drawn after them, is left out: its draws move when they are on)
    never = CameraEffects(
        p_gamma=1, p_white_balance=1, p_blur=1, p_noise=0, p_jpeg=1, p_contrast=1e-12
    )
    np.testing.assert_array_equal(
        never({**sample, "rng": np.random.default_rng(7)})["image"], plain["image"]
    )
    on = CameraEffects(p_contrast=1.0, p_sharpen=1.0)({**sample, "rng": np.random.default_rng(7)})
    assert on["P2"] is sample["P2"]  # pixels only
    assert CameraEffects().p_contrast == 0.0 and CameraEffects().p_sharpen == 0.0


def test_from_config_with_and_without_the_keys():
    import ml_collections

    from gac_jax.data.camera_effects import from_config

    old = from_config(ml_collections.ConfigDict({"camera_effects": True}))  # an older run folder
    assert old.p_contrast == 0.0 and old.p_sharpen == 0.0
    on = from_config(ml_collections.ConfigDict({"sharpen_contrast": True}))
    assert on.p_contrast == on.p_sharpen == 0.8
    assert on.contrast == (1.0, 1.8) and on.sharpen == (0.5, 2.0)
    tuned = from_config(
        ml_collections.ConfigDict(
            {
                "sharpen_contrast": True,
                "sharpen_contrast_share": 1.0,
                "contrast_range": (1.2, 2.2),
                "sharpen_range": (1.0, 3.0),
            }
        )
    )
    assert tuned.p_contrast == tuned.p_sharpen == 1.0
    assert tuned.contrast == (1.2, 2.2) and tuned.sharpen == (1.0, 3.0)
