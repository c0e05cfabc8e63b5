"""KITTI detection AP: hand-computed cases, the real frames, and a loop oracle of the devkit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gac_jax.data.kitti import KittiObjectLayout, KittiObjects, read_label, read_split
from gac_jax.evaluation import kitti_object as ko
from gac_jax.evaluation.ap_table import format_table
from tests import kitti_devkit_oracle as ref


def objects(rows, scores=None):
    """rows: (type, trunc, occ, alpha, (x1, y1, x2, y2), (h, w, l), (x, y, z), ry)."""
    if not rows:
        return KittiObjects.empty()
    t, tr, oc, al, bb, dims, loc, ry = zip(*rows, strict=True)
    return KittiObjects.from_arrays(
        type=list(t),
        truncated=tr,
        occluded=oc,
        alpha=al,
        bbox=np.array(bb, dtype=float),
        dimensions=np.array(dims, dtype=float),
        location=np.array(loc, dtype=float),
        rotation_y=ry,
        score=np.full(len(rows), np.nan) if scores is None else scores,
    )


CAR_DIMS = (1.5, 1.6, 3.9)


def car(box, x, z, alpha=0.0, occ=0, trunc=0.0, kind="Car", dims=CAR_DIMS):
    return (kind, trunc, occ, alpha, box, dims, (x, 1.6, z), 0.0)


def dontcare(box):
    return (
        "DontCare",
        -1.0,
        -1,
        -10.0,
        box,
        (-1.0, -1.0, -1.0),
        (-1000.0, -1000.0, -1000.0),
        -10.0,
    )


def test_get_thresholds_by_hand():
    # 4 valid GT, TP scores .9 .7 .5: recall 1/4, 2/4, 3/4. Every step moves recall by more than
    # 1/40, so each TP starts a new sample: thresholds = all three scores.
    np.testing.assert_array_equal(ko.get_thresholds(np.array([0.5, 0.9, 0.7]), 4), [0.9, 0.7, 0.5])
    # 80 GT and 80 TPs (recall step 1/80): samples 0, 1/40, 2/40 ... need every other score;
    # i=0 and i=1 are both taken (recall 1/80 and 2/80), then i = 3, 5, ..., 79: 41 thresholds.
    scores = np.linspace(1.0, 0.01, 80)
    t = ko.get_thresholds(scores, 80)
    assert len(t) == 41
    np.testing.assert_array_equal(t, scores[[0, 1] + list(range(3, 80, 2))])
    assert ko.get_thresholds(np.zeros(0), 5).shape == (0,)


def test_ap_r11_r40_and_aos_by_hand():
    # One frame, four easy Cars (height 50 px). Detections: TPs on cars 0, 1, 2 with scores
    # .9, .7, .5 and orientation errors 0, pi (flipped), pi/2; a FP with score .8; car 3 missed.
    gt = objects([car((100 * i, 100, 100 * i + 60, 150), 10.0 * i, 20.0) for i in range(4)])
    dt = objects(
        [
            car((0, 100, 60, 150), 0.0, 20.0, alpha=0.0),
            car((100, 100, 160, 150), 10.0, 20.0, alpha=math.pi),
            car((200, 100, 260, 150), 20.0, 20.0, alpha=math.pi / 2),
            car((700, 100, 760, 150), 70.0, 20.0, alpha=0.3),
        ],
        scores=[0.9, 0.7, 0.5, 0.8],
    )
    res = ko.evaluate_detections([gt], [dt], classes=("Car",))
    # Thresholds .9 .7 .5 (see test_get_thresholds_by_hand).
    # t=.9: TP 1, FP 0 -> precision 1;   t=.7: TP 2, FP 1 (.8) -> 2/3;   t=.5: TP 3, FP 1 -> 3/4.
    # Running max from the right: [1, 3/4, 3/4, 0, ... 0] (41 samples).
    # R11 uses samples 0, 4, ..., 40: only sample 0 is non-zero -> 1/11 = 9.0909 %.
    # R40 uses samples 1..40: 3/4 + 3/4 -> 1.5/40 = 3.75 %.
    # AOS similarity (1 + cos d)/2: 1, 0, 0.5. t=.9: 1/1; t=.7: (1 + 0)/3; t=.5: (1 + 0 + .5)/4
    # -> [1, 1/3, .375] -> max from right [1, .375, .375]: R11 1/11, R40 .75/40 = 1.875 %.
    for key in ("0.70", "0.50"):
        entry11 = res["ap11"]["Car"][key]
        entry40 = res["ap40"]["Car"][key]
        for metric in ("bbox", "bev", "3d"):
            assert entry11[metric] == pytest.approx([100 / 11] * 3, abs=1e-9)
            assert entry40[metric] == pytest.approx([3.75] * 3, abs=1e-9)
        assert entry11["aos"] == pytest.approx([100 / 11] * 3, abs=1e-9)
        assert entry40["aos"] == pytest.approx([1.875] * 3, abs=1e-9)


def test_ignore_rules_by_hand():
    # Ground truth: A, F easy Cars; B a Van (neighbour class); C a Car occluded 2 (hard only);
    # D a DontCare region; E a Car only 20 px tall (ignored at every difficulty).
    gt = objects(
        [
            car((0, 100, 60, 150), 0.0, 20.0),  # A
            car((100, 100, 160, 150), 10.0, 20.0, kind="Van"),  # B
            car((200, 100, 260, 150), 20.0, 20.0, occ=2),  # C
            dontcare((300, 100, 400, 150)),  # D
            car((500, 100, 530, 120), 50.0, 20.0),  # E
            car((600, 100, 660, 150), 60.0, 20.0),  # F
        ]
    )
    dt = objects(
        [
            car((0, 100, 60, 150), 0.0, 20.0),  # a on A
            car((100, 100, 160, 150), 10.0, 20.0),  # b: a Car on the Van
            car((200, 100, 260, 150), 20.0, 20.0),  # c on C
            car((310, 105, 390, 150), -30.0, 5.0),  # d inside DontCare (3D box elsewhere)
            car((500, 100, 530, 120), 50.0, 20.0),  # e on E (20 px: ignored detection)
            car((2, 100, 58, 150), 0.0, 20.0, kind="Pedestrian"),  # f other class on A
            car((600, 100, 660, 150), 60.0, 20.0),  # on F
        ],
        scores=[0.9, 0.8, 0.7, 0.6, 0.5, 0.95, 0.4],
    )
    res = ko.evaluate_detections([gt], [dt], classes=("Car",))
    strict = res["ap40"]["Car"]["0.70"]
    # easy / moderate: 2 valid GT (A, F); TP scores .9 .4 -> thresholds [.9, .4].
    #   t=.4: a, F TPs; b on the Van and c on the ignored hard car are neither TP nor FP; e is
    #   too small; f is another class; d is in the DontCare region: not a FP for bbox.
    #   bbox precision [1, 1] -> R40 = 1/40 = 2.5 %.  For bev/3d the DontCare region has no 3D
    #   extent, so d is a FP: precision [1, 2/3] -> R40 = (2/3)/40.
    # hard: C counts (3 valid GT), TP scores .9 .7 .4, precision 1 at all three -> 2/40 = 5 %;
    #   bev/3d: t=.9 1, t=.7 1, t=.4 3/4 (d) -> R40 = (1 + 3/4)/40.
    assert strict["bbox"] == pytest.approx([2.5, 2.5, 5.0], abs=1e-9)
    assert strict["bev"] == pytest.approx([200 / 3 / 40, 200 / 3 / 40, 175 / 40], abs=1e-9)
    assert strict["3d"] == strict["bev"]
    assert res["ap11"]["Car"]["0.70"]["bbox"] == pytest.approx([100 / 11] * 3, abs=1e-9)


def test_aos_off_when_any_alpha_is_invalid():
    gt = objects([car((0, 100, 60, 150), 0.0, 20.0)])
    dt = objects([car((0, 100, 60, 150), 0.0, 20.0, alpha=-10.0)], scores=[0.5])
    res = ko.evaluate_detections([gt], [dt])
    assert res["ap40"]["Car"]["0.70"]["aos"] is None
    assert res["ap40"]["Car"]["0.70"]["bbox"] == [0.0, 0.0, 0.0]  # 1 GT: only sample 0


def test_result_schema_and_table():
    gt = objects([car((0, 100, 60, 150), 0.0, 20.0)])
    dt = objects([car((0, 100, 60, 150), 0.0, 20.0)], scores=[0.5])
    res = ko.evaluate_detections([gt], [dt])
    assert set(res) == {"ap11", "ap40"}
    for ap in res.values():
        assert list(ap) == ["Car", "Pedestrian", "Cyclist"]
        assert list(ap["Car"]) == ["0.70", "0.50"]
        assert list(ap["Pedestrian"]) == ["0.50", "0.25"]
        assert list(ap["Cyclist"]) == ["0.50", "0.25"]
        for per_cls in ap.values():
            for entry in per_cls.values():
                assert list(entry) == ["bbox", "aos", "bev", "3d"]
                assert all(
                    len(v) == 3 and all(isinstance(x, float) for x in v) for v in entry.values()
                )
    table = format_table(res)
    assert (
        "AP|R40" in table and "AP|R11" in table and "Pedestrian @ bbox 0.50, bev/3d 0.25" in table
    )
    with pytest.raises(ValueError, match="unsupported class"):
        ko.evaluate_detections([gt], [dt], classes=("Van",))


# ------------------------------------------------------------------------------ real frames


def _real_frames(root):
    layout = KittiObjectLayout(root)
    return [read_label(layout.label(i)) for i in layout.frame_ids("labeled")]


def _perfect(gt):
    keep = gt.type != "DontCare"
    return gt.select(keep).replace(score=np.ones(int(keep.sum())))


def _valid_counts(gts, cls, difficulty):
    n = 0
    for g in gts:
        for i in range(len(g)):
            h = g.bbox[i, 3] - g.bbox[i, 1]
            n += (
                g.type[i] == cls
                and g.occluded[i] <= ko.MAX_OCCLUSION[difficulty]
                and g.truncated[i] <= ko.MAX_TRUNCATION[difficulty]
                and h > ko.MIN_HEIGHT[difficulty]
            )
    return n


def test_perfect_detections_on_real_frames(kitti_object_root):
    gts = _real_frames(kitti_object_root)
    assert len(gts) == len(read_split(kitti_object_root / "ImageSets" / "labeled.txt"))
    res = ko.evaluate_detections(gts, [_perfect(g) for g in gts])
    # The devkit indexes precision by threshold, one threshold per TP while n <= 40 valid
    # objects: perfect detections of n objects give precision 1 at samples 0..n-1 only, so
    # AP|R40 = (n - 1)/40 and AP|R11 = (number of multiples of 4 below n)/11 -- not 100.
    checked = 0
    for cls in ko.CLASSES:
        for d in range(3):
            n = _valid_counts(gts, cls, d)
            exp40 = 100.0 * max(min(n, 41) - 1, 0) / 40.0
            exp11 = 100.0 * len(range(0, min(n, 41), 4)) / 11.0
            for key in res["ap40"][cls]:
                for metric in ("bbox", "bev", "3d", "aos"):
                    assert res["ap40"][cls][key][metric][d] == pytest.approx(exp40, abs=1e-9)
                    assert res["ap11"][cls][key][metric][d] == pytest.approx(exp11, abs=1e-9)
            checked += n > 0
    assert checked >= 6  # Car and Pedestrian at least, all difficulties


def test_perfect_and_noisy_detections_on_replicated_real_frames(kitti_object_root):
    # Repeating the real frames 41 times gives every class/difficulty present >= 41 objects,
    # enough for the 41 recall samples: perfect detections then score exactly 100.
    frames = _real_frames(kitti_object_root)
    gts = frames * 41
    res = ko.evaluate_detections(gts, [_perfect(g) for g in gts])
    for cls in ko.CLASSES:
        for d in range(3):
            if _valid_counts(frames, cls, d) == 0:
                continue
            for ap in ("ap11", "ap40"):
                for entry in res[ap][cls].values():
                    for metric in ("bbox", "bev", "3d", "aos"):
                        assert entry[metric][d] == pytest.approx(100.0, abs=1e-9), (cls, d, metric)

    # More noise -> lower AP. Noise on the 3D location and 2D box, random scores.
    rng = np.random.default_rng(0)
    scores = [rng.random(int(np.sum(g.type != "DontCare"))) for g in gts]
    moderate_car = []
    for sigma in (0.0, 0.15, 0.4, 1.0):
        noisy = []
        for g, s in zip(gts, scores, strict=True):
            p = _perfect(g)
            n = len(p)
            noisy.append(
                p.replace(
                    location=p.location + rng.normal(0, sigma, (n, 3)) * [1, 0.3, 1],
                    bbox=p.bbox + rng.normal(0, 10 * sigma, (n, 4)),
                    score=s,
                )
            )
        r = ko.evaluate_detections(gts, noisy, classes=("Car",))["ap40"]["Car"]
        moderate_car.append((r["0.70"]["3d"][1], r["0.50"]["3d"][1], r["0.70"]["bbox"][1]))
    strict3d, loose3d, bbox = zip(*moderate_car, strict=True)
    assert strict3d[0] == pytest.approx(100.0) and all(np.diff(strict3d) < 0)
    assert all(np.diff(loose3d) < 0)
    # (2D IoU 0.7 tolerates the smallest box noise, 1.5 px, on these few cars: no drop there)
    assert all(np.diff(bbox) <= 0) and all(np.diff(bbox[1:]) < 0)
    assert all(lo >= st for lo, st in zip(loose3d, strict3d, strict=True))

    # Detections of the wrong frames are mostly false positives.
    # (each frame gets the next real frame's: never its own)
    shuffled = [_perfect(gts[(i + 1) % len(gts)]) for i in range(len(gts))]
    r = ko.evaluate_detections(gts, shuffled, classes=("Car",))["ap40"]["Car"]["0.70"]
    assert r["3d"][1] < strict3d[-1] and r["bbox"][1] < 30.0


# ------------------------------------------------------------------------------ oracle


def _dense_random_set(rng, n_frames):
    """Crowded small scenes: many overlapping boxes, tied scores, all special cases."""
    kinds = ["Car", "Van", "Pedestrian", "Person_sitting", "Cyclist", "DontCare", "Truck"]
    gts, dts = [], []
    for _ in range(n_frames):
        rows = []
        for _ in range(rng.integers(0, 9)):
            k = kinds[rng.choice(7, p=[0.35, 0.1, 0.2, 0.05, 0.12, 0.13, 0.05])]
            x1, y1 = rng.uniform(0, 300), rng.uniform(100, 200)
            box = (x1, y1, x1 + rng.uniform(10, 120), y1 + rng.uniform(15, 70))
            dims = tuple(rng.uniform(0.5, 4.0, 3))
            loc = (rng.uniform(-4, 4), rng.uniform(1.0, 2.0), rng.uniform(10, 18))
            if k == "DontCare" and rng.random() < 0.5:
                rows.append(dontcare(box))  # placeholder 3D box, as in real labels
            else:  # some DontCare regions with a real 3D box exercise the cpp's BEV/3D rule
                rows.append(
                    (
                        k,
                        rng.choice([0.0, 0.1, 0.2, 0.4, 0.6]),
                        int(rng.integers(0, 4)),
                        rng.uniform(-3, 3),
                        box,
                        dims,
                        loc,
                        rng.uniform(-3, 3),
                    )
                )
        gt = objects(rows)
        drows = []
        for i in range(len(gt)):
            if gt.type[i] == "DontCare" or rng.random() < 0.2:
                continue
            for _ in range(rng.integers(1, 3)):  # duplicates compete for the same GT
                jit = rng.normal(0, 4, 4)
                t = (
                    gt.type[i]
                    if rng.random() < 0.8
                    else rng.choice(["Car", "Pedestrian", "Cyclist"])
                )
                drows.append(
                    (
                        t,
                        0.0,
                        0,
                        gt.alpha[i] + rng.normal(0, 0.5),
                        tuple(gt.bbox[i] + jit),
                        tuple(gt.dimensions[i] * rng.uniform(0.8, 1.2, 3)),
                        tuple(gt.location[i] + rng.normal(0, 0.4, 3)),
                        gt.rotation_y[i] + rng.normal(0, 0.3),
                    )
                )
        for _ in range(rng.integers(0, 4)):
            x1, y1 = rng.uniform(0, 300), rng.uniform(100, 200)
            drows.append(
                (
                    rng.choice(["Car", "Pedestrian", "Cyclist"]),
                    0.0,
                    0,
                    rng.uniform(-3, 3),
                    (x1, y1, x1 + rng.uniform(10, 120), y1 + rng.uniform(15, 70)),
                    tuple(rng.uniform(0.5, 4.0, 3)),
                    (rng.uniform(-4, 4), rng.uniform(1.0, 2.0), rng.uniform(10, 18)),
                    rng.uniform(-3, 3),
                )
            )
        scores = np.round(rng.random(len(drows)), 1)  # many ties
        dts.append(objects(drows, scores=scores))
        gts.append(gt)
    return gts, dts


@pytest.mark.parametrize("seed", [0, 1])
def test_matches_loop_oracle_of_the_devkit(seed):
    rng = np.random.default_rng(seed)
    gts, dts = _dense_random_set(rng, 50)
    evalset = ko.DetectionEvalSet(gts, dts)
    g_rec = [ref.to_records(g) for g in gts]
    d_rec = [ref.to_records(d) for d in dts]
    n_nonzero = 0
    for cls in ko.CLASSES:
        for metric_idx, metric in enumerate(ko.METRICS):
            for min_overlap in sorted({s[metric_idx] for s in ko.MIN_OVERLAPS[cls]}):
                with_aos = metric == "bbox"
                for d in range(3):
                    prec, aos = evalset.precision_curves(cls, d, metric, min_overlap, with_aos)
                    ref_prec, ref_aos = ref.eval_class(
                        g_rec, d_rec, cls, d, metric, min_overlap, with_aos
                    )
                    np.testing.assert_allclose(prec, ref_prec, rtol=0, atol=1e-12)
                    if with_aos:
                        np.testing.assert_allclose(aos, ref_aos, rtol=0, atol=1e-12)
                    for points in (11, 40):
                        assert ko.average_precision(prec, points) == pytest.approx(
                            ref.ap(ref_prec, points), abs=1e-9
                        )
                    n_nonzero += prec[0] > 0
    assert n_nonzero >= 25  # of 45 curves: the random sets produce real precision curves
    # DontCare regions with a real 3D box suppress BEV/3D false positives (the cpp's rule).
    assert (evalset.dontcare_overlap("bev") > 0.25).any()
    assert (evalset.dontcare_overlap("3d") > 0.25).any()
