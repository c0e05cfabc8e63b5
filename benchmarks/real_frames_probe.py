"""What a detector's false positives on real frames respond to: the same frames, changed.

Runs a trained detector on the real labelled KITTI frames of ``../shared`` as they are and
changed as a whole (blurred, grey, half the contrast, sharpened, darker, brighter, half the
resolution), counting its Car boxes at the deployed score threshold that overlap a labelled
Car or Van at 2D IoU >= 0.5 (true) or none (false). Then, for every other box of the plain
frames, it changes only the region around the box (the box grown by 30 % each side: blurred,
grey, half the contrast, the darkest pixels of its lower part lifted) and reports how much the
score of the box found again there (IoU >= 0.5; 0 if none) changes, separately for false and
true boxes. A cue that lowers false boxes' scores more than true ones' is one the generated
world teaches the detector wrongly.

    python benchmarks/real_frames_probe.py --workdir W [--samples ../shared/data/kitti_samples]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from gac_jax.api.detector import Detector3D  # noqa: E402
from gac_jax.data.kitti import read_label, read_split  # noqa: E402
from gac_jax.data.kitti_calib import read_calib  # noqa: E402
from gac_jax.detection.nms import box_iou_matrix  # noqa: E402


def _grey(p):
    return np.repeat(cv2.cvtColor(p, cv2.COLOR_RGB2GRAY)[..., None], 3, -1)


def _half_contrast(p):
    mean = p.reshape(-1, 3).mean(0)
    return np.clip(mean + 0.5 * (p.astype(np.float32) - mean), 0, 255).astype(np.uint8)


def _sharpen(p):
    soft = cv2.GaussianBlur(p.astype(np.float32), (0, 0), 1.5)
    return np.clip(2.0 * p - soft, 0, 255).astype(np.uint8)


def _lift_dark_base(p):
    """The darkest 30 % of the lower 40 % of the patch, halfway to the patch's median colour."""
    q = p.astype(np.float32)
    low = q[int(0.6 * len(q)) :]
    lum = low.mean(-1)
    dark = lum < np.percentile(lum, 30)
    low[dark] = 0.5 * low[dark] + 0.5 * np.median(q.reshape(-1, 3), 0)
    q[int(0.6 * len(q)) :] = low
    return np.clip(q, 0, 255).astype(np.uint8)


FRAME_CHANGES = {
    "as recorded": lambda p: p,
    "blur sigma 1 px": lambda p: cv2.GaussianBlur(p, (0, 0), 1.0),
    "blur sigma 2 px": lambda p: cv2.GaussianBlur(p, (0, 0), 2.0),
    "grey": _grey,
    "half the contrast": _half_contrast,
    "sharpened": _sharpen,
    "darker (x0.6)": lambda p: (p * 0.6).astype(np.uint8),
    "brighter (gamma 0.6)": lambda p: (255 * (p / 255.0) ** 0.6).astype(np.uint8),
    "half resolution": lambda p: cv2.resize(
        cv2.resize(p, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA), p.shape[1::-1]
    ),
}
BOX_CHANGES = {
    "blur sigma 2 px": lambda p: cv2.GaussianBlur(p, (0, 0), 2.0),
    "grey": _grey,
    "half the contrast": _half_contrast,
    "dark base lifted": _lift_dark_base,
}


def _around(image, box, change):
    H, W = image.shape[:2]
    x0, y0, x1, y1 = box
    gw, gh = 0.3 * (x1 - x0), 0.3 * (y1 - y0)
    u0, u1 = int(max(0, x0 - gw)), int(min(W, x1 + gw))
    v0, v1 = int(max(0, y0 - gh)), int(min(H, y1 + gh))
    out = image.copy()
    out[v0:v1, u0:u1] = change(image[v0:v1, u0:u1].copy())
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--workdir", required=True, type=Path)
    p.add_argument("--samples", type=Path, default=REPO.parent / "shared/data/kitti_samples")
    args = p.parse_args()
    root = args.samples / "object"
    if not (root / "ImageSets" / "labeled.txt").exists():
        sys.exit(
            f"{root}: no labelled real frames (the real KITTI samples are not beside the repo)"
        )
    det = Detector3D.from_workdir(args.workdir)
    threshold = float(det.config.eval.score_threshold)
    print(one_line(describe_machine("jax", "numpy", "cv2")))
    print(f"{args.workdir}: {det.weights}; score threshold {threshold}")

    def cars(image, P2):
        found = [o for o in det.predict(image, P2) if o.name == "Car" and o.score >= threshold]
        boxes = np.array([o.box_2d for o in found], np.float64).reshape(-1, 4)
        return boxes, np.array([o.score for o in found])

    frames = {k: [0, 0] for k in FRAME_CHANGES}
    boxes_changed = {k: ([], []) for k in BOX_CHANGES}
    for fid in read_split(root / "ImageSets" / "labeled.txt"):
        image = cv2.cvtColor(
            cv2.imread(str(root / f"training/image_2/{fid}.png")), cv2.COLOR_BGR2RGB
        )
        P2 = read_calib(root / f"training/calib/{fid}.txt").P2
        labels = read_label(root / f"training/label_2/{fid}.txt")
        gt = labels.bbox[np.isin(labels.type, ["Car", "Van"])]

        def best_iou(boxes, gt=gt):
            if len(boxes) == 0 or len(gt) == 0:
                return np.zeros(len(boxes))
            return box_iou_matrix(boxes, gt).max(1)

        for name, change in FRAME_CHANGES.items():
            iou = best_iou(cars(change(image), P2)[0])
            frames[name][0] += int((iou < 0.5).sum())
            frames[name][1] += int((iou >= 0.5).sum())
        boxes, scores = cars(image, P2)
        for k, (box, score, iou) in enumerate(zip(boxes, scores, best_iou(boxes), strict=True)):
            if k % 2:
                continue
            for name, change in BOX_CHANGES.items():
                again, again_scores = cars(_around(image, box, change), P2)
                overlap = box_iou_matrix(box[None], again)[0] if len(again) else np.zeros(0)
                new = again_scores[overlap >= 0.5].max() if np.any(overlap >= 0.5) else 0.0
                boxes_changed[name][int(iou >= 0.5)].append(new - score)
    print("whole frames changed: false / true Car boxes over all frames")
    for name, (false, true) in frames.items():
        print(f"  {name:22s} false {false:4d}  true {true:4d}")
    print("the region around every other box changed: mean score change of false / true boxes")
    for name, (false, true) in boxes_changed.items():
        f, t = np.array(false), np.array(true)
        fm = f"{f.mean():+.2f}" if len(f) else "-"
        tm = f"{t.mean():+.2f}" if len(t) else "-"
        print(f"  {name:22s} false {fm} ({len(f)} boxes)  true {tm} ({len(t)} boxes)")


if __name__ == "__main__":
    main()
