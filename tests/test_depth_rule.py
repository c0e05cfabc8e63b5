"""The depth network's paired guard (gac_jax.guard.depth_rule) on constructed runs.

Identical runs -> within; a candidate 0.5 SILog worse on every image -> beyond, saying which
way; a small noisy change -> undecided with the frames that would decide at the next look,
and that many frames (same spread) then decide; both cameras of a frame count as one unit;
the t interval against scipy.stats and a float64 hand computation; fewer frames than the
minimum are refused, and the guard frames are spread over the drives, not the first N.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gac_jax.guard import depth_rule as pdg

METRICS = pdg.REPORTED


def rows(silog: np.ndarray, frames: int, cameras=(2, 3), **other) -> list[dict]:
    """Per-image rows: ``silog`` has one value per image, frame-major."""
    out, k = [], 0
    for f in range(frames):
        for c in cameras:
            row = {"frame": f"{f:06d}", "camera": c}
            row |= {m: float(other.get(m, 10.0)) for m in METRICS}
            row["silog"] = float(silog[k])
            out.append(row)
            k += 1
    return out


def test_identical_runs_are_within():
    rng = np.random.default_rng(0)
    ref = rows(rng.uniform(10, 20, 400), 200)
    d = pdg.decide_depth(ref, [dict(r) for r in ref])
    assert d["verdict"] == "within" and d["frames"] == 200 and d["images"] == 400
    assert d["criteria"]["silog"]["diff"] == 0 and d["criteria"]["silog"]["sd"] == 0
    assert "SILog within 0.2" in d["reason"]


def test_a_worse_candidate_is_beyond_and_says_which_way():
    rng = np.random.default_rng(1)
    base = rng.uniform(10, 20, 200)
    ref = rows(base, 100)
    cand = rows(base + 0.5 + rng.normal(0, 0.1, 200), 100)
    d = pdg.decide_depth(ref, cand)
    assert d["verdict"] == "beyond" and "up (worse)" in d["reason"]
    assert d["criteria"]["silog"]["diff"] == pytest.approx(0.5, abs=0.05)
    better = pdg.decide_depth(cand, ref)
    assert better["verdict"] == "beyond" and "down (better)" in better["reason"]


def test_few_frames_are_undecided_and_the_stated_count_decides():
    rng = np.random.default_rng(2)
    small = 120
    base = rng.uniform(10, 20, small)
    ref = rows(base, small, cameras=(2,))
    d = pdg.decide_depth(ref, rows(base + rng.normal(0.05, 1.5, small), small, cameras=(2,)))
    assert d["verdict"] == "undecided" and d["frames"] == small and d["look"] == 1
    need = d["frames_needed"]
    assert need > small and f"about {need} frames would decide it at look 2" in d["reason"]
    # the same mean and spread on that many frames decides it; one frame fewer does not
    row = d["criteria"]["silog"]

    def run(n: int) -> dict:
        z = rng.normal(0, 1, n)
        diffs = row["diff"] + row["sd"] * (z - z.mean()) / z.std(ddof=1)  # exact mean and sd
        base = rng.uniform(10, 20, n)
        return pdg.decide_depth(rows(base, n, (2,)), rows(base + diffs, n, (2,)), look=2)

    assert run(need)["verdict"] == "within"
    assert run(need - 1)["verdict"] == "undecided"


def test_a_frame_is_the_unit_not_an_image():
    # the two cameras of a frame move together: 2 frames x 2 images = 2 units
    ref = rows(np.full(4, 15.0), 2)
    cand = rows(np.array([15.1, 15.1, 15.3, 15.3]), 2)
    frames, diffs = pdg.frame_differences(ref, cand)
    assert frames == ["000000", "000001"]
    np.testing.assert_allclose(diffs[:, METRICS.index("silog")], [0.1, 0.3])
    d = pdg.decide_depth(ref, cand, min_frames=2)
    assert d["frames"] == 2 and d["images"] == 4


def test_mean_interval_against_scipy_and_by_hand():
    stats = pytest.importorskip("scipy.stats")
    x = np.array([0.3, -0.1, 0.25, 0.05, 0.4, -0.2, 0.1])
    mean, lo, hi = pdg.mean_interval(x, 0.05)
    ref_lo, ref_hi = stats.t.interval(0.90, len(x) - 1, loc=x.mean(), scale=stats.sem(x))
    assert mean == pytest.approx(x.mean()) and lo == pytest.approx(ref_lo)
    assert hi == pytest.approx(ref_hi)
    # by hand: t_{0.95, 6} = 1.943180
    half = 1.943180 * x.std(ddof=1) / math.sqrt(len(x))
    assert hi - mean == pytest.approx(half, rel=1e-5)
    assert pdg.mean_interval(np.array([1.0]), 0.05)[1] == -math.inf


def test_different_images_are_refused():
    ref = rows(np.full(4, 15.0), 2)
    with pytest.raises(ValueError, match="different images.*000001 camera 3"):
        pdg.decide_depth(ref, ref[:3])


def test_fewer_frames_than_the_minimum_are_refused():
    ref = rows(np.full(2 * 99, 15.0), 99)
    with pytest.raises(ValueError, match="at least 100 frames spread over the drives, got 99"):
        pdg.decide_depth(ref, [dict(r) for r in ref])
    enough = rows(np.full(2 * 100, 15.0), 100)
    assert pdg.decide_depth(enough, [dict(r) for r in enough])["frames"] == 100


def test_guard_frames_are_spread_over_the_drives():
    sizes = {"2011_09_26_drive_0001_sync": 300, "2011_09_26_drive_0009_sync": 50}
    sizes |= {"2011_09_28_drive_0002_sync": 120, "2011_09_29_drive_0004_sync": 30}
    sizes |= {"2011_10_03_drive_0042_sync": 500}
    ids = [f"{drive}/{k:010d}" for drive, n in sizes.items() for k in range(n)]
    ids = list(reversed(ids))  # the order of the list does not matter
    picked = pdg.spread_frames(ids, 100)
    assert len(set(picked)) == 100 and picked == pdg.spread_frames(ids, 100)
    per_drive = {d: sum(p.startswith(d + "/") for p in picked) for d in sizes}
    for drive, n in sizes.items():  # each drive its share of the 1,000 frames
        assert abs(per_drive[drive] - n / 10) <= 1, (drive, per_drive)
    first = [int(p.rsplit("/", 1)[1]) for p in picked if p.startswith("2011_10_03")]
    assert min(np.diff(sorted(first))) == 10  # spread within a drive, not consecutive
    assert pdg.spread_frames(ids, 5000) == sorted(ids)
    assert pdg.drive_of("2011_09_26_drive_0002_sync_image_0000000005_image_02") == (
        "2011_09_26_drive_0002_sync"
    )
