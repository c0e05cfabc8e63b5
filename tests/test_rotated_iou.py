"""Box overlaps: hand-computed cases and a shapely cross-check on thousands of random pairs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import Polygon

from gac_jax import geometry
from gac_jax.evaluation import rotated_iou as ri


def bev(x, z, l, w, ry):
    return np.array([[x, z, l, w, ry]], dtype=np.float64)


def iou_bev(a, b, criterion=-1):
    return float(ri.bev_overlap(a, b, criterion)[0, 0])


class TestBevHandCases:
    def test_identical(self):
        a = bev(3.0, 20.0, 4.0, 1.8, 0.7)
        assert iou_bev(a, a) == pytest.approx(1.0, abs=1e-12)

    def test_touching_edges_and_corners_is_zero(self):
        a = bev(0.0, 0.0, 4.0, 2.0, 0.0)
        # length along x at ry = 0: a spans x in [-2, 2]; b starts where a ends.
        assert iou_bev(a, bev(4.0, 0.0, 4.0, 2.0, 0.0)) == 0.0
        assert iou_bev(a, bev(4.0, 2.0, 4.0, 2.0, 0.0)) == 0.0  # corner contact
        assert iou_bev(a, bev(10.0, 0.0, 4.0, 2.0, 0.3)) == 0.0  # far apart

    def test_contained(self):
        big = bev(1.0, 5.0, 6.0, 4.0, 0.4)
        small = bev(1.0, 5.0, 2.0, 1.0, 1.3)
        # intersection = small (area 2); union = big (area 24)
        assert iou_bev(big, small) == pytest.approx(2.0 / 24.0, abs=1e-12)
        assert iou_bev(small, big, criterion=0) == pytest.approx(1.0, abs=1e-12)
        assert iou_bev(small, big, criterion=1) == pytest.approx(2.0 / 24.0, abs=1e-12)

    def test_rotated_90_degrees(self):
        # 4 x 2 box and the same box turned by 90 deg about the same centre:
        # intersection is the central 2 x 2 square (4), union 8 + 8 - 4 = 12.
        a = bev(-7.0, 31.0, 4.0, 2.0, 0.2)
        b = bev(-7.0, 31.0, 4.0, 2.0, 0.2 + math.pi / 2)
        assert iou_bev(a, b) == pytest.approx(4.0 / 12.0, abs=1e-12)

    def test_rotated_45_degrees(self):
        # Two 2 x 2 squares, one turned by 45 deg: the intersection is the regular octagon
        # of inradius 1, area 8 (sqrt2 - 1); IoU = 8(sqrt2-1) / (8 - 8(sqrt2-1)) = 1/sqrt2.
        a = bev(0.0, 0.0, 2.0, 2.0, 0.0)
        b = bev(0.0, 0.0, 2.0, 2.0, math.pi / 4)
        inter = 8.0 * (math.sqrt(2.0) - 1.0)
        assert float(ri.bev_intersection_area_pairs(a, b)[0]) == pytest.approx(inter, abs=1e-12)
        assert iou_bev(a, b) == pytest.approx(1.0 / math.sqrt(2.0), abs=1e-12)

    def test_half_shift(self):
        # Shift by half the length along the heading: intersection 2 x 2 = 4, union 12.
        ry = 0.9
        a = bev(0.0, 0.0, 4.0, 2.0, ry)
        b = bev(2.0 * math.cos(ry), -2.0 * math.sin(ry), 4.0, 2.0, ry)
        assert iou_bev(a, b) == pytest.approx(1.0 / 3.0, abs=1e-12)

    def test_heading_convention_matches_core_geometry(self):
        # At ry = pi/2 the length points along -z: x extent is w, z extent is l.
        corners = ri.bev_corners(bev(0.0, 0.0, 4.0, 2.0, math.pi / 2))[0]
        assert np.ptp(corners[:, 0]) == pytest.approx(2.0)
        assert np.ptp(corners[:, 1]) == pytest.approx(4.0)
        rng = np.random.default_rng(3)
        loc = rng.normal(0, 10, (50, 3))
        dims = rng.uniform(0.5, 5, (50, 3))
        ry = rng.uniform(-4, 4, 50)
        ours = ri.bev_corners(ri.bev_boxes(loc, dims, ry))
        core = geometry.box3d_corners(loc, dims, ry)[:, :4][:, :, [0, 2]]
        for k in range(50):
            # same point sets (order may differ)
            d = np.linalg.norm(ours[k][:, None, :] - core[k][None, :, :], axis=-1)
            assert d.min(axis=1).max() < 1e-12

    def test_zero_area_box_gives_zero(self):
        a = bev(0.0, 0.0, 4.0, 0.0, 0.0)
        assert iou_bev(a, bev(0.0, 0.0, 4.0, 2.0, 0.0)) == 0.0
        assert iou_bev(a, a) == 0.0

    def test_bad_criterion(self):
        with pytest.raises(ValueError, match="criterion"):
            ri.bev_overlap(bev(0, 0, 1, 1, 0), bev(0, 0, 1, 1, 0), criterion=2)


class TestBox3dHandCases:
    def test_vertical_offset(self):
        # Same footprint (4 x 2 = 8 m^2), h = 2, one 0.5 m lower (y down): height overlap 1.5,
        # inter = 12, volumes 16 each, IoU = 12 / (32 - 12) = 0.6.
        a = np.array([[1.0, 1.6, 20.0, 2.0, 2.0, 4.0, 0.3]])
        b = a.copy()
        b[0, 1] += 0.5
        assert float(ri.box3d_overlap(a, b)[0, 0]) == pytest.approx(0.6, abs=1e-12)
        assert float(ri.box3d_overlap(a, b, criterion=0)[0, 0]) == pytest.approx(0.75, abs=1e-12)

    def test_stacked_boxes_do_not_overlap(self):
        a = np.array([[0.0, 1.0, 10.0, 1.0, 2.0, 4.0, 0.0]])
        b = a.copy()
        b[0, 1] -= 1.0  # b spans y in [-1, 0], a in [0, 1]
        assert float(ri.box3d_overlap(a, b)[0, 0]) == 0.0

    def test_combined_rotation_and_offset(self):
        # 45-degree squares (octagon 8(sqrt2-1)) with heights 1 and 2 overlapping over 1 m.
        a = np.array([[0.0, 1.0, 0.0, 1.0, 2.0, 2.0, 0.0]])
        b = np.array([[0.0, 1.0, 0.0, 2.0, 2.0, 2.0, math.pi / 4]])
        inter = 8.0 * (math.sqrt(2.0) - 1.0) * 1.0
        expected = inter / (4.0 + 8.0 - inter)
        assert float(ri.box3d_overlap(a, b)[0, 0]) == pytest.approx(expected, abs=1e-12)


class TestBox2d:
    def test_hand_values(self):
        a = np.array([[0.0, 0.0, 10.0, 10.0]])
        b = np.array([[5.0, 5.0, 15.0, 25.0]])
        # inter 5 x 5 = 25; areas 100 and 200
        assert float(ri.box2d_overlap(a, b)[0, 0]) == pytest.approx(25 / 275)
        assert float(ri.box2d_overlap(a, b, 0)[0, 0]) == pytest.approx(25 / 100)
        assert float(ri.box2d_overlap(a, b, 1)[0, 0]) == pytest.approx(25 / 200)

    def test_touching_and_inverted(self):
        a = np.array([[0.0, 0.0, 10.0, 10.0]])
        assert float(ri.box2d_overlap(a, np.array([[10.0, 0.0, 20.0, 10.0]]))[0, 0]) == 0.0
        assert float(ri.box2d_overlap(a, np.array([[8.0, 8.0, 2.0, 2.0]]))[0, 0]) == 0.0

    def test_all_pairs_shape(self):
        rng = np.random.default_rng(0)
        a = np.sort(rng.uniform(0, 100, (5, 2, 2)), axis=1).transpose(0, 2, 1).reshape(5, 4)
        b = np.sort(rng.uniform(0, 100, (3, 2, 2)), axis=1).transpose(0, 2, 1).reshape(3, 4)
        a = a[:, [0, 2, 1, 3]]
        b = b[:, [0, 2, 1, 3]]
        m = ri.box2d_overlap(a, b)
        assert m.shape == (5, 3)
        for i in range(5):
            for j in range(3):
                assert m[i, j] == pytest.approx(ri.box2d_overlap(a[i : i + 1], b[j : j + 1])[0, 0])


def _random_pairs(rng, n):
    """Random BEV box pairs, biased towards overlapping, nested, identical and touching cases."""
    a = np.column_stack(
        [
            rng.uniform(-5, 5, n),
            rng.uniform(0, 60, n),
            rng.uniform(0.2, 6, n),
            rng.uniform(0.2, 3, n),
            rng.uniform(-np.pi, np.pi, n),
        ]
    )
    b = a.copy()
    b[:, :2] += rng.normal(0, 1.5, (n, 2))
    b[:, 2:4] *= rng.uniform(0.3, 1.7, (n, 2))
    b[:, 4] += rng.choice([0.0, np.pi / 2, np.pi / 4, np.pi], n) + rng.normal(0, 0.3, n)
    same = rng.random(n) < 0.05
    b[same] = a[same]  # identical boxes
    nested = rng.random(n) < 0.05
    b[nested, :2] = a[nested, :2]
    b[nested, 2:4] = a[nested, 2:4] * 0.5
    return a, b


def test_bev_and_3d_overlap_match_shapely():
    rng = np.random.default_rng(42)
    n = 4000
    a, b = _random_pairs(rng, n)
    inter = ri.bev_intersection_area_pairs(a, b)
    iou = ri.bev_overlap_pairs(a, b)
    # Independent polygons: bottom faces of the core's 3D corners.
    loc_a = np.column_stack([a[:, 0], np.zeros(n), a[:, 1]])
    loc_b = np.column_stack([b[:, 0], np.zeros(n), b[:, 1]])
    dims_a = np.column_stack([np.ones(n), a[:, 3], a[:, 2]])
    dims_b = np.column_stack([np.ones(n), b[:, 3], b[:, 2]])
    ca = geometry.box3d_corners(loc_a, dims_a, a[:, 4])[:, :4][:, :, [0, 2]]
    cb = geometry.box3d_corners(loc_b, dims_b, b[:, 4])[:, :4][:, :, [0, 2]]
    ha = rng.uniform(0.5, 2.5, n)
    hb = ha * rng.uniform(0.5, 1.5, n)
    ya = rng.uniform(1.0, 2.0, n)
    yb = ya + rng.normal(0, 0.7, n)
    box_a = np.column_stack([a[:, 0], ya, a[:, 1], ha, a[:, 3], a[:, 2], a[:, 4]])
    box_b = np.column_stack([b[:, 0], yb, b[:, 1], hb, b[:, 3], b[:, 2], b[:, 4]])
    iou3d = ri.box3d_overlap_pairs(box_a, box_b)
    n_positive = 0
    for k in range(n):
        pa, pb = Polygon(ca[k]), Polygon(cb[k])
        ref_inter = pa.intersection(pb).area
        ref_iou = ref_inter / (pa.area + pb.area - ref_inter)
        assert abs(inter[k] - ref_inter) <= 1e-9, k
        assert abs(iou[k] - ref_iou) <= 1e-9, k
        dy = max(0.0, min(ya[k], yb[k]) - max(ya[k] - ha[k], yb[k] - hb[k]))
        v_int = ref_inter * dy
        ref3d = v_int / (pa.area * ha[k] + pb.area * hb[k] - v_int)
        assert abs(iou3d[k] - ref3d) <= 1e-9, k
        n_positive += ref_inter > 0
    assert n_positive > n // 2  # the sample exercises real overlaps


def test_all_pairs_matrix_matches_pairwise():
    rng = np.random.default_rng(7)
    a, b = _random_pairs(rng, 30)
    full = ri.bev_overlap(a, b[:20])
    for i in range(30):
        row = ri.bev_overlap_pairs(np.repeat(a[i : i + 1], 20, 0), b[:20])
        np.testing.assert_allclose(full[i], row, atol=1e-15)
