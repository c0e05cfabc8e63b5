"""The 3D MOT block by AB3DMOT's rule equals AB3DMOT's own evaluation script.

tests/data/tracking/ab3dmot_figures.json holds the figures of xinshuoweng/AB3DMOT's
``scripts/KITTI/evaluate.py`` (run by benchmarks/ab3dmot_oracle.py) on the sets of
tests/data/tracking/ab3dmot_sets.tar.xz: two generated clip sets tracked by the 3D tracker,
a set with Vans, sitting persons and DontCare regions, tracking_cases.clean_3d_lines and a
case of the script's floating-point drift of track scores.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from gac_jax.evaluation.tracking.ab3dmot_rules import ab3dmot_metrics
from gac_jax.evaluation.tracking.evaluator import load_tracking_folders
from gac_jax.evaluation.tracking.mot3d import mot3d_metrics

REPO = Path(__file__).resolve().parents[1]
FIGURES = json.loads((REPO / "tests/data/tracking/ab3dmot_figures.json").read_text())
sys.path.insert(0, str(REPO / "benchmarks"))
import ab3dmot_oracle  # noqa: E402  (the sets' archive and the clean case)

CASES = [(name, iou, cls) for name in (*ab3dmot_oracle.SETS, "clean_3d", "score_drift")
         for iou, by_class in FIGURES[name].items() for cls in by_class]  # fmt: skip


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    root = tmp_path_factory.mktemp("ab3dmot_sets")
    roots = ab3dmot_oracle.extract_sets(root / "sets")
    roots["clean_3d"] = ab3dmot_oracle.clean_3d_set(root / "clean_3d")
    roots["score_drift"] = ab3dmot_oracle.score_drift_set(root / "score_drift")
    return {name: load_tracking_folders(r / "label_02", r / "results") for name, r in roots.items()}


def test_the_fixture_covers_the_clip_sets_both_ious_and_classes():
    clip_sets = {(name, iou, cls) for name, iou, cls in CASES if name.startswith("clips")}
    assert {(iou, cls) for _, iou, cls in clip_sets} >= {
        (iou, cls) for iou in ("0.25", "0.50") for cls in ("car", "pedestrian")
    }
    assert len({name for name, _, _ in clip_sets}) == 2


@pytest.mark.parametrize(("name", "iou", "cls"), CASES)
def test_equals_ab3dmot_script(sets, name, iou, cls):
    script = FIGURES[name][iou][cls]
    mine = ab3dmot_metrics(sets[name], cls, float(iou))
    if script["MOTA"] == float("-inf"):  # no ground truth of the class: nothing to score
        assert mine["sAMOTA"] is None and mine["MOTA"] is None
        return
    assert mine["thresholds"] == script["thresholds"]
    for key in ("sAMOTA", "AMOTA", "AMOTP", "MOTA", "MOTP"):
        assert mine[key] == pytest.approx(script[key], abs=1e-6), (name, iou, cls, key)


def test_the_rules_differ_on_the_clip_sets(sets):
    """On the clips the TrackEval-based figures are not the script's (the docs' table)."""
    for name in ("clips_a", "clips_b"):
        ab = ab3dmot_metrics(sets[name], "car", 0.25)["sAMOTA"]
        te = mot3d_metrics(sets[name], "car", 0.25)["sAMOTA"]
        assert abs(ab - te) > 0.01


def _line(frame, tid, z, score=None, typ="Car"):
    u, half = 600 + 700 * 0.0 / z, 700 * 0.8 / z
    text = (
        f"{frame} {tid} {typ} 0 0 0 {u - half:.4f} 170 {u + half:.4f} {170 + 700 * 1.5 / z:.4f} "
        f"1.5 1.6 3.9 0 1.5 {z:.6f} 0"
    )
    return text + (f" {score}\n" if score is not None else "\n")


def test_a_switch_across_a_miss_is_not_counted(tmp_path):
    """One car over 4 frames: track A (0.9) in frame 0, missed in 1, track B (0.8) in 2-3.
    The script counts no switch (the frame before B is a miss): MOTA (3 - 0 - 0) / 4 at its
    best threshold, 0.8; TrackEval's CLEAR counts one: (3 - 0 - 1) / 4."""
    for d in ("label_02", "results"):
        (tmp_path / d).mkdir()
    z = [20.0, 21.0, 22.0, 23.0]
    (tmp_path / "label_02/0000.txt").write_text("".join(_line(f, 0, z[f]) for f in range(4)))
    res = [_line(0, 1, z[0], 0.9)] + [_line(f, 2, z[f], 0.8) for f in (2, 3)]
    (tmp_path / "results/0000.txt").write_text("".join(res))
    seqs = load_tracking_folders(tmp_path / "label_02", tmp_path / "results")
    ab = ab3dmot_metrics(seqs, "car", 0.5)
    assert ab["MOTA"] == pytest.approx(0.75) and ab["threshold"] == pytest.approx(0.8)
    assert mot3d_metrics(seqs, "car", 0.5)["MOTA"] == pytest.approx(0.5)


def test_the_score_drift_drops_a_track_at_its_own_score(sets):
    """One track of score 0.17 on a car over 7 frames: its mean 0.16999999999999998 is every
    threshold; the script takes the mean of the means again, 0.16999999999999996, and drops
    the track at every threshold: sAMOTA 0 (the fixture's figure from the script itself);
    the means taken once keep it: every sMOTA is 1."""
    script = ab3dmot_metrics(sets["score_drift"], "car", 0.5)
    assert script["sAMOTA"] == pytest.approx(0.0, abs=1e-12) and script["AMOTA"] == 0.0
    assert script["MOTA"] == 1.0 and script["threshold"] is None  # no threshold beats 0
    once = ab3dmot_metrics(sets["score_drift"], "car", 0.5, score_drift=False)
    assert once["thresholds"] == script["thresholds"] > 0
    assert once["sAMOTA"] == pytest.approx(once["thresholds"] / 40)
    assert mot3d_metrics(sets["score_drift"], "car", 0.5)["sAMOTA"] == once["sAMOTA"]
