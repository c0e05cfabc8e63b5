"""The KITTI 3D object detection benchmark (2D, BEV, 3D AP and AOS), exactly as the official devkit.

Follows ``evaluate_object.cpp`` of the KITTI object devkit (``cleanData``,
``computeStatistics``, ``getThresholds``, ``eval_class``) and its python port
(traveller59/kitti-object-eval-python, used by second.pytorch and visualDet3D):

* classes Car, Pedestrian, Cyclist; neighbour classes (Van for Car,
  Person_sitting for Pedestrian) are "ignored" ground truth: matching them is
  neither a TP nor a FP. Names compare case-insensitively.
* difficulties easy / moderate / hard: ground truth counts if its 2D box is
  taller than 40 / 25 / 25 px (``height <= min`` is ignored), its occlusion is
  at most 0 / 1 / 2 and its truncation at most 0.15 / 0.30 / 0.50; otherwise it
  is ignored. Detections lower than the minimum height (``|y2 - y1| < min``,
  whatever their class) are ignored detections.
* score thresholds: the scores of the true positives that best sample the 41
  recall positions 0, 1/40, ..., 1 (``getThresholds``); precision and AOS at
  each threshold, then the running maximum from the right.
* AP|R11 = mean of the precision at recall 0, 0.1, ..., 1 (every 4th of the 41
  samples); AP|R40 = mean over the 40 samples at recall 1/40 ... 1 (recall 0
  excluded). Both in percent.
* DontCare regions: a detection that is not matched to any ground truth and
  overlaps a DontCare region by more than the class's minimum overlap
  (intersection over the *detection's* area, criterion 0) is not a false
  positive. The official cpp does this for all three metrics, each with its own
  overlap; the python port does it only for the 2D metric. We follow the cpp.
  With real KITTI labels the two agree: DontCare lines carry the placeholder 3D
  box (location -1000, size -1), whose BEV/3D overlap with any real detection
  is 0.
* AOS (the devkit computes it with the 2D matching only) is ``None`` when any
  detection has the invalid orientation ``alpha = -10`` (the cpp's rule; the
  port only looks at the first detection).

Overlap settings: the official thresholds ("strict": Car 0.7, Pedestrian and
Cyclist 0.5 for bbox/bev/3d) and the port's second setting that papers report
as "AP@0.5" ("loose": bev/3d at Car 0.5, Pedestrian/Cyclist 0.25; the 2D bbox
threshold stays at 0.7/0.5 as in the port's table). Results are keyed by the
class's bev/3d threshold of the setting: Car "0.70" and "0.50", Pedestrian and
Cyclist "0.50" and "0.25". Under the loose key "bbox" and "aos" therefore
repeat the strict 2D numbers, as the port prints them.

Differences from the python port (all follow the cpp): BEV/3D overlaps are
exact in float64 (the port uses a float32 GPU kernel); AOS switch as above;
DontCare for BEV/3D as above (no effect on real labels). Where both would
divide 0 by 0 (no TP and no FP at a threshold, only possible in contrived
cases) the precision is taken as 0. A class without detections scores 0 (the
cpp would skip it). Everything is vectorised over frames (see
:meth:`DetectionEvalSet.precision_curves`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gac_jax.data.kitti import KittiObjects
from gac_jax.evaluation import rotated_iou

CLASSES = ("Car", "Pedestrian", "Cyclist")
DIFFICULTIES = ("easy", "moderate", "hard")
METRICS = ("bbox", "bev", "3d")
MIN_HEIGHT = (40.0, 25.0, 25.0)
MAX_OCCLUSION = (0, 1, 2)
MAX_TRUNCATION = (0.15, 0.3, 0.5)
N_SAMPLE_POINTS = 41
NEIGHBOUR_CLASS = {"car": "van", "pedestrian": "person_sitting"}
# Minimum overlaps (bbox, bev, 3d) per class: (strict = official, loose = the port's 2nd row).
MIN_OVERLAPS = {
    "Car": ((0.7, 0.7, 0.7), (0.7, 0.5, 0.5)),
    "Pedestrian": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
    "Cyclist": ((0.5, 0.5, 0.5), (0.5, 0.25, 0.25)),
}
NO_DETECTION = -10000000.0  # the devkit's initial "best score" in the threshold pass
_GT_TYPES = ("car", "van", "pedestrian", "person_sitting", "cyclist")


def iou_key(min_overlap: float) -> str:
    """Result key of an overlap setting: the bev/3d threshold with two decimals, e.g. ``"0.70"``."""
    return f"{min_overlap:.2f}"


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_points: int = N_SAMPLE_POINTS):
    """The devkit's ``getThresholds``: TP scores (descending) closest to each recall sample.

    Args:
      scores: (M,) scores of all true positives of the threshold pass.
      num_gt: number of non-ignored ground truth objects (recall denominator).

    Returns:
      (T,) float64 thresholds, T <= ``num_sample_points``, in decreasing order.
    """
    v = np.sort(np.asarray(scores, dtype=np.float64))[::-1]
    n = v.size
    if n == 0:
        return np.zeros((0,), dtype=np.float64)
    i = np.arange(n, dtype=np.float64)
    l_recall = (i + 1.0) / float(num_gt)
    r_recall = np.where(np.arange(n) < n - 1, (i + 2.0) / float(num_gt), l_recall)
    last = np.arange(n) == n - 1
    out = []
    current = 0.0
    start = 0
    step = 1.0 / (num_sample_points - 1.0)
    while start < n and len(out) < num_sample_points:
        # Skip while the right-hand recall is closer to the current sample than the left one.
        keep = ~((r_recall[start:] - current) < (current - l_recall[start:])) | last[start:]
        k = start + int(np.argmax(keep))
        out.append(v[k])
        current += step
        start = k + 1
    return np.asarray(out, dtype=np.float64)


def average_precision(curve: np.ndarray, points: int) -> float:
    """AP in percent of a 41-sample (enveloped) curve: ``points`` = 11 (R11) or 40 (R40)."""
    curve = np.asarray(curve, dtype=np.float64)
    if points == 11:
        return float(curve[0::4].sum() / 11.0 * 100.0)
    if points == 40:
        return float(curve[1:].sum() / 40.0 * 100.0)
    raise ValueError(f"points must be 11 or 40, got {points}")


def same_frame_pairs(frame_a: np.ndarray, frame_b: np.ndarray, n_frames: int):
    """Pairs (i, j) with ``frame_a[i] == frame_b[j]`` (both sorted), ordered by frame, i, j."""
    ca = np.bincount(frame_a, minlength=n_frames)
    cb = np.bincount(frame_b, minlength=n_frames)
    oa = np.concatenate([[0], np.cumsum(ca)[:-1]])
    ob = np.concatenate([[0], np.cumsum(cb)[:-1]])
    npair = ca * cb
    pf = np.repeat(np.arange(n_frames), npair)
    k = np.arange(int(npair.sum())) - np.repeat(np.cumsum(npair) - npair, npair)
    nb = cb[pf]
    return oa[pf] + k // nb, ob[pf] + k % nb


def _ceil_pow2(n: np.ndarray) -> np.ndarray:
    return (1 << np.ceil(np.log2(np.maximum(n, 1))).astype(np.int64)).astype(np.int64)


class _Group:
    """Frames with the same padded sizes: candidate GT x candidate detections of one evaluation."""

    def __init__(self, n_frames, gp, dp):
        self.cand = np.zeros((n_frames, gp, dp), dtype=bool)
        self.overlap = np.zeros((n_frames, gp, dp), dtype=np.float64)
        self.ign_g = np.full((n_frames, gp), -1, dtype=np.int64)
        self.alpha_g = np.zeros((n_frames, gp), dtype=np.float64)
        self.ign_d = np.full((n_frames, dp), -1, dtype=np.int64)
        self.score = np.full((n_frames, dp), -np.inf, dtype=np.float64)
        self.alpha_d = np.zeros((n_frames, dp), dtype=np.float64)
        self.dc = np.zeros((n_frames, dp), dtype=bool)
        self.real_d = np.zeros((n_frames, dp), dtype=bool)


class DetectionEvalSet:
    """Ground truth and detections of a whole evaluation set, flattened for vectorised scoring.

    Args:
      gt: per frame, the ground-truth objects (DontCare included).
      dt: per frame, the detections (``score`` set).
    """

    def __init__(self, gt: Sequence[KittiObjects], dt: Sequence[KittiObjects]):
        if len(gt) != len(dt):
            raise ValueError(f"{len(gt)} ground-truth frames but {len(dt)} detection frames")
        self.num_frames = len(gt)
        g = KittiObjects.concatenate(list(gt))
        d = KittiObjects.concatenate(list(dt))
        self.gt_frame = np.repeat(np.arange(self.num_frames), [len(o) for o in gt])
        self.dt_frame = np.repeat(np.arange(self.num_frames), [len(o) for o in dt])
        self.gt_type = np.char.lower(g.type.astype(str))
        self.dt_type = np.char.lower(d.type.astype(str))
        self.gt_height = g.bbox[:, 3] - g.bbox[:, 1]
        self.gt_occluded = g.occluded
        self.gt_truncated = g.truncated
        self.gt_alpha = g.alpha
        self.dt_height = np.abs(d.bbox[:, 3] - d.bbox[:, 1])
        self.dt_alpha = d.alpha
        self.dt_score = d.score.astype(np.float64)
        if np.any(np.isnan(self.dt_score)):
            raise ValueError("every detection needs a score (found NaN)")
        self._g, self._d = g, d
        # The cpp computes AOS unless some detection has the invalid orientation -10.
        self.compute_aos = not bool(np.any(d.alpha == -10.0))
        self._pairs: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._dontcare: dict[str, np.ndarray] = {}
        self._curves: dict[tuple, tuple[np.ndarray, np.ndarray | None]] = {}

    # ---------------------------------------------------------------- overlaps (cached)

    def _overlaps(self, metric: str, ig: np.ndarray, jd: np.ndarray, criterion: int) -> np.ndarray:
        g, d = self._g, self._d
        if metric == "bbox":
            return rotated_iou.box2d_overlap_pairs(d.bbox[jd], g.bbox[ig], criterion)
        a = rotated_iou.boxes3d(d.location[jd], d.dimensions[jd], d.rotation_y[jd])
        b = rotated_iou.boxes3d(g.location[ig], g.dimensions[ig], g.rotation_y[ig])
        inter = rotated_iou.bev_intersection_area_pairs(
            a[:, [0, 2, 5, 4, 6]], b[:, [0, 2, 5, 4, 6]]
        )
        if metric == "bev":
            area_a = np.abs(a[:, 5] * a[:, 4])
            area_b = np.abs(b[:, 5] * b[:, 4])
            denom = {-1: area_a + area_b - inter, 0: area_a, 1: area_b}[criterion]
            out = np.zeros_like(inter)
            np.divide(inter, denom, out=out, where=denom > 0)
            return out
        if metric == "3d":
            return rotated_iou.box3d_overlap_from_bev(a, b, inter, criterion)
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")

    def match_pairs(self, metric: str):
        """Same-frame (gt, detection) pairs with positive overlap: (gt_idx, dt_idx, overlap)."""
        if metric not in self._pairs:
            sub = np.flatnonzero(np.isin(self.gt_type, _GT_TYPES))
            i, j = same_frame_pairs(self.gt_frame[sub], self.dt_frame, self.num_frames)
            ig = sub[i]
            ov = self._overlaps(metric, ig, j, -1)
            keep = ov > 0
            self._pairs[metric] = (ig[keep], j[keep], ov[keep])
        return self._pairs[metric]

    def dontcare_overlap(self, metric: str) -> np.ndarray:
        """(num_detections,) largest overlap with a DontCare region, by detection area."""
        if metric not in self._dontcare:
            sub = np.flatnonzero(self.gt_type == "dontcare")
            i, j = same_frame_pairs(self.gt_frame[sub], self.dt_frame, self.num_frames)
            best = np.zeros(len(self.dt_frame), dtype=np.float64)
            if j.size:
                np.maximum.at(best, j, self._overlaps(metric, sub[i], j, 0))
            self._dontcare[metric] = best
        return self._dontcare[metric]

    # ---------------------------------------------------------------- cleanData

    def ignore_flags(self, class_name: str, difficulty: int):
        """The devkit's ``cleanData``: (ignored_gt (G,), ignored_det (D,), num_valid_gt).

        ``0`` = evaluated, ``1`` = ignored (may be matched, never counted),
        ``-1`` = other class (never matched).
        """
        name = class_name.lower()
        neighbour = NEIGHBOUR_CLASS.get(name)
        valid = np.where(self.gt_type == name, 1, -1)
        if neighbour is not None:
            valid = np.where(self.gt_type == neighbour, 0, valid)
        ignore = (
            (self.gt_occluded > MAX_OCCLUSION[difficulty])
            | (self.gt_truncated > MAX_TRUNCATION[difficulty])
            | (self.gt_height <= MIN_HEIGHT[difficulty])
        )
        ign_g = np.where(
            (valid == 1) & ~ignore, 0, np.where((valid == 0) | ((valid == 1) & ignore), 1, -1)
        )
        # The cpp truncates the detection height to an int; with integer minimum heights
        # ``int(h) < min`` is the same as ``h < min``.
        ign_d = np.where(
            self.dt_height < MIN_HEIGHT[difficulty], 1, np.where(self.dt_type == name, 0, -1)
        )
        return ign_g, ign_d, int(np.sum(ign_g == 0))

    # ---------------------------------------------------------------- computeStatistics

    def _groups(self, cg, cd, co, ign_g, ign_d, dc_supp) -> list[_Group]:
        ug, g_inv = np.unique(cg, return_inverse=True)
        ud, d_inv = np.unique(cd, return_inverse=True)
        frames, g_first, n_g = np.unique(self.gt_frame[ug], return_index=True, return_counts=True)
        _, d_first, n_d = np.unique(self.dt_frame[ud], return_index=True, return_counts=True)
        g_local = np.arange(len(ug)) - np.repeat(g_first, n_g)
        d_local = np.arange(len(ud)) - np.repeat(d_first, n_d)
        g_fidx = np.repeat(np.arange(len(frames)), n_g)
        d_fidx = np.repeat(np.arange(len(frames)), n_d)
        # Bucket frames by padded (candidate GT, candidate detection) counts to limit padding.
        sizes = np.stack([_ceil_pow2(n_g), _ceil_pow2(n_d)], axis=1)
        groups = []
        for gp, dp in np.unique(sizes, axis=0):
            in_b = (sizes[:, 0] == gp) & (sizes[:, 1] == dp)
            fb = np.flatnonzero(in_b)
            row = np.full(len(frames), -1)
            row[fb] = np.arange(len(fb))
            grp = _Group(len(fb), int(gp), int(dp))
            grp.frame = frames[fb]  # the frame of each row
            gm = in_b[g_fidx]
            gr, gc, gi = row[g_fidx[gm]], g_local[gm], ug[gm]
            grp.ign_g[gr, gc] = ign_g[gi]
            grp.alpha_g[gr, gc] = self.gt_alpha[gi]
            dm = in_b[d_fidx]
            dr, dcol, di = row[d_fidx[dm]], d_local[dm], ud[dm]
            grp.ign_d[dr, dcol] = ign_d[di]
            grp.score[dr, dcol] = self.dt_score[di]
            grp.alpha_d[dr, dcol] = self.dt_alpha[di]
            grp.dc[dr, dcol] = dc_supp[di]
            grp.real_d[dr, dcol] = True
            pm = in_b[g_fidx[g_inv]]
            pr = row[g_fidx[g_inv[pm]]]
            grp.cand[pr, g_local[g_inv[pm]], d_local[d_inv[pm]]] = True
            grp.overlap[pr, g_local[g_inv[pm]], d_local[d_inv[pm]]] = co[pm]
            groups.append(grp)
        return groups

    @staticmethod
    def threshold_pass(grp: _Group) -> tuple[np.ndarray, np.ndarray]:
        """``computeStatistics(compute_fp=False)``: each GT takes its highest-scoring
        candidate. Returns the true positives' scores and their rows (frames of the group)."""
        n, gp, dp = grp.cand.shape
        rows = np.arange(n)
        assigned = np.zeros((n, dp), dtype=bool)
        out, tp_rows = [], []
        for gi in range(gp):
            cand = grp.cand[:, gi] & ~assigned & (grp.score > NO_DETECTION)
            j = np.argmax(np.where(cand, grp.score, -np.inf), axis=1)  # first of equal scores
            has = cand.any(axis=1)
            tp = has & (grp.ign_g[:, gi] == 0) & (grp.ign_d[rows, j] == 0)
            out.append(grp.score[rows[tp], j[tp]])
            tp_rows.append(rows[tp])
            assigned[rows[has], j[has]] = True
        return np.concatenate(out), np.concatenate(tp_rows)

    @staticmethod
    def level_statistics(grp: _Group, with_aos: bool):
        """``computeStatistics(compute_fp=True)`` per frame of the group when exactly its ``k``
        highest-scoring detections pass (stable order): (tp, fp, similarity) (n, dp + 1)."""
        n, gp, dp = grp.cand.shape
        # Level k = the k highest-scoring detections of the frame pass the threshold.
        order = np.argsort(-grp.score, axis=1, kind="stable")
        rank = np.empty((n, dp), dtype=np.int64)
        np.put_along_axis(rank, order, np.broadcast_to(np.arange(dp), (n, dp)), axis=1)
        rank[~grp.real_d] = dp
        levels = np.arange(dp + 1)
        eligible = rank[:, None, :] < levels[None, :, None]  # (n, K, dp)
        assigned = np.zeros_like(eligible)
        tp = np.zeros((n, dp + 1), dtype=np.int64)
        sim = np.zeros((n, dp + 1), dtype=np.float64)
        valid_d = (grp.ign_d == 0)[:, None, :]
        ignored_d = (grp.ign_d == 1)[:, None, :]
        slots = np.arange(dp)
        rows = np.arange(n)[:, None]
        for gi in range(gp):
            cand = grp.cand[:, gi, None, :] & eligible & ~assigned
            vc = cand & valid_d
            # Largest overlap among non-ignored candidates (first on ties), else the first
            # ignored (too small) candidate.
            jv = np.argmax(np.where(vc, grp.overlap[:, gi, None, :], -1.0), axis=2)
            has_v = vc.any(axis=2)
            ic = cand & ignored_d
            ji = np.argmax(ic, axis=2)
            has = has_v | ic.any(axis=2)
            j = np.where(has_v, jv, ji)
            hit = has_v & (grp.ign_g[:, gi] == 0)[:, None]
            tp += hit
            if with_aos:
                delta = grp.alpha_g[:, gi, None] - grp.alpha_d[rows, j]
                sim += np.where(hit, (1.0 + np.cos(delta)) / 2.0, 0.0)
            assigned |= has[..., None] & (slots == j[..., None])
        fp = np.sum(eligible & valid_d & ~assigned & ~grp.dc[:, None, :], axis=2)
        return tp, fp, sim

    @staticmethod
    def _statistics_pass(grp: _Group, thresholds: np.ndarray, with_aos: bool):
        """``computeStatistics(compute_fp=True)`` at each threshold: (tp, fp, similarity) (T,)."""
        tp, fp, sim = DetectionEvalSet.level_statistics(grp, with_aos)
        # Per frame and threshold, the level = number of its detections scoring >= threshold.
        level = np.sum(grp.score[:, :, None] >= thresholds[None, None, :], axis=1)  # (n, T)
        return tuple(np.take_along_axis(a, level, axis=1).sum(axis=0) for a in (tp, fp, sim))

    def curve_parts(self, class_name: str, difficulty: int, metric: str, min_overlap: float):
        """``(num_valid_gt, lone (D,) bool, groups)``: the detections with no candidate ground
        truth that are false positives (not ignored, not in a DontCare area) and the frame
        groups of the statistics passes of one precision curve."""
        ign_g, ign_d, n_valid = self.ignore_flags(class_name, difficulty)
        pg, pd, ov = self.match_pairs(metric)
        sel = (ov > min_overlap) & (ign_g[pg] != -1) & (ign_d[pd] != -1)
        cg, cd, co = pg[sel], pd[sel], ov[sel]
        dc_supp = self.dontcare_overlap(metric) > min_overlap
        is_cand_d = np.zeros(len(self.dt_score), dtype=bool)
        is_cand_d[cd] = True
        groups = self._groups(cg, cd, co, ign_g, ign_d, dc_supp) if cg.size else []
        return n_valid, (ign_d == 0) & ~is_cand_d & ~dc_supp, groups

    def precision_curves(
        self,
        class_name: str,
        difficulty: int,
        metric: str,
        min_overlap: float,
        with_aos: bool = False,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The devkit's ``eval_class`` for one class, difficulty (0, 1, 2) and metric.

        Returns:
          precision (41,) and, with ``with_aos`` (meaningful for ``metric="bbox"``),
          orientation similarity (41,), both after the running max from the right;
          entries beyond the number of thresholds are 0.
        """
        if metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
        if not 0.0 <= min_overlap < 1.0:
            raise ValueError(f"min_overlap must be in [0, 1), got {min_overlap}")
        cache_key = (class_name.lower(), difficulty, metric, float(min_overlap), with_aos)
        if cache_key in self._curves:
            return self._curves[cache_key]
        n_valid, lone, groups = self.curve_parts(class_name, difficulty, metric, min_overlap)
        lone_fp = np.sort(self.dt_score[lone])
        tp_scores = [self.threshold_pass(grp)[0] for grp in groups]
        thresholds = get_thresholds(
            np.concatenate(tp_scores) if tp_scores else np.zeros(0), max(n_valid, 1)
        )
        t = len(thresholds)
        tp = np.zeros(t)
        fp = (len(lone_fp) - np.searchsorted(lone_fp, thresholds, side="left")).astype(np.float64)
        sim = np.zeros(t)
        for grp in groups:
            a, b, c = self._statistics_pass(grp, thresholds, with_aos)
            tp += a
            fp += b
            sim += c
        precision = np.zeros(N_SAMPLE_POINTS)
        aos = np.zeros(N_SAMPLE_POINTS) if with_aos else None
        denom = tp + fp
        np.divide(tp, denom, out=precision[:t], where=denom > 0)
        precision = np.maximum.accumulate(precision[::-1])[::-1]
        if with_aos:
            np.divide(sim, denom, out=aos[:t], where=denom > 0)
            aos = np.maximum.accumulate(aos[::-1])[::-1]
        self._curves[cache_key] = (precision, aos)
        return precision, aos


def evaluate_detections(
    gt: Sequence[KittiObjects],
    dt: Sequence[KittiObjects],
    classes: Sequence[str] = CLASSES,
    compute_aos: bool | None = None,
) -> dict:
    """KITTI AP of detections against ground truth, both per frame (same order).

    Args:
      gt: ground-truth objects per frame (labels, DontCare included).
      dt: detections per frame (``score`` set; ``alpha`` used for AOS).
      classes: a subset of ``CLASSES``.
      compute_aos: None = the devkit rule (off if any detection has alpha -10).

    Returns:
      ``{"ap11"|"ap40": {class: {iou_key: {"bbox"|"bev"|"3d"|"aos": [easy, moderate, hard]}}}}``
      in percent; ``iou_key`` is the class's bev/3d threshold of the setting
      (Car "0.70"/"0.50", Pedestrian and Cyclist "0.50"/"0.25"); "aos" is None
      when AOS is not computed.
    """
    evalset = DetectionEvalSet(gt, dt)
    with_aos = evalset.compute_aos if compute_aos is None else bool(compute_aos)
    result: dict = {"ap11": {}, "ap40": {}}
    for cls in classes:
        if cls not in MIN_OVERLAPS:
            raise ValueError(f"unsupported class {cls!r}; the benchmark evaluates {CLASSES}")
        for ap_key, points in (("ap11", 11), ("ap40", 40)):
            per_setting = {}
            for setting in MIN_OVERLAPS[cls]:
                entry = {}
                for metric, min_overlap in zip(METRICS, setting, strict=True):
                    aos_here = with_aos and metric == "bbox"
                    values, aos_values = [], []
                    for diff in range(3):
                        prec, aos = evalset.precision_curves(
                            cls, diff, metric, min_overlap, aos_here
                        )
                        values.append(average_precision(prec, points))
                        if aos_here:
                            aos_values.append(average_precision(aos, points))
                    entry[metric] = values
                    if metric == "bbox":
                        entry["aos"] = aos_values if aos_here else None
                per_setting[iou_key(setting[1])] = entry
            result[ap_key][cls] = per_setting
    return result
