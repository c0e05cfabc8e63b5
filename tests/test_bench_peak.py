"""The measured peak of benchmarks/bench_peak.py and the shares bench_stream.py prints.

The peak graph's MACs, counted from its ONNX graph (gac_jax.deploy.graph_macs), equal the hand
count; every share of the peak bench_stream.py prints (core_accounting.mac_summary) is at most
100 %, or says on its line why it is above. No benchmark is run here.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

from gac_jax.deploy.graph_macs import count_macs

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_peak  # noqa: E402
import core_accounting  # noqa: E402


@pytest.mark.parametrize(
    ("channels", "size", "layers", "kernel"),
    [(8, 4, 3, 1), (8, 5, 2, 3), tuple(bench_peak.DEFAULT_SHAPE.values())],
)
def test_peak_graph_macs_equal_the_hand_count(channels, size, layers, kernel):
    model = bench_peak.peak_graph(channels, size, layers, kernel)
    # each layer: size x size outputs (same padding) x channels outputs, each a sum of
    # channels x kernel x kernel products
    by_hand = layers * (size * size) * channels * (channels * kernel * kernel)
    assert bench_peak.hand_count(channels, size, layers, kernel) == by_hand
    assert count_macs(model) == {"Conv": by_hand, "total": by_hand}
    assert sum(node.op_type == "Conv" for node in model.graph.node) == layers


def test_the_default_graph_is_9_66_gmac():
    assert bench_peak.hand_count(**bench_peak.DEFAULT_SHAPE) == 4 * 16 * 16 * 1024 * 1024 * 9
    assert 4 * 16 * 16 * 1024 * 1024 * 9 == 9_663_676_416


def _peak(median, lo, hi):
    return {"median": median, "min": lo, "max": hi}


PERCENT = re.compile(r"(\d+) % of")


def _check_shares(text: str) -> list[int]:
    """Every share in ``text`` (one per line or more): <= 100, or the line says why."""
    shares = []
    for line in text.splitlines():
        for share in map(int, PERCENT.findall(line)):
            shares.append(share)
            assert share <= 100 or "(above the median peak: " in line, line
    return shares


def test_share_of_peak_above_100_says_why():
    peak = _peak(200e9, 180e9, 220e9)
    assert core_accounting.share_of_peak(150e9, peak) == "75 % of 200"
    within = core_accounting.share_of_peak(210e9, peak)
    assert within.startswith("105 % of 200 (above the median peak: within the peak's rounds")
    reason = core_accounting.share_of_peak(300e9, peak, ("2 convolutions ran as Winograd",))
    assert reason.endswith("(above the median peak: 2 convolutions ran as Winograd)")
    assert "not this network's ceiling" in core_accounting.share_of_peak(300e9, peak)
    for value in (1e9, 199e9, 200e9, 201e9, 220e9, 221e9, 1e13):
        _check_shares(core_accounting.share_of_peak(value, peak))


def test_every_share_bench_stream_prints_is_at_most_100_or_explained(capsys):
    """mac_summary on rows like bench_stream.py's: network alone (wall and CPU), the peaks of
    three precisions; rows below, within the spread of and above the peaks."""
    peaks = {
        p: {
            "wall_macs_per_s": _peak(m * 2, m * 1.8, m * 2.2),
            "core_macs_per_s": _peak(m, m * 0.95, m * 1.05),
        }
        for p, m in (("f32", 50e9), ("bf16", 100e9), ("int8", 200e9))
    }
    macs = {"Conv": int(95.8e9), "total": int(95.8e9)}
    rows = []
    for runtime, precision, ms, cpu_ms in (
        ("jax", "f32", 2500.0, 4000.0),
        ("onnxruntime", "f32", 800.0, 1700.0),  # faster than OpenVINO's f32 peak
        ("openvino", "f32", 1000.0, 2000.0),
        ("openvino", "bf16", 470.0, 940.0),  # within the peak's spread
        ("openvino", "int8", 150.0, 300.0),  # above every round
    ):
        row = {"config": "paper", "runtime": runtime, "precision": precision}
        row.update(label=f"{runtime} {precision}", infer_ms=ms, infer_cpu_ms=cpu_ms)
        if runtime == "openvino":
            row["network_ms"] = ms
            row["primitives"] = {"brgconv_avx512_1x1_I8": 60}
        rows.append(row)
    rows[-1]["primitives"]["jit_avx512_core_wino_4x3"] = 3
    core_accounting.mac_summary(rows, "paper", macs, peaks)
    out = capsys.readouterr().out
    shares = _check_shares(out)
    assert len(shares) == 2 * len(rows) and max(shares) > 100  # both kinds of line occur
    assert "onnxruntime is not the peak's runtime" in out
    assert "3 convolutions ran as Winograd" in out
    assert rows[2]["share_of_peak"] == pytest.approx(95.8e9 / 1.0 / 100e9)
