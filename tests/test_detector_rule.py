"""The paired guard (gac_jax.guard.criteria, detector_rule) on constructed cases.

Found objects and false positives agree with the loop transcription of the devkit's
statistics pass (tests/kitti_devkit_oracle.py) on real KITTI labels. On 1,000 cars, three
changes that recall at the deployed threshold does not see (false positives re-scored from
0.55 to 0.99, true positives scored below the false positives, every heading turned 25
degrees) are each "beyond", as is a known share of heading flips; identical runs are
"within" on enough frames and "undecided" on few, with the frames that then decide.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from gac_jax.data.kitti import KittiObjects, read_label, read_split
from gac_jax.guard import ap_bootstrap
from gac_jax.guard import criteria as gc
from gac_jax.guard import detector_rule as pg
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
            alpha=gc.wrap(objects.alpha + turn),
            rotation_y=gc.wrap(objects.rotation_y + turn),
            score=np.linspace(0.9, 0.5, len(objects)),
        )
        out.append(d)
    return out


def label_detections(gts: list[KittiObjects], rng, scale: float = 1.0) -> list[KittiObjects]:
    """The labels as detections (cars and vans as "Car", the rest "Pedestrian"), moved,
    resized and turned a little (``scale`` times the default noise), random scores."""
    out = []
    for g in gts:
        n = len(g)
        d = KittiObjects.from_arrays(
            type=np.where(np.isin(g.type, ["Car", "Van"]), "Car", "Pedestrian"),
            alpha=g.alpha + rng.normal(0, 0.6 * scale, n),
            bbox=g.bbox + rng.normal(0, 6 * scale, (n, 4)),
            dimensions=g.dimensions * rng.uniform(1 - 0.15 * scale, 1 + 0.15 * scale, (n, 3)),
            location=g.location + rng.normal(0, 0.4 * scale, (n, 3)),
            rotation_y=g.rotation_y + rng.normal(0, 0.2 * scale, n),
            score=rng.uniform(0.2, 1.0, n),
        )
        out.append(d)
    return out


def test_found_objects_match_the_devkit_statistics_pass(kitti_object_root):
    ids = read_split(kitti_object_root / "ImageSets" / "labeled.txt")
    gts = [read_label(kitti_object_root / "training" / "label_2" / f"{i}.txt") for i in ids]
    dts = label_detections(gts, np.random.default_rng(3))
    min_score = 0.4
    got = gc.frame_outcomes(gts, dts, "Car", (min_score, 0.7))
    for d, name in enumerate(("easy", "moderate", "hard")):
        for crit, metric, thr in gc.criteria("Car"):
            for t, tag, fp_tag in (
                (min_score, crit, f"{crit} fp"),
                (0.7, f"{crit} s>=0.70", f"{crit} fp s>=0.70"),
            ):
                tp, fps = 0, []
                for g, dt in zip(gts, dts, strict=True):
                    gr, dr = oracle.to_records(g), oracle.to_records(dt)
                    ign_g, dc, ign_d, _ = oracle.clean_data("Car", gr, dr, d)
                    ov = [[oracle.overlap(metric, x, y) for y in gr] for x in dr]
                    ov_dc = [[oracle.overlap(metric, x, y, 0) for y in dc] for x in dr]
                    stats = oracle.compute_statistics(
                        gr, dr, dc, ign_g, ign_d, True, ov, ov_dc, thr, thresh=t
                    )
                    tp += stats["tp"]
                    fps.append(stats["fp"])
                assert int(got[name]["found"][tag].sum()) == tp, (name, tag)
                assert got[name]["fp"][fp_tag].tolist() == fps, (name, tag)


# ----------------------------------------------------------------------------- toy runs


def _noisy(dets: list[KittiObjects], seed: int = 3, heading_deg: float = 4.0, centre_m=0.1):
    """Detections with small heading and centre errors (so the error quantiles are > 0)."""
    rng = np.random.default_rng(seed)
    out = []
    for d in dets:
        turn = np.radians(rng.normal(0, heading_deg, len(d)))
        out.append(
            dataclasses.replace(
                d,
                alpha=gc.wrap(d.alpha + turn),
                rotation_y=gc.wrap(d.rotation_y + turn),
                location=d.location + rng.normal(0, centre_m, d.location.shape),
            )
        )
    return out


def _with_false_positive(dets: list[KittiObjects], fp_score: float, tp_scores=None):
    """One false positive per frame (a car-sized box far from every label) at ``fp_score``;
    the true positives' scores replaced by ``tp_scores`` (per frame) when given."""
    out = []
    for d in dets:
        fp = KittiObjects.from_arrays(
            type=np.array(["Car"]),
            alpha=np.array([0.3]),
            bbox=np.array([[20.0, 20.0, 180.0, 80.0]]),
            dimensions=np.array([[1.5, 1.6, 3.9]]),
            location=np.array([[-40.0, 1.65, 70.0]]),
            rotation_y=np.array([0.0]),
            score=np.array([fp_score]),
        )
        tp = d if tp_scores is None else dataclasses.replace(d, score=np.asarray(tp_scores))
        out.append(KittiObjects.concatenate([tp, fp]))
    return out


def _verdict(gts, ref, cand, resamples=60) -> dict:
    tables = gc.guard_tables(gts, ref, cand, min_score=0.5)
    ap = ap_bootstrap.paired_ap_bootstrap(gts, ref, cand, resamples=resamples)
    return pg.decide(tables, len(gts), ap=ap)


@pytest.fixture(scope="module")
def cars():
    gts = _frames(250)  # 1,000 easy cars
    return gts, _noisy(_detections(gts))


def _deployed_recall_unchanged(result: dict) -> bool:
    """What the recall-only rule looked at: recall at the deployed threshold (no suffix)."""
    plain = [
        r
        for n, r in result["criteria"].items()
        if r["kind"] == "recall" and not any(k in n for k in (" s>=", " p50", " p90"))
    ]
    return len(plain) == 18 and all(r["ref_only"] == r["cand_only"] == 0 for r in plain)


def test_false_positives_rescored_higher_are_beyond(cars):
    gts, dets = cars
    ref = _with_false_positive(dets, 0.55)
    cand = _with_false_positive(dets, 0.99)
    result = _verdict(gts, ref, cand)
    assert result["verdict"] == "beyond", result["reason"]
    fp = result["criteria"]["Car easy 2d@0.70 fp s>=0.90"]
    assert (fp["ref_only"], fp["cand_only"], fp["n"]) == (0, 250, 1000)
    assert fp["status"] == "beyond" and fp["diff"] == pytest.approx(25.0)
    assert result["criteria"]["Car easy 2d@0.70 fp"]["status"] != "beyond"  # same set at 0.5
    ap = result["criteria"]["Car AP40 2d@0.70 moderate"]
    assert ap["diff"] < -10 and ap["status"] == "beyond"
    assert _deployed_recall_unchanged(result)


def test_true_positives_scored_below_false_positives_are_beyond(cars):
    gts, dets = cars
    ref = _with_false_positive(dets, 0.55)  # true positives 0.9 .. 0.5 above the 0.55 ... mostly
    low = np.linspace(0.54, 0.51, 4)
    cand = _with_false_positive(dets, 0.95, tp_scores=low)
    result = _verdict(gts, ref, cand)
    assert result["verdict"] == "beyond", result["reason"]
    recall = result["criteria"]["Car moderate 2d@0.70 s>=0.70"]
    assert recall["cand_only"] == 0 and recall["ref_only"] > 400 and recall["status"] == "beyond"
    assert _deployed_recall_unchanged(result)
    assert result["criteria"]["Car AP40 2d@0.70 moderate"]["status"] == "beyond"


def test_every_heading_turned_25_degrees_is_beyond(cars):
    gts, dets = cars
    turn = np.radians(25.0)
    cand = [
        dataclasses.replace(
            d, alpha=gc.wrap(d.alpha + turn), rotation_y=gc.wrap(d.rotation_y + turn)
        )
        for d in dets
    ]
    result = _verdict(gts, dets, cand)
    assert result["verdict"] == "beyond", result["reason"]
    p50 = result["criteria"]["Car easy heading p50"]
    assert p50["ref_only"] >= 450 and p50["cand_only"] == 0 and p50["status"] == "beyond"
    aos = result["criteria"]["Car AP40 aos easy"]
    assert aos["diff"] < -3 and aos["status"] == "beyond"


def test_a_known_share_of_heading_flips_is_beyond_and_named():
    # 10 %: on 250 frames, 5 % (47 objects lost) is not beyond at alpha / (2 K) for a test
    # that allows a frame to gain all its 4 objects (frame_betting)
    gts = _frames(250)
    ref, cand = _detections(gts), _detections(gts, flip_share=0.10)
    turned = [np.abs(gc.wrap(a.alpha - b.alpha)) > 3 for a, b in zip(ref, cand, strict=True)]
    flipped = int(sum(t.sum() for t in turned))
    tables = gc.guard_tables(gts, ref, cand)
    result = pg.decide(tables, frames=len(gts))
    assert result["verdict"] == "beyond"
    assert "heading" in result["deciding"]
    beyond = {n.split(" ", 2)[-1] for n, r in result["criteria"].items() if r["status"] == "beyond"}
    assert beyond and all(n.startswith("heading") for n in beyond)
    heading = result["criteria"]["Car moderate heading"]
    assert heading["ref_only"] == flipped and heading["cand_only"] == 0
    assert heading["diff"] == pytest.approx(-100 * flipped / 1000)
    # the boxes did not move: every box criterion found the same objects
    assert all(r["ref_only"] == r["cand_only"] == 0 for n, r in tables.items() if "@" in n)
    matched = pg.matched_differences(ref, cand)
    assert matched["heading_flips"] == flipped
    assert matched["heading_flip_share"] == pytest.approx(flipped / 1000)


# ----------------------------------------------------------------------------- the rule


def _table(per_frame: int, frames: int, lost_frames=(), gained_frames=()) -> dict:
    """A paired table of ``frames`` frames of ``per_frame`` objects; whole frames lost or
    gained."""
    n = np.full(frames, per_frame)
    lost, gained = np.zeros(frames, np.int64), np.zeros(frames, np.int64)
    lost[list(lost_frames)] = per_frame
    gained[list(gained_frames)] = per_frame
    return {
        "n": int(n.sum()),
        "both": 0,
        "ref_only": int(lost.sum()),
        "cand_only": int(gained.sum()),
        "neither": 0,
        "frame_n": n,
        "frame_ref_only": lost,
        "frame_cand_only": gained,
    }


def test_agreement_on_few_frames_is_undecided_and_the_stated_frames_decide():
    result = pg.decide({"Car easy 3d@0.70": _table(4, 250)}, frames=250)
    assert result["verdict"] == "undecided" and result["look"] == 1
    need = result["frames_needed"]
    # no change: every frame is X = 0.005 * 4 above the margin; a frame could lose all its 4
    # objects, so each bets 0.95 / (0.995 * 4) of the capital, which must reach 1 / (alpha / 4)
    # at the next look: n log(1 + 0.95 * 0.005 / 0.995) >= log(4 / 0.05)
    by_hand = math.ceil(math.log(4 / 0.05) / math.log1p(0.95 * 0.005 / 0.995))
    assert by_hand <= need <= by_hand * 1.02
    assert f"about {need} frames would decide it at look 2" in result["reason"]
    assert pg.decide({"x": _table(4, need)}, need, look=2)["verdict"] == "within"
    assert pg.decide({"x": _table(4, need - 20)}, need - 20, look=2)["verdict"] == "undecided"
    # the same frames at look 1 (more alpha) also decide; later looks spend less
    assert pg.decide({"x": _table(4, by_hand)}, by_hand, look=1)["verdict"] == "within"
    assert pg.decide({"x": _table(4, by_hand)}, by_hand, look=3)["verdict"] == "undecided"


def test_an_ap_entry_decides_too():
    table = {"Car easy 3d@0.70": _table(4, 2000)}
    ap_in = {"Car AP40 3d@0.70 easy": {"diff": 0.3, "se": 0.2}}
    ap_out = {"Car AP40 3d@0.70 easy": {"diff": -1.5, "se": 0.05}}
    assert pg.decide(table, 2000, ap=ap_in)["verdict"] == "within"
    result = pg.decide(table, 2000, ap=ap_out)
    assert result["verdict"] == "beyond" and result["deciding"] == "Car AP40 3d@0.70 easy"
    wide = pg.decide(table, 2000, ap={"Car AP40 3d@0.70 easy": {"diff": 0.3, "se": 0.5}})
    assert wide["verdict"] == "undecided"
    # se shrinks as 1/sqrt(frames): the stated frames make z se fit into the gap of 0.7
    z = 2.241402727604947  # normal quantile at 1 - 0.05 / 4 / 2 (look 2, one side)
    need = wide["frames_needed"]
    assert need == math.ceil(2000 * (z * 0.5 / 0.7) ** 2)
