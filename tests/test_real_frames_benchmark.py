"""The real-frame benchmark's own figures (benchmarks/real_frames.py), on hand-made labels: the
box-scale medians of the cars found (its false-positive counts and the operating point are the
package's: tests/test_operating_point.py). No network runs."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import real_frames  # noqa: E402
from label_cases import label_line, objects  # noqa: E402

GT = objects(
    [
        label_line("Car", (100, 100, 200, 160), z=20.0),
        label_line("Car", (400, 100, 440, 120), z=40.0),  # 20 px tall: not counted as a car to find
        label_line("Van", (600, 100, 700, 180)),
        label_line("DontCare", (800, 100, 900, 150)),
    ],
    False,
)


def test_box_scale_medians_of_the_cars_found():
    # a box 0.8 x 0.9 of the label's about its centre (IoU 0.72), 1.1 times as far
    dt = objects([label_line("Car", (110, 103, 190, 157), z=22.0, score=0.9)], True)
    scale = real_frames.box_scale([GT], [dt], 0.5)
    assert scale["cars"] == 1
    assert scale["width"] == pytest.approx(0.8)
    assert scale["height"] == pytest.approx(0.9)
    assert scale["depth"] == pytest.approx(1.1)
    # below the threshold, or at IoU under 0.5: no car found
    assert real_frames.box_scale([GT], [dt], 0.95)["cars"] == 0
    far = objects([label_line("Car", (150, 100, 250, 160), score=0.9)], True)  # IoU 1/3
    assert real_frames.box_scale([GT], [far], 0.5)["cars"] == 0
    assert np.isnan(real_frames.box_scale([GT], [far], 0.5)["width"])
