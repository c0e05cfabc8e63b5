"""Anchor generation: hand-checked sizes, counts, ordering and bins."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from gac_jax.detection.anchors import AnchorLayout, box_iou_np, generate_anchors, nearest_bin

REFERENCE_SIZES = [24.0, 28.5, 33.9, 40.4, 48.0, 57.1, 67.9, 80.7, 96.0, 114.2, 135.8, 161.5]
REFERENCE_SIZES += [192.0, 228.3, 271.5, 322.9]


def test_sizes_and_counts_of_the_reference_layout():
    layout = AnchorLayout(image_size=(288, 1280))
    np.testing.assert_allclose(np.round(layout.sizes, 1), REFERENCE_SIZES)
    assert layout.feature_size == (18, 80)
    assert layout.anchors_per_cell == 32
    assert layout.num_anchors == 18 * 80 * 32 == 46080
    anchors = generate_anchors(layout)
    assert anchors.boxes.shape == (46080, 4) and len(anchors) == 46080


def test_feature_size_is_ceil_of_the_image_over_the_stride():
    assert AnchorLayout(image_size=(289, 1281)).feature_size == (19, 81)
    assert AnchorLayout(image_size=(64, 256)).feature_size == (4, 16)


def test_ordering_is_row_col_ratio_scale():
    layout = AnchorLayout(image_size=(288, 1280))
    anchors = generate_anchors(layout)
    wf, a_per = 80, 32
    # First anchor: cell (0, 0), ratio 0.5 (wide), scale 1: w = 24 / sqrt(0.5), h = 24 * sqrt(0.5).
    w0, h0 = 24 / math.sqrt(0.5), 24 * math.sqrt(0.5)
    np.testing.assert_allclose(anchors.boxes[0], [8 - w0 / 2, 8 - h0 / 2, 8 + w0 / 2, 8 + h0 / 2])
    # Cell (row 3, col 7), ratio 1 (index 1), scale index 5: size 24 * 2^(5/4), square.
    row, col, ratio_idx, scale_idx = 3, 7, 1, 5
    n = (row * wf + col) * a_per + ratio_idx * 16 + scale_idx
    size = 24 * 2 ** (5 / 4)
    cu, cv = (col + 0.5) * 16, (row + 0.5) * 16
    np.testing.assert_allclose(anchors.centers[n], [cu, cv])
    np.testing.assert_allclose(anchors.shapes[n], [size, size])
    np.testing.assert_allclose(
        anchors.boxes[n], [cu - size / 2, cv - size / 2, cu + size / 2, cv + size / 2]
    )
    assert anchors.bin_index[n] == 16 + 5
    assert anchors.scale_index[n] == 5 and anchors.ratio_index[n] == 1
    # The last anchor is in the bottom-right cell, square, largest scale.
    np.testing.assert_allclose(anchors.centers[-1], [1272.0, 280.0])
    np.testing.assert_allclose(anchors.shapes[-1], [24 * 2 ** (15 / 4)] * 2)
    # The centre is constant within a cell and advances by the stride along the row.
    assert np.all(anchors.centers[:32] == anchors.centers[0])
    np.testing.assert_allclose(anchors.centers[32] - anchors.centers[0], [16.0, 0.0])
    np.testing.assert_allclose(anchors.centers[wf * 32] - anchors.centers[0], [0.0, 16.0])


def test_multiclass_ratios_give_48_anchors_with_tall_boxes():
    layout = AnchorLayout(image_size=(288, 1280), ratios=(0.5, 1.0, 2.0))
    anchors = generate_anchors(layout)
    assert layout.anchors_per_cell == 48 and len(anchors) == 18 * 80 * 48
    tall = anchors.shapes[anchors.ratio_index == 2]
    np.testing.assert_allclose(tall[:, 1] / tall[:, 0], 2.0)
    np.testing.assert_allclose(np.sqrt(tall[:, 0] * tall[:, 1])[:16], layout.sizes)


@pytest.mark.parametrize("ratios", [(0.5, 1.0), (0.5, 1.0, 2.0)])
def test_bins_match_the_reference_nearest_size_and_ratio_rule(ratios):
    layout = AnchorLayout(image_size=(64, 96), ratios=ratios)
    anchors = generate_anchors(layout)
    np.testing.assert_array_equal(nearest_bin(anchors.shapes, layout), anchors.bin_index)
    np.testing.assert_array_equal(
        anchors.bin_index, anchors.ratio_index * layout.num_scales + anchors.scale_index
    )


def test_box_iou_np_matches_shapely():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 100, (12, 2))
    a = np.concatenate([xy, xy + rng.uniform(1, 60, (12, 2))], axis=1)
    xy = rng.uniform(0, 100, (9, 2))
    b = np.concatenate([xy, xy + rng.uniform(1, 60, (9, 2))], axis=1)
    ious = box_iou_np(a, b)
    for i in range(len(a)):
        for j in range(len(b)):
            pa, pb = shapely.box(*a[i]), shapely.box(*b[j])
            expected = pa.intersection(pb).area / pa.union(pb).area
            assert ious[i, j] == pytest.approx(expected, abs=1e-12)


def test_layout_round_trip_and_validation():
    layout = AnchorLayout(image_size=(288, 1280), ratios=(0.5, 1.0, 2.0))
    assert AnchorLayout.from_dict(layout.to_dict()) == layout
    assert layout.differences(AnchorLayout.from_dict(layout.to_dict())) == []
    diffs = layout.differences(AnchorLayout(image_size=(288, 1280)))
    assert len(diffs) == 1 and diffs[0].startswith("ratios")
    with pytest.raises(ValueError, match="image_size"):
        AnchorLayout(image_size=(0, 10))
    with pytest.raises(ValueError, match="ratios"):
        AnchorLayout(image_size=(10, 10), ratios=(-1.0,))
