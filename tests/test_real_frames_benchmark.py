"""The real-frame benchmark's own figures (benchmarks/real_frames.py), on hand-made labels: the
box-scale medians of the cars found (its false-positive counts and the operating point are the
package's: tests/test_operating_point.py). No network runs."""

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
