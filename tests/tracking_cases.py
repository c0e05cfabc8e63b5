"""KITTI tracking label / result files for the tracking-evaluation tests and the oracle script.

``write_case(name, root)`` writes ``root/label_02/SSSS.txt``, ``root/results/SSSS.txt``
(every labelled sequence has a result file, possibly empty, as the official evaluation
wants) and the seqmap ``root/evaluate_tracking.seqmap.training`` (the sequences to score and
their lengths), and returns the number of frames of each sequence of the seqmap. The official
figures of every case are in ``tests/data/tracking/trackeval_figures.json``
(benchmarks/trackeval_oracle.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

# "hand": each line of a sequence is (frame, id, type, trunc, occ, x1, y1, x2, y2[, score]).
# 3D fields are a car-sized box 10 m ahead, shifted with the id so that 3D IoUs stay simple.
HAND_LABELS = {
    "0000": [
        # car 1 tracked in frames 0-5; car 2 in 0-5; a Van in 0-2; DontCare in 0-5
        *[(f, 1, "Car", 0, 0, 100 + 5 * f, 100, 200 + 5 * f, 180) for f in range(6)],
        *[(f, 2, "Car", 0, 1, 400, 120, 480, 200) for f in range(6)],
        *[(f, 3, "Van", 0, 0, 600, 100, 700, 200) for f in range(3)],
        *[(f, -1, "DontCare", -1, -1, 800, 50, 900, 150) for f in range(6)],
        # a truncated car (level 1) and a car of unknown occlusion (3): scored as neither
        (1, 4, "Car", 1, 0, 0, 100, 60, 200),
        (2, 5, "Car", 0, 3, 300, 300, 360, 360),
        # pedestrian 6 and a sitting person 7
        *[(f, 6, "Pedestrian", 0, 0, 250, 150, 280, 230) for f in range(4)],
        *[(f, 7, "Person", 0, 0, 520, 150, 550, 230) for f in range(2)],
        # frame 6 has no object at all (an empty frame); frame 7 has car 1 again
        (7, 1, "Car", 0, 0, 140, 100, 240, 180),
    ],
    "0001": [],  # a sequence with no objects
    "0002": [*[(f, 0, "Car", 0, 0, 10, 10, 110, 90) for f in range(3)]],
}
HAND_RESULTS = {
    "0000": [
        # car 1: id 10 in frames 0-2, missed in 3, id 11 in 4-5 (an id switch + a fragment)
        *[(f, 10, "Car", 0, 0, 102 + 5 * f, 101, 201 + 5 * f, 181, 0.9) for f in range(3)],
        *[(f, 11, "Car", 0, 0, 101 + 5 * f, 99, 199 + 5 * f, 179, 0.8) for f in (4, 5)],
        (7, 11, "Car", 0, 0, 141, 100, 241, 180, 0.8),
        # car 2: id 20 throughout, loose in frame 2 (IoU < 0.5: a FP and a FN)
        *[(f, 20, "Car", 0, 0, 402, 121, 481, 201, 0.7) for f in (0, 1, 3, 4, 5)],
        (2, 20, "Car", 0, 0, 440, 160, 520, 240, 0.7),
        # on the Van (removed), inside the DontCare region (removed), a 20 px box (removed)
        *[(f, 30, "Car", 0, 0, 602, 101, 701, 199, 0.6) for f in range(3)],
        (0, 31, "Car", 0, 0, 810, 60, 880, 140, 0.5),
        (1, 32, "Car", 0, 0, 700, 300, 760, 320, 0.5),
        # on the truncated and the occluded car (removed); a real false positive
        (1, 33, "Car", 0, 0, 2, 100, 61, 201, 0.5),
        (2, 34, "Car", 0, 0, 301, 301, 360, 359, 0.5),
        (3, 35, "Car", 0, 0, 900, 300, 1000, 380, 0.4),
        # pedestrian: id 60 frames 0-3; a box on the sitting person (removed)
        *[(f, 60, "Pedestrian", 0, 0, 251, 151, 281, 231, 0.9) for f in range(4)],
        (0, 61, "Pedestrian", 0, 0, 521, 151, 551, 231, 0.5),
        # a Van result box is not a Car result (ignored for Car)
        (5, 70, "Van", 0, 0, 600, 100, 700, 200, 0.5),
    ],
    "0001": [(2, 5, "Car", 0, 0, 10, 10, 100, 100, 0.3)],  # FPs in a sequence with no objects
    "0002": [],  # labels but no result box
}


def _line(row, with_score: bool) -> str:
    frame, tid, typ, trunc, occ, x1, y1, x2, y2, *score = row
    ox = 2.0 * (tid % 7) - 6.0
    loc = f"{ox + (x1 - 100) / 100:.3f} 1.6 {10 + 3 * (tid % 5):.3f}"
    dims = "1.5 1.6 3.9" if typ != "DontCare" else "-1 -1 -1"
    if typ == "DontCare":
        loc = "-1000 -1000 -1000"
    text = f"{frame} {tid} {typ} {trunc} {occ} -10 {x1} {y1} {x2} {y2} {dims} {loc} 0.0"
    if with_score:
        text += f" {score[0] if score else 1.0}"
    return text + "\n"


def _write(folder: Path, seqs: dict[str, list], with_score: bool) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for name, rows in seqs.items():
        (folder / f"{name}.txt").write_text("".join(_line(r, with_score) for r in rows))


def _generated(seed: int, n_seq: int, n_frames: int):
    """Random scenes: moving boxes with gaps, id switches, noise, distractors, DontCare."""
    rng = np.random.default_rng(seed)
    labels, results = {}, {}
    types = ["Car", "Car", "Car", "Van", "Pedestrian", "Pedestrian", "Person", "Cyclist"]
    for s in range(n_seq):
        gt_rows, tr_rows = [], []
        next_tid = 100
        for obj in range(int(rng.integers(0, 14))):
            typ = types[int(rng.integers(len(types)))]
            start = int(rng.integers(0, n_frames - 2))
            length = int(rng.integers(2, n_frames - start + 1))
            x, y = rng.uniform(0, 1100), rng.uniform(80, 250)
            w, h = (
                (rng.uniform(30, 70), rng.uniform(60, 130))
                if typ in ("Pedestrian", "Person")
                else (
                    rng.uniform(40, 200),
                    rng.uniform(20, 120),
                )
            )
            vx = rng.normal(0, 6)
            tid = next_tid
            for f in range(start, start + length):
                x += vx
                trunc = int(rng.random() < 0.05)
                occ = int(rng.choice([0, 1, 2, 3], p=[0.6, 0.2, 0.15, 0.05]))
                box = (round(x, 2), round(y, 2), round(x + w, 2), round(y + h, 2))
                gt_rows.append((f, obj, typ, trunc, occ, *box))
                if rng.random() < 0.15:  # missed
                    continue
                if rng.random() < 0.04:  # id switch
                    next_tid += 1
                    tid = next_tid
                noise = rng.normal(0, 0.06 * w, 4)
                pred = tuple(round(float(v), 2) for v in np.array(box) + noise)
                rtype = "Car" if typ in ("Car", "Van") else typ
                if typ == "Person":
                    rtype = "Pedestrian"
                tr_rows.append((f, tid, rtype, 0, 0, *pred, round(float(rng.uniform(0.1, 1)), 3)))
            next_tid += 1
        for f in range(n_frames):
            if rng.random() < 0.3:  # a false positive
                x, y = rng.uniform(0, 1100), rng.uniform(50, 300)
                w, h = rng.uniform(15, 120), rng.uniform(15, 110)
                typ = "Car" if rng.random() < 0.6 else "Pedestrian"
                box = tuple(round(float(v), 2) for v in (x, y, x + w, y + h))
                tr_rows.append((f, next_tid, typ, 0, 0, *box, round(float(rng.uniform(0, 1)), 3)))
                next_tid += 1
            if rng.random() < 0.2:  # a DontCare region
                x, y = rng.uniform(0, 1100), rng.uniform(50, 300)
                box = tuple(round(float(v), 2) for v in (x, y, x + 80, y + 60))
                gt_rows.append((f, -1, "DontCare", -1, -1, *box))
        labels[f"{s:04d}"] = sorted(gt_rows, key=lambda r: r[0])
        results[f"{s:04d}"] = sorted(tr_rows, key=lambda r: r[0])
    return labels, results


def _overlapping(seed: int, n_frames: int):
    """Pairs of cars a few pixels apart, tracked with noise larger than the gap: every frame
    has several matchings above IoU 0.5, and continuing the previous one decides."""
    rng = np.random.default_rng(seed)
    gt_rows, tr_rows = [], []
    for pair in range(3):
        x, y = 150.0 + 300 * pair, 120.0
        for f in range(n_frames):
            for k in range(2):
                box = (x + 6 * k + 2 * f, y, x + 6 * k + 2 * f + 100, y + 80)
                gt_rows.append((f, 2 * pair + k, "Car", 0, 0, *box))
                if rng.random() < 0.1:
                    continue
                tid = 10 * pair + k + (5 if f >= n_frames // 2 and k == 0 and pair == 1 else 0)
                pred = tuple(round(float(v), 2) for v in np.array(box) + rng.normal(0, 4, 4))
                tr_rows.append((f, tid, "Car", 0, 0, *pred, round(float(rng.uniform(0.3, 1)), 3)))
    return {"0000": gt_rows}, {"0000": tr_rows}


def clean_3d_lines(seed: int = 5, n_frames: int = 20) -> tuple[dict, dict]:
    """Label and result *lines* of one sequence for the 3D MOT metrics: three cars with 3D
    boxes (BEV noise only), tracked with an id switch (no gap), a late start and scored
    tracks, and low-scored false-positive tracks. Nothing is ignored, no track has a gap
    after it starts and no frame has two candidate matches, so the older KITTI devkit code
    AB3DMOT's script builds on and the CLEAR matching here count the same."""
    rng = np.random.default_rng(seed)
    gt, res = [], []
    cars = [(-4.0, 12.0, 0.3), (0.5, 20.0, -0.2), (5.0, 30.0, 0.4)]  # x, z, z-speed per frame
    for f in range(n_frames):
        for k, (x, z0, vz) in enumerate(cars):
            z = z0 + vz * f
            u, half = 600 + 700 * x / z, 700 * 0.8 / z
            box2d = (
                f"{u - half:.2f} {170 - 700 * 0.1 / z:.2f} {u + half:.2f} {170 + 700 * 1.6 / z:.2f}"
            )
            gt.append(f"{f} {k} Car 0 0 0 {box2d} 1.50 1.60 3.90 {x:.4f} 1.6000 {z:.4f} 0.1000\n")
            if k == 2 and f < 4:  # car 2 is found late
                continue
            tid = {0: 1, 1: 2 if f < 11 else 3, 2: 4}[k]  # car 1 switches from track 2 to 3
            score = {1: 0.9, 2: 0.7, 3: 0.55, 4: 0.4}[tid] + 0.01 * rng.random()
            dx, dz = rng.normal(0, 0.15 + 0.15 * k, 2)
            res.append(
                f"{f} {tid} Car 0 0 0 {box2d} 1.50 1.60 3.90 {x + dx:.4f} 1.6000 {z + dz:.4f} "
                f"0.1000 {score:.4f}\n"
            )
        if f % 4 == 0:  # a short false-positive track far from the cars
            tid = 100 + f
            for g in range(f, min(f + 2, n_frames)):
                res.append(
                    f"{g} {tid} Car 0 0 0 100.00 150.00 160.00 200.00 1.50 1.60 3.90 "
                    f"-9.0000 1.6000 {45 + g:.4f} 0.1000 {0.1 + 0.01 * f:.4f}\n"
                )
    res.sort(key=lambda line: int(line.split()[0]))
    return {"0000": gt}, {"0000": res}


CASES = ("hand", "generated_1", "generated_2", "crowded", "overlapping", "seqmap_subset")
# a case whose seqmap lists some of its sequences, each 5 frames longer than its lines reach
SUBSET = {"seqmap_subset": ("generated_1", ("0001", "0003"), 5)}


def case_files(name: str) -> tuple[dict, dict]:
    """(labels, results): sequence -> rows, of a named case."""
    if name in SUBSET:
        return case_files(SUBSET[name][0])
    if name == "hand":
        return HAND_LABELS, HAND_RESULTS
    if name == "generated_1":
        return _generated(1, n_seq=4, n_frames=40)
    if name == "generated_2":
        return _generated(2, n_seq=3, n_frames=60)
    if name == "overlapping":
        return _overlapping(4, n_frames=25)
    if name == "crowded":  # many overlapping boxes: the per-frame Hungarian has real choices
        labels, results = _generated(3, n_seq=2, n_frames=30)
        for seq in labels:
            labels[seq] = [
                (*r[:5], r[5] % 300, r[6], r[5] % 300 + (r[7] - r[5]), r[8]) for r in labels[seq]
            ]
            results[seq] = [
                (*r[:5], r[5] % 300, r[6], r[5] % 300 + (r[7] - r[5]), *r[8:]) for r in results[seq]
            ]
        return labels, results
    raise KeyError(name)


def write_case(name: str, root: Path) -> dict[str, int]:
    """Writes a case under ``root``; returns ``{sequence: number of frames}`` of its seqmap."""
    labels, results = case_files(name)
    _write(root / "label_02", labels, with_score=False)
    _write(root / "results", results, with_score=True)
    listed, extra = (SUBSET[name][1], SUBSET[name][2]) if name in SUBSET else (labels, 0)
    frames = {}
    for seq in listed:
        used = [r[0] for r in labels[seq]] + [r[0] for r in results.get(seq, [])]
        frames[seq] = max(used, default=0) + 1 + extra
    seqmap = "".join(f"{seq} empty 000000 {n:06d}\n" for seq, n in frames.items())
    (root / "evaluate_tracking.seqmap.training").write_text(seqmap)
    return frames
