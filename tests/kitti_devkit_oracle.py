"""Straightforward loop-based float64 transcription of the official KITTI devkit
(``evaluate_object.cpp``: cleanData, computeStatistics, getThresholds, eval_class),
used only as an independent oracle in tests. Overlaps use shapely for the rotated
ground-plane rectangles. Slow on purpose: one Python loop per box pair.
"""

from __future__ import annotations

import math

import numpy as np
from shapely.geometry import Polygon

MIN_HEIGHT = [40, 25, 25]
MAX_OCCLUSION = [0, 1, 2]
MAX_TRUNCATION = [0.15, 0.3, 0.5]
N_SAMPLE_PTS = 41


def _polygon(x, z, l, w, ry):
    c, s = math.cos(ry), math.sin(ry)
    pts = []
    for px, pz in ((l / 2, w / 2), (l / 2, -w / 2), (-l / 2, -w / 2), (-l / 2, w / 2)):
        pts.append((c * px + s * pz + x, -s * px + c * pz + z))
    return Polygon(pts)


def image_overlap(a, b, criterion=-1):
    """a, b: xyxy tuples (a = detection)."""
    x1, y1 = max(a[0], b[0]), max(a[1], b[1])
    x2, y2 = min(a[2], b[2]), min(a[3], b[3])
    w, h = x2 - x1, y2 - y1
    if w <= 0 or h <= 0:
        return 0.0
    inter = w * h
    area_a = (a[2] - a[0]) * (a[3] - a[1])
    area_b = (b[2] - b[0]) * (b[3] - b[1])
    if criterion == -1:
        return inter / (area_a + area_b - inter)
    if criterion == 0:
        return inter / area_a
    return inter / area_b


def ground_overlap(d, g, criterion=-1):
    """d, g: dicts with loc (x, y, z), dims (h, w, l), ry (d = detection)."""
    pd = _polygon(d["loc"][0], d["loc"][2], abs(d["dims"][2]), abs(d["dims"][1]), d["ry"])
    pg = _polygon(g["loc"][0], g["loc"][2], abs(g["dims"][2]), abs(g["dims"][1]), g["ry"])
    inter = pd.intersection(pg).area
    if criterion == -1:
        union = pd.area + pg.area - inter
        return inter / union if union > 0 else 0.0
    area = pd.area if criterion == 0 else pg.area
    return inter / area if area > 0 else 0.0


def box3d_overlap(d, g, criterion=-1):
    pd = _polygon(d["loc"][0], d["loc"][2], abs(d["dims"][2]), abs(d["dims"][1]), d["ry"])
    pg = _polygon(g["loc"][0], g["loc"][2], abs(g["dims"][2]), abs(g["dims"][1]), g["ry"])
    inter_area = pd.intersection(pg).area
    ymax = min(d["loc"][1], g["loc"][1])
    ymin = max(d["loc"][1] - d["dims"][0], g["loc"][1] - g["dims"][0])
    inter = inter_area * max(0.0, ymax - ymin)
    vd = d["dims"][0] * d["dims"][1] * d["dims"][2]
    vg = g["dims"][0] * g["dims"][1] * g["dims"][2]
    denom = {-1: vd + vg - inter, 0: vd, 1: vg}[criterion]
    return inter / denom if denom > 0 else 0.0


def overlap(metric, d, g, criterion=-1):
    if metric == "bbox":
        return image_overlap(d["bbox"], g["bbox"], criterion)
    if metric == "bev":
        return ground_overlap(d, g, criterion)
    return box3d_overlap(d, g, criterion)


def to_records(objs):
    out = []
    for i in range(len(objs)):
        out.append(
            dict(
                type=str(objs.type[i]),
                trunc=float(objs.truncated[i]),
                occ=int(objs.occluded[i]),
                alpha=float(objs.alpha[i]),
                bbox=tuple(float(v) for v in objs.bbox[i]),
                dims=tuple(float(v) for v in objs.dimensions[i]),
                loc=tuple(float(v) for v in objs.location[i]),
                ry=float(objs.rotation_y[i]),
                score=float(objs.score[i]),
            )
        )
    return out


def clean_data(cls, gt, det, difficulty):
    ignored_gt, ignored_det, dc = [], [], []
    n_gt = 0
    cname = cls.lower()
    for g in gt:
        height = g["bbox"][3] - g["bbox"][1]
        t = g["type"].lower()
        if t == cname:
            valid = 1
        elif (cname, t) in (("pedestrian", "person_sitting"), ("car", "van")):
            valid = 0
        else:
            valid = -1
        ignore = (
            g["occ"] > MAX_OCCLUSION[difficulty]
            or g["trunc"] > MAX_TRUNCATION[difficulty]
            or height <= MIN_HEIGHT[difficulty]
        )
        if valid == 1 and not ignore:
            ignored_gt.append(0)
            n_gt += 1
        elif valid == 0 or (ignore and valid == 1):
            ignored_gt.append(1)
        else:
            ignored_gt.append(-1)
    for g in gt:
        if g["type"].lower() == "dontcare":
            dc.append(g)
    for d in det:
        valid = 1 if d["type"].lower() == cname else -1
        height = int(abs(d["bbox"][1] - d["bbox"][3]))
        if height < MIN_HEIGHT[difficulty]:
            ignored_det.append(1)
        elif valid == 1:
            ignored_det.append(0)
        else:
            ignored_det.append(-1)
    return ignored_gt, dc, ignored_det, n_gt


def compute_statistics(
    gt,
    det,
    dc,
    ignored_gt,
    ignored_det,
    compute_fp,
    ov_gt,
    ov_dc,
    min_overlap,
    compute_aos=False,
    thresh=0.0,
):
    """``ov_gt[j][i]``: overlap of detection j and ground truth i (criterion -1);
    ``ov_dc[j][k]``: overlap of detection j with DontCare k by detection area (criterion 0)."""
    NO_DETECTION = -10000000.0
    tp = fp = fn = 0
    v = []
    delta = []
    assigned = [False] * len(det)
    ignored_threshold = [False] * len(det)
    if compute_fp:
        for i, d in enumerate(det):
            if d["score"] < thresh:
                ignored_threshold[i] = True
    for i, g in enumerate(gt):
        if ignored_gt[i] == -1:
            continue
        det_idx = -1
        valid_detection = NO_DETECTION
        max_overlap = 0.0
        assigned_ignored_det = False
        for j, d in enumerate(det):
            if ignored_det[j] == -1 or assigned[j] or ignored_threshold[j]:
                continue
            ov = ov_gt[j][i]
            if not compute_fp and ov > min_overlap and d["score"] > valid_detection:
                det_idx = j
                valid_detection = d["score"]
            elif (
                compute_fp
                and ov > min_overlap
                and (ov > max_overlap or assigned_ignored_det)
                and ignored_det[j] == 0
            ):
                max_overlap = ov
                det_idx = j
                valid_detection = 1
                assigned_ignored_det = False
            elif (
                compute_fp
                and ov > min_overlap
                and valid_detection == NO_DETECTION
                and ignored_det[j] == 1
            ):
                det_idx = j
                valid_detection = 1
                assigned_ignored_det = True
        if valid_detection == NO_DETECTION and ignored_gt[i] == 0:
            fn += 1
        elif valid_detection != NO_DETECTION and (ignored_gt[i] == 1 or ignored_det[det_idx] == 1):
            assigned[det_idx] = True
        elif valid_detection != NO_DETECTION:
            tp += 1
            v.append(det[det_idx]["score"])
            if compute_aos:
                delta.append(g["alpha"] - det[det_idx]["alpha"])
            assigned[det_idx] = True
    similarity = 0.0
    if compute_fp:
        for i in range(len(det)):
            if not (
                assigned[i] or ignored_det[i] == -1 or ignored_det[i] == 1 or ignored_threshold[i]
            ):
                fp += 1
        nstuff = 0
        for k in range(len(dc)):
            for j in range(len(det)):
                if assigned[j] or ignored_det[j] in (-1, 1) or ignored_threshold[j]:
                    continue
                if ov_dc[j][k] > min_overlap:
                    assigned[j] = True
                    nstuff += 1
        fp -= nstuff
        if compute_aos:
            tmp = [0.0] * fp + [(1.0 + math.cos(x)) / 2.0 for x in delta]
            similarity = sum(tmp) if (tp > 0 or fp > 0) else -1
    return dict(tp=tp, fp=fp, fn=fn, v=v, similarity=similarity)


def get_thresholds(v, n_gt):
    v = sorted(v, reverse=True)
    t = []
    current = 0.0
    for i in range(len(v)):
        l_recall = (i + 1) / n_gt
        r_recall = (i + 2) / n_gt if i < len(v) - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < len(v) - 1:
            continue
        t.append(v[i])
        current += 1.0 / (N_SAMPLE_PTS - 1.0)
    return t


def eval_class(gt_frames, dt_frames, cls, difficulty, metric, min_overlap, compute_aos):
    """Returns (precision[41], aos[41] or None) after the running max, as the devkit."""
    n_gt = 0
    v = []
    cleaned = []
    for gt, det in zip(gt_frames, dt_frames, strict=True):
        ig, dc, idet, n = clean_data(cls, gt, det, difficulty)
        n_gt += n
        ov_gt = [[overlap(metric, d, g, -1) for g in gt] for d in det]
        ov_dc = [[overlap(metric, d, c, 0) for c in dc] for d in det]
        cleaned.append((ig, dc, idet, ov_gt, ov_dc))
        st = compute_statistics(gt, det, dc, ig, idet, False, ov_gt, ov_dc, min_overlap)
        v += st["v"]
    thresholds = get_thresholds(v, n_gt)
    pr = [dict(tp=0, fp=0, fn=0, sim=0.0) for _ in thresholds]
    for (gt, det), (ig, dc, idet, ov_gt, ov_dc) in zip(
        zip(gt_frames, dt_frames, strict=True), cleaned, strict=True
    ):
        for ti, th in enumerate(thresholds):
            st = compute_statistics(
                gt, det, dc, ig, idet, True, ov_gt, ov_dc, min_overlap, compute_aos, th
            )
            pr[ti]["tp"] += st["tp"]
            pr[ti]["fp"] += st["fp"]
            pr[ti]["fn"] += st["fn"]
            if st["similarity"] != -1:
                pr[ti]["sim"] += st["similarity"]
    precision = [0.0] * N_SAMPLE_PTS
    aos = [0.0] * N_SAMPLE_PTS
    for i, p in enumerate(pr):
        precision[i] = p["tp"] / (p["tp"] + p["fp"])
        if compute_aos:
            aos[i] = p["sim"] / (p["tp"] + p["fp"])
    for i in range(len(thresholds)):
        precision[i] = max(precision[i:])
        if compute_aos:
            aos[i] = max(aos[i:])
    return np.array(precision), (np.array(aos) if compute_aos else None)


def ap(curve, points):
    if points == 11:
        return sum(curve[i] for i in range(0, 41, 4)) / 11 * 100
    return sum(curve[i] for i in range(1, 41)) / 40 * 100
