"""The paired per-object guard (gac_jax.evaluation.paired_guard) on constructed cases.

Found objects agree with the loop transcription of the devkit's statistics pass
(tests/kitti_devkit_oracle.py) on real KITTI labels; the exact intervals agree with
Clopper-Pearson from the beta distribution (scipy, when installed); identical runs on
enough objects are "within", a run with a known share of heading flips is "beyond" and
names the heading, and identical runs on few objects are "undecided" with the objects and
frames that would decide.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gac_jax.data.kitti import KittiObjects, read_label, read_split
from gac_jax.evaluation import paired_guard as pg
from tests import kitti_devkit_oracle as oracle


def _frames(n_frames: int, cars: int = 4, seed: int = 0) -> list[KittiObjects]:
    """Easy cars (tall, unoccluded, untruncated) spread over the image and the road."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n_frames):
        x = np.linspace(-12, 12, cars) + rng.uniform(-0.5, 0.5, cars)
        z = rng.uniform(8, 25, cars)
        u = 620 + 720 * x / z
        h = 1.5 * 720 / z
        out.append(
            KittiObjects.from_arrays(
                type=np.array(["Car"] * cars),
                alpha=rng.uniform(-np.pi, np.pi, cars),
                bbox=np.stack([u - 1.5 * h, 180 - h, u + 1.5 * h, 180 + 0.2 * h], -1),
                dimensions=np.tile([1.5, 1.6, 3.9], (cars, 1)),
                location=np.stack([x, np.full(cars, 1.65), z], -1),
                rotation_y=rng.uniform(-np.pi, np.pi, cars),
                score=np.full(cars, np.nan),
            )
        )
    return out


def _detections(labels: list[KittiObjects], flip_share: float = 0.0, seed: int = 1):
    """The labels as detections (scores 0.9 .. 0.5); ``flip_share`` of them turned by 180 deg
    (the same 2D/BEV/3D box, the opposite heading)."""
    rng = np.random.default_rng(seed)
    out = []
    for objects in labels:
        flip = rng.random(len(objects)) < flip_share
        turn = np.where(flip, np.pi, 0.0)
        d = dataclasses.replace(
            objects,
            alpha=pg._wrap(objects.alpha + turn),
            rotation_y=pg._wrap(objects.rotation_y + turn),
            score=np.linspace(0.9, 0.5, len(objects)),
        )
        out.append(d)
    return out


def test_found_objects_match_the_devkit_statistics_pass(kitti_object_root):
    ids = read_split(kitti_object_root / "ImageSets" / "labeled.txt")
    gts = [read_label(kitti_object_root / "training" / "label_2" / f"{i}.txt") for i in ids]
    rng = np.random.default_rng(3)
    dts = []
    for g in gts:  # the labels (cars and vans as "Car"), moved, resized and turned a little
        n = len(g)
        d = KittiObjects.from_arrays(
            type=np.where(np.isin(g.type, ["Car", "Van"]), "Car", "Pedestrian"),
            alpha=g.alpha + rng.normal(0, 0.6, n),
            bbox=g.bbox + rng.normal(0, 6, (n, 4)),
            dimensions=g.dimensions * rng.uniform(0.85, 1.15, (n, 3)),
            location=g.location + rng.normal(0, 0.4, (n, 3)),
            rotation_y=g.rotation_y + rng.normal(0, 0.2, n),
            score=rng.uniform(0.2, 1.0, n),
        )
        dts.append(d)
    min_score = 0.4
    got = pg.object_outcomes(gts, dts, "Car", min_score)
    for d, name in enumerate(("easy", "moderate", "hard")):
        for crit, metric, thr in pg.criteria("Car"):
            tp = 0
            for g, dt in zip(gts, dts, strict=True):
                gr, dr = oracle.to_records(g), oracle.to_records(dt)
                ign_g, dc, ign_d, _ = oracle.clean_data("Car", gr, dr, d)
                ov = [[oracle.overlap(metric, x, y) for y in gr] for x in dr]
                ov_dc = [[oracle.overlap(metric, x, y, 0) for y in dc] for x in dr]
                stats = oracle.compute_statistics(
                    gr, dr, dc, ign_g, ign_d, True, ov, ov_dc, thr, thresh=min_score
                )
                tp += stats["tp"]
            assert int(got[name][crit].sum()) == tp, (name, crit)


def test_intervals_are_clopper_pearson():
    stats = pytest.importorskip("scipy.stats")
    for x, n in ((0, 10), (3, 10), (10, 10), (50, 1000), (7, 31)):
        a = 0.025
        lo = stats.beta.ppf(a, x, n - x + 1) if x else 0.0
        hi = stats.beta.ppf(1 - a, x + 1, n - x) if x < n else 1.0
        assert pg.clopper_pearson(x, n, a) == pytest.approx((lo, hi), abs=1e-9)
    # no discordant object: +-(upper bound of the discordant share), 736 objects = 0.5 points
    lo, hi = pg.difference_interval(0, 0, 736, 0.05)
    assert lo == -hi and hi == pytest.approx(100 * (1 - 0.025 ** (1 / 736)), abs=1e-9)
    assert pg.mcnemar_p(0, 6) == pytest.approx(2 / 64)
    assert pg.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])


def test_identical_runs_on_enough_objects_are_within():
    gts = _frames(250)  # 1,000 easy cars
    dts = _detections(gts)
    tables = pg.guard_tables(gts, dts, _detections(gts))
    assert len(tables) == 3 * 6 and all(t["n"] == 1000 for t in tables.values())
    assert all(t["ref_only"] == t["cand_only"] == 0 for t in tables.values())
    result = pg.decide(tables, frames=len(gts))
    assert result["verdict"] == "within", result["reason"]
    matched = pg.matched_differences(dts, dts)
    assert matched["matched"] == 1000 and matched["heading_flips"] == 0
    assert matched["heading_deg"]["max"] == 0.0 and matched["centre_m"]["max"] == 0.0


def test_a_known_share_of_heading_flips_is_beyond_and_named():
    gts = _frames(250)
    ref, cand = _detections(gts), _detections(gts, flip_share=0.05)
    turned = [np.abs(pg._wrap(a.alpha - b.alpha)) > 3 for a, b in zip(ref, cand, strict=True)]
    flipped = int(sum(t.sum() for t in turned))
    tables = pg.guard_tables(gts, ref, cand)
    result = pg.decide(tables, frames=len(gts))
    assert result["verdict"] == "beyond"
    assert result["deciding"].endswith("heading")
    assert set(n.split()[-1] for n, r in result["criteria"].items() if r["status"] == "beyond") == {
        "heading"
    }
    heading = result["criteria"]["Car moderate heading"]
    assert heading["ref_only"] == flipped and heading["cand_only"] == 0
    assert heading["diff"] == pytest.approx(-100 * flipped / 1000)
    assert "heading" in result["reason"] and f"{heading['diff']:+.2f}" in result["reason"]
    # the boxes did not move: every box criterion found the same objects
    assert all(r["ref_only"] == r["cand_only"] == 0 for n, r in tables.items() if "@" in n)
    matched = pg.matched_differences(ref, cand)
    assert matched["heading_flips"] == flipped
    assert matched["heading_flip_share"] == pytest.approx(flipped / 1000)


def test_too_few_objects_are_undecided_with_the_count_needed():
    gts = _frames(25)  # 100 cars: agreement on them cannot show +-0.5 points
    dts = _detections(gts)
    result = pg.decide(pg.guard_tables(gts, dts, dts), frames=len(gts))
    assert result["verdict"] == "undecided"
    need = math.ceil(math.log(0.025) / math.log(1 - 0.005))  # q_hi(0 of n) <= 0.5 points
    assert all(v in (need, need + 1) for v in result["objects_needed"].values())
    assert result["frames_needed"] == math.ceil(max(result["objects_needed"].values()) / 4)
    assert f"about {result['frames_needed']} frames" in result["reason"]
    # and that many frames of the same kind do decide it
    more = _frames(result["frames_needed"], seed=5)
    again = pg.decide(pg.guard_tables(more, _detections(more), _detections(more)), len(more))
    assert again["verdict"] == "within"
