"""The detector's eval transform reproduces the authors' test chain on real KITTI frames.

Reference chain (visualDet3D, spec §1.5): ``ConvertToFloat -> CropTop(100) ->
Resize(288, keep aspect) -> crop/pad right to 1280 -> Normalize (ImageNet)``, the resize
in float32 with ``cv2.resize`` (bilinear). Two independent references are used: that
chain written out with cv2, and a float64 numpy bilinear resampler with cv2's sampling
grid (so the check does not rest on cv2 alone).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gac_jax.builders.detect3d import eval_transform
from gac_jax.config import load_config
from gac_jax.data import transforms as tr
from gac_jax.data.sources import KittiObjectSource

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "detect3d_kitti.py"


@pytest.fixture(scope="module")
def kitti_config():
    return load_config(str(CONFIG))


@pytest.fixture(scope="module")
def frames(kitti_object_root):
    src = KittiObjectSource(kitti_object_root, "labeled")
    return [src[i] for i in range(len(src))]


def _linear_weights(dst: int, src: int) -> tuple[np.ndarray, np.ndarray]:
    """cv2's INTER_LINEAR taps along one axis: index i0 (dst,) and weight of i0 + 1 (dst,)."""
    x = (np.arange(dst) + 0.5) * (src / dst) - 0.5
    i0 = np.floor(x).astype(np.int64)
    f = x - i0
    f[i0 < 0], i0[i0 < 0] = 0.0, 0
    last = i0 >= src - 1
    f[last], i0[last] = 0.0, src - 1
    return i0, f


def numpy_bilinear(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Float64 bilinear resize of an (H, W, C) image to ``size`` = (H', W') on cv2's grid."""
    img = np.asarray(image, np.float64)
    r0, fr = _linear_weights(size[0], img.shape[0])
    c0, fc = _linear_weights(size[1], img.shape[1])
    r1, c1 = np.minimum(r0 + 1, img.shape[0] - 1), np.minimum(c0 + 1, img.shape[1] - 1)
    rows = img[r0] * (1 - fr)[:, None, None] + img[r1] * fr[:, None, None]
    return rows[:, c0] * (1 - fc)[None, :, None] + rows[:, c1] * fc[None, :, None]


def reference_chain(image: np.ndarray, P2: np.ndarray, crop_top: int, height: int, width: int):
    """The authors' test chain written out: (0-255 float image before Normalize, P2 as they
    compute it, the network input after Normalize, the resized width)."""
    img = np.asarray(image, np.float32)[crop_top:]  # ConvertToFloat, CropTop
    P = np.array(P2, np.float64)
    P[1] -= crop_top * P[2]  # cy -= 100, P[1, 3] -= 100 P[2, 3]
    s = height / img.shape[0]
    new_w = int(round(img.shape[1] * s))
    img = cv2.resize(img, (new_w, height))  # float32 in, float32 out, bilinear
    P[:2] *= s  # the reference's scaling (no half-pixel term, one scale for x and y)
    out = np.zeros((height, width, 3), np.float32)
    out[:, : min(width, new_w)] = img[:, :width]
    mean = np.array([0.485, 0.456, 0.406], np.float32)
    std = np.array([0.229, 0.224, 0.225], np.float32)
    return out, P, (out / np.float32(255.0) - mean) / std, new_w


def test_eval_transform_matches_reference_float_pipeline(kitti_config, frames):
    d = kitti_config.data
    raw = eval_transform(kitti_config, normalize=False)
    full = eval_transform(kitti_config)
    uint8_worst = 0.0
    for sample in frames:
        h, w = sample["image"].shape[:2]
        ref_img, ref_P2, ref_input, new_w = reference_chain(
            sample["image"], sample["P2"], d.crop_top, d.height, d.width
        )
        out = raw(dict(sample))
        assert out["image"].dtype == np.float32 and out["image"].shape == ref_img.shape
        assert np.abs(out["image"] - ref_img).max() <= 1e-3, sample["frame_id"]
        independent = numpy_bilinear(sample["image"][d.crop_top :], (d.height, new_w))
        keep = min(d.width, new_w)
        np.testing.assert_allclose(out["image"][:, :keep], independent[:, :keep], atol=1e-3)
        # P2: crop then cv2's sampling grid u' = sx (u + 0.5) - 0.5 (exact up to rounding).
        P = np.array(sample["P2"], np.float64)
        P[1] -= d.crop_top * P[2]
        sx, sy = new_w / w, d.height / (h - d.crop_top)
        P[0] = sx * P[0] + (0.5 * sx - 0.5) * P[2]
        P[1] = sy * P[1] + (0.5 * sy - 0.5) * P[2]
        np.testing.assert_allclose(out["P2"], P, rtol=0, atol=1e-12)  # float64 rounding
        # The reference's P2 (one scale s, no half-pixel term) puts original pixels less than
        # 0.5 px away from where this P2 and the resampled image put them.
        s = d.height / (h - d.crop_top)
        ref_A = np.array([[s, 0.0, 0.0], [0.0, s, -s * d.crop_top], [0.0, 0.0, 1.0]])
        np.testing.assert_allclose(ref_P2, ref_A @ np.asarray(sample["P2"]), atol=1e-9)
        grid = np.array([[0.0, 0.0, 1.0], [w - 1, d.crop_top, 1.0], [w - 1, h - 1, 1.0]])
        shift = (grid @ out["image_transform"].T - grid @ ref_A.T)[:, :2]
        assert np.abs(shift).max() < 0.5
        net = full(dict(sample))["image"]
        np.testing.assert_allclose(net, ref_input, atol=1e-3 / 255 / 0.224)
        # The old uint8 resize is what this test rules out.
        uint8 = cv2.resize(sample["image"][d.crop_top :], (new_w, d.height))[:, :keep]
        uint8_worst = max(uint8_worst, float(np.abs(uint8 - ref_img[:, :keep]).max()))
    assert uint8_worst > 0.25  # a uint8 resize would fail the 1e-3 check by far


def test_resize_is_float_for_every_input_dtype(frames):
    """Resize always returns float32 (uint8 or float input); crops/pads keep that dtype."""
    sample = frames[0]
    a = tr.Resize(150, 500)(dict(sample))["image"]
    b = tr.Resize(150, 500)({**sample, "image": sample["image"].astype(np.float32)})["image"]
    assert a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    padded = tr.CropOrPadWidth(520)({**sample, "image": a})["image"]
    assert padded.dtype == np.float32 and not padded[:, 500:].any()


def test_authors_variant_gives_the_authors_p2(frames):
    """``configs/detect3d_kitti.py:authors`` scales P2 by 288/275 after the crop, as the
    reference does (the exact grid's 1301/1242 is the default), to float32 rounding of the
    network's P2 input; the pixels are the same as with the exact grid."""
    authors = load_config(f"{CONFIG}:authors")
    d = authors.data
    assert d.resize_calibration == "authors" and authors.model.gac.offset_formula == "reference_v1"
    grid = eval_transform(load_config(str(CONFIG)), normalize=False)
    chain = eval_transform(authors, normalize=False)
    for sample in frames:
        h, w = sample["image"].shape[:2]
        _, ref_P2, _, new_w = reference_chain(
            sample["image"], sample["P2"], d.crop_top, d.height, d.width
        )
        out = chain(dict(sample))
        np.testing.assert_allclose(out["P2"].astype(np.float32), ref_P2.astype(np.float32), 0, 0)
        exact = grid(dict(sample))
        np.testing.assert_array_equal(out["image"], exact["image"])
        s = d.height / (h - d.crop_top)
        assert out["P2"][0, 0] / sample["P2"][0, 0] == pytest.approx(s, rel=1e-12)
        assert exact["P2"][0, 0] / sample["P2"][0, 0] == pytest.approx(new_w / w, rel=1e-12)
        if (h, w) == (375, 1242):  # the common KITTI size: 288/275 against 1301/1242
            assert (s, new_w / w) == (288 / 275, 1301 / 1242)
        # original pixels map back through the same convention
        np.testing.assert_allclose(out["image_transform"] @ [0.0, d.crop_top, 1.0], [0, 0, 1])
