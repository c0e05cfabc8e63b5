"""The real-frame benchmark's own counts (benchmarks/real_frames.py), on hand-made labels:
false positives with KITTI's excuses, cars found, and the box-scale medians. No network runs."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from gac_jax.data.kitti import parse_label

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import real_frames  # noqa: E402


def _line(kind, box, z=20.0, score=None):
    x0, y0, x1, y1 = box
    s = f"{kind} 0 0 0 {x0} {y0} {x1} {y1} 1.5 1.6 3.9 0 1.6 {z} 0"
    return s if score is None else f"{s} {score}"


def _objects(lines, with_score):
    return parse_label("\n".join(lines), with_score=with_score)


GT = _objects(
    [
        _line("Car", (100, 100, 200, 160), z=20.0),
        _line("Car", (400, 100, 440, 120), z=40.0),  # 20 px tall: not counted as a car to find
        _line("Van", (600, 100, 700, 180)),
        _line("DontCare", (800, 100, 900, 150)),
    ],
    False,
)


def test_false_positives_excuse_vans_and_dontcare_and_take_each_car_once():
    dt = _objects(
        [
            _line("Car", (100, 100, 200, 160), z=22.0, score=0.9),  # the car
            _line("Car", (102, 100, 202, 160), score=0.8),  # the same car again: false
            _line("Car", (600, 100, 700, 180), score=0.7),  # on the Van: excused
            _line("Car", (810, 110, 860, 140), score=0.7),  # inside DontCare: excused
            _line("Car", (1000, 100, 1050, 140), score=0.6),  # nothing there: false
            _line("Car", (300, 100, 350, 140), score=0.3),  # below the threshold
        ],
        True,
    )
    assert real_frames.false_positives(GT, dt, 0.5) == (5, 2, 1, 1)
    assert real_frames.false_positives(GT, dt, 0.85) == (1, 0, 1, 1)


def test_box_scale_medians_of_the_cars_found():
    # a box 0.8 x 0.9 of the label's about its centre (IoU 0.72), 1.1 times as far
    dt = _objects([_line("Car", (110, 103, 190, 157), z=22.0, score=0.9)], True)
    scale = real_frames.box_scale([GT], [dt], 0.5)
    assert scale["cars"] == 1
    assert scale["width"] == pytest.approx(0.8)
    assert scale["height"] == pytest.approx(0.9)
    assert scale["depth"] == pytest.approx(1.1)
    # below the threshold, or at IoU under 0.5: no car found
    assert real_frames.box_scale([GT], [dt], 0.95)["cars"] == 0
    far = _objects([_line("Car", (150, 100, 250, 160), score=0.9)], True)  # IoU 1/3
    assert real_frames.box_scale([GT], [far], 0.5)["cars"] == 0
    assert np.isnan(real_frames.box_scale([GT], [far], 0.5)["width"])


def test_threshold_sweep_and_operating_point_by_hand():
    dt = _objects(
        [
            _line("Car", (100, 100, 200, 160), score=0.9),  # the car (the one >= 25 px tall)
            _line("Car", (1000, 100, 1050, 140), score=0.7),  # nothing there: false
            _line("Car", (1100, 100, 1150, 140), score=0.55),  # nothing there: false
        ],
        True,
    )
    empty = _objects([], True)
    sweep = real_frames.threshold_sweep([GT, GT], [dt, empty], (0.5, 0.6, 0.8, 0.95))
    # two frames: 3 detections of which 2 false at 0.5; one of the two tall cars found
    assert sweep[0.5]["detections"] == 1.5 and sweep[0.5]["false_positives"] == 1.0
    assert sweep[0.5]["precision"] == pytest.approx(1 / 3)
    assert sweep[0.5]["recall"] == pytest.approx(0.5)
    assert sweep[0.5]["f1"] == pytest.approx(2 * (1 / 3) * 0.5 / (1 / 3 + 0.5))
    assert sweep[0.6]["precision"] == pytest.approx(0.5) and sweep[0.6]["found"] == 1
    assert sweep[0.8] == {
        "detections": 0.5,
        "false_positives": 0.0,
        "found": 1,
        "precision": 1.0,
        "recall": 0.5,
        "f1": pytest.approx(2 / 3),
    }
    assert sweep[0.95]["f1"] == 0.0 and sweep[0.95]["found"] == 0
    assert real_frames.operating_point(sweep) == 0.8
    # a tie goes to the lowest threshold
    assert real_frames.operating_point({0.7: {"f1": 0.5}, 0.6: {"f1": 0.5}}) == 0.6
