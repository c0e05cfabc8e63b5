"""3D MOT figures from AB3DMOT's own evaluation script: the fixture of the AB3DMOT rule.

    python benchmarks/ab3dmot_oracle.py --ab3dmot /path/to/AB3DMOT [--make-sets]
        [--out tests/data/tracking/ab3dmot_figures.json]

``--ab3dmot`` is a checkout of https://github.com/xinshuoweng/AB3DMOT (its
``scripts/KITTI/evaluate.py`` and ``AB3DMOT_libs``). That script imports numba (for ``jit``),
matplotlib (for its plots) and xinshuo_io; this script stands in for them (``jit`` does
nothing, no plot is drawn) and changes nothing else. It runs the script's ``evaluate`` at 3D
IoU 0.25 and 0.5 on each set, in a temporary folder laid out as the script expects (the set's
labels as ``scripts/KITTI/label``, its seqmap as ``evaluate_tracking.seqmap.val``, its results
as ``results/KITTI/SET/data_0``), and writes, per set and per class the script scores, its
sAMOTA, AMOTA, AMOTP, the number of score thresholds, and the MOTA and MOTP of its "best
results with a single threshold" to the fixture that tests/test_ab3dmot_rules.py reads.

The sets (``SETS``, each ``SET/label_02/SSSS.txt``, ``SET/results/SSSS.txt`` and
``SET/evaluate_tracking.seqmap.training`` in ``tests/data/tracking/ab3dmot_sets.tar.xz``,
:func:`extract_sets`; written by ``--make-sets``):

* ``clips_a``, ``clips_b``: generated driving clips (:mod:`gac_jax.data.synthetic`, 3
  sequences of 40 frames, seeds 31 and 32: Cars, Pedestrians, Cyclists, DontCare regions,
  occlusion and truncation levels), tracked by the 3D tracker (:class:`gac_jax.tracking.Tracker`,
  world frame with the clips' poses) from simulated detections of the labelled objects:
  missed more often the more occluded, depth error growing with distance, noisy 2D boxes,
  sizes and headings, scores, false positives. ``clips_b``'s detector is noisier and its
  tracker starts and ends tracks sooner.
* ``mixed``: the set of ``benchmarks/bench_track_eval.py`` (2 sequences of 40 frames, seed 5):
  Vans, sitting persons (``Person``), DontCare regions and occluded ground truth, results of
  the Vans typed Car: the rules of the distractor classes.
* ``clean_3d``: ``tests/tracking_cases.clean_3d_lines`` (written to a temporary folder).
* ``score_drift``: :func:`score_drift_set`, the script's floating-point drift of track scores.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "tests"), str(REPO)]

import tracking_cases  # noqa: E402

SETS_ARCHIVE = REPO / "tests/data/tracking/ab3dmot_sets.tar.xz"
SETS = ("clips_a", "clips_b", "mixed")
SEQMAP = "evaluate_tracking.seqmap.training"
IOUS = (0.25, 0.5)


@dataclasses.dataclass(frozen=True)
class Noise:
    """The simulated detector's errors and the tracker's birth / death."""

    depth_per_m: float  # depth error (std) per metre of distance
    box_px: float  # 2D box corner error (std, pixels)
    false_positives: float  # per frame (Poisson mean)
    min_hits: int
    max_misses: int


CLIP_SETS = {
    "clips_a": (31, Noise(0.03, 2.0, 0.4, min_hits=3, max_misses=4)),
    "clips_b": (32, Noise(0.06, 4.0, 0.8, min_hits=1, max_misses=2)),
}
CLASSES = {"Car": (3, 8), "Pedestrian": (2, 6), "Cyclist": (1, 3)}  # road users per 66 m
DETECTED = np.array([0.95, 0.8, 0.55, 0.3])  # probability of a detection per occlusion level


def _detections(rng, labels, P2, image_size, noise: Noise):
    """Simulated detections of one frame's labelled objects (KittiObjects with scores)."""
    from gac_jax.data.kitti import KittiObjects
    from gac_jax.geometry import box2d_from_corners, box3d_corners

    obj = labels.objects.select(labels.objects.type != "DontCare")
    occ = np.clip(obj.occluded, 0, 3)
    hit = rng.random(len(obj)) < DETECTED[occ] * np.where(obj.truncated > 0, 0.8, 1.0)
    obj, occ = obj.select(hit), occ[hit]
    n = len(obj)
    z = obj.location[:, 2]
    small = np.where(obj.type == "Car", 1.0, 0.3)  # people's boxes: smaller errors, or IoU 0
    error = np.stack(
        [
            rng.normal(0, (0.05 + 0.004 * z) * small),
            rng.normal(0, 0.03, n),
            rng.normal(0, (0.1 + noise.depth_per_m * z) * small),
        ],
        axis=1,
    )
    flip = np.where(rng.random(n) < 0.05, np.pi, 0.0)
    types_ = obj.type.copy()
    swap = rng.random(n) < 0.03
    types_[swap] = np.where(types_[swap] == "Pedestrian", "Cyclist", types_[swap])
    k = rng.poisson(noise.false_positives)
    fp_loc = np.stack([rng.uniform(-12, 12, k), rng.normal(1.65, 0.05, k), rng.uniform(8, 60, k)])
    fp_dims = np.tile([1.5, 1.6, 3.9], (k, 1)) * rng.normal(1, 0.05, (k, 3))
    fp_ry = rng.uniform(-np.pi, np.pi, k)
    fp_box = box2d_from_corners(box3d_corners(fp_loc.T, fp_dims, fp_ry), P2, image_size)
    ok = np.isfinite(fp_box).all(axis=1) & (fp_box[:, 2] > fp_box[:, 0] + 2)
    return KittiObjects.predictions(
        type=np.concatenate([types_, np.full(int(ok.sum()), "Car")]),
        alpha=np.concatenate([obj.alpha, fp_ry[ok]]),
        bbox=np.concatenate([obj.bbox + rng.normal(0, noise.box_px, (n, 4)), fp_box[ok]]),
        dimensions=np.concatenate([obj.dimensions * rng.normal(1, 0.05, (n, 3)), fp_dims[ok]]),
        location=np.concatenate([obj.location + error, fp_loc.T[ok]]),
        rotation_y=np.concatenate([obj.rotation_y + rng.normal(0, 0.08, n) + flip, fp_ry[ok]]),
        score=np.concatenate(
            [
                np.clip(0.9 - 0.15 * occ + rng.normal(0, 0.1, n), 0.05, 0.99),
                rng.uniform(0.05, 0.45, int(ok.sum())),
            ]
        ),
    )


def make_clip_set(name: str, out: Path, work: Path) -> None:
    """Generates the clips of ``name``, tracks them, writes the set to ``out``."""
    from gac_jax.data.kitti_tracking import KittiTrackingLayout
    from gac_jax.data.synthetic.calibration import KITTI_SIZE
    from gac_jax.data.synthetic.clips import generate_clips
    from gac_jax.tracking import Tracker, TrackerParams

    seed, noise = CLIP_SETS[name]
    clips = work / name
    generate_clips(clips, 3, 40, seed=seed, classes=CLASSES)
    layout = KittiTrackingLayout(clips)
    rng = np.random.default_rng(seed)
    seqmap = ""
    for d in ("label_02", "results"):
        (out / d).mkdir(parents=True)
    for seq in layout.sequences():
        params = TrackerParams(min_hits=noise.min_hits, max_misses=noise.max_misses)
        tracker, lines, n = Tracker(params), [], 0
        for frame in layout.frames(seq):
            det = _detections(rng, frame.labels, frame.P2, KITTI_SIZE, noise)
            tracks = tracker.update(det, pose=frame.pose, timestamp=frame.frame / 10.0)
            lines += tracks.to_kitti_tracking_lines(frame.frame)
            n += 1
        shutil.copy(layout.label(seq), out / "label_02" / f"{seq}.txt")
        (out / "results" / f"{seq}.txt").write_text("".join(line + "\n" for line in lines))
        seqmap += f"{seq} empty 000000 {n:06d}\n"
    (out / SEQMAP).write_text(seqmap)


def make_sets(work: Path) -> None:
    """Writes the sets to :data:`SETS_ARCHIVE` (sorted members, no times: reproducible)."""
    from bench_track_eval import generate  # benchmarks/ is on sys.path

    from gac_jax.data.files import atomic_write

    root = work / "sets"
    for name in SETS:
        if name in CLIP_SETS:
            make_clip_set(name, root / name, work)
        else:
            generate(root / name, 2, 40, seed=5)
    files = sorted(p for p in root.rglob("*") if p.is_file())
    with atomic_write(SETS_ARCHIVE, "wb") as f, tarfile.open(fileobj=f, mode="w:xz") as tar:
        for path in files:
            info = tarfile.TarInfo(path.relative_to(root).as_posix())
            info.size, info.mode = path.stat().st_size, 0o644
            with path.open("rb") as data:
                tar.addfile(info, data)
    print(f"wrote {SETS_ARCHIVE} ({len(files)} files)", flush=True)


def extract_sets(out: Path, archive: Path = SETS_ARCHIVE) -> dict[str, Path]:
    """Extracts the sets to ``out``; returns ``{set: its folder}``."""
    with tarfile.open(archive, "r:xz") as tar:
        tar.extractall(out, filter="data")
    return {name: out / name for name in SETS}


def clean_3d_set(root: Path) -> Path:
    labels, results = tracking_cases.clean_3d_lines()
    for name, lines in (("label_02", labels), ("results", results)):
        (root / name).mkdir(parents=True)
        for seq, text in lines.items():
            (root / name / f"{seq}.txt").write_text("".join(text))
    n = 1 + max(int(line.split()[0]) for line in labels["0000"] + results["0000"])
    (root / SEQMAP).write_text(f"0000 empty 000000 {n:06d}\n")
    return root


def score_drift_set(root: Path) -> Path:
    """One car over 7 frames, tracked by one track of score 0.17 on every line (its box 0.1 m
    off: the script's polygon clipping overstates the IoU of coinciding boxes): the track's
    mean is 0.16999999999999998, the mean of 7 such means 0.16999999999999996, so the script
    drops the track at its own score, every threshold (its sAMOTA is 0)."""

    def line(f, dx):
        return (
            f"{f} 0 Car 0 0 0 560.00 120.00 680.00 220.00 1.50 1.60 3.90 {dx:.4f} 1.6000 "
            f"{15 + f + dx / 2:.4f} 0.0"
        )

    labels = [line(f, 0.0) + "\n" for f in range(7)]
    results = [line(f, 0.1) + " 0.17\n" for f in range(7)]
    for name, text in (("label_02", labels), ("results", results)):
        (root / name).mkdir(parents=True)
        (root / name / "0000.txt").write_text("".join(text))
    (root / SEQMAP).write_text("0000 empty 000000 000007\n")
    return root


def _stand_ins() -> None:
    def jit(*args, **kwargs):
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda f: f

    sys.modules.setdefault("numba", types.SimpleNamespace(jit=jit, njit=jit))
    mpl = types.ModuleType("matplotlib")
    mpl.use = lambda *a, **k: None
    mpl.pyplot = types.ModuleType("matplotlib.pyplot")
    sys.modules.setdefault("matplotlib", mpl)
    sys.modules.setdefault("matplotlib.pyplot", mpl.pyplot)
    sys.modules.setdefault("xinshuo_io", types.SimpleNamespace(fileparts=None))


def load_script(checkout: Path):
    """AB3DMOT's ``evaluate`` module, with hooks that keep the figures it computes."""
    _stand_ins()
    sys.path[:0] = [str(checkout / "scripts" / "KITTI"), str(checkout)]
    import evaluate as script  # the script itself

    script.mail = script.mailpy.Mail("")  # a global its __main__ block sets
    script.figures = {}
    output, save = script.stat.output, script.trackingEvaluation.saveToStats

    def stat_output(self):
        output(self)
        fig = script.figures.setdefault(self.cls, {})
        fig.update(sAMOTA=self.sAMOTA, AMOTA=self.amota, AMOTP=self.amotp)
        fig["thresholds"] = len(self.mota_list)

    def save_to_stats(self, dump, threshold=None, recall=None):
        save(self, dump, threshold, recall)
        if threshold is None:  # the pass at the best single threshold
            fig = script.figures.setdefault(self.cls, {})
            fig.update(MOTA=self.MOTA, MOTP=float(self.MOTP))

    script.stat.output = stat_output
    script.stat.plot = lambda self: None
    script.trackingEvaluation.saveToStats = save_to_stats
    return script


def run_set(script, root: Path, work: Path) -> dict:
    """The script's figures of the set ``root``: ``{iou: {class: figures}}``."""
    kitti = work / "scripts" / "KITTI"
    shutil.copytree(root / "label_02", kitti / "label")
    shutil.copy(root / SEQMAP, kitti / "evaluate_tracking.seqmap.val")
    shutil.copytree(root / "results", work / "results" / "KITTI" / "set" / "data_0")
    out, cwd = {}, os.getcwd()
    os.chdir(work)
    try:
        for thres in IOUS:
            script.figures = {}
            with contextlib.redirect_stdout(io.StringIO()):
                ok = script.evaluate("set", script.mail, 1, True, False, thres)
            if not ok:
                raise SystemExit(f"AB3DMOT's evaluation failed on {root} at IoU {thres}")
            out[f"{thres:.2f}"] = {
                c: {k: float(v) for k, v in f.items()} for c, f in script.figures.items()
            }
    finally:
        os.chdir(cwd)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ab3dmot", required=True, help="path of an AB3DMOT checkout")
    parser.add_argument("--make-sets", action="store_true", help="(re)write the sets first")
    parser.add_argument("--out", default=str(REPO / "tests/data/tracking/ab3dmot_figures.json"))
    args = parser.parse_args(argv)
    checkout = Path(args.ab3dmot).resolve()
    rev = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    figures = {"_oracle": f"xinshuoweng/AB3DMOT@{rev or 'unknown'} scripts/KITTI/evaluate.py"}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.make_sets:
            make_sets(tmp / "clips")
        script = load_script(checkout)
        roots = extract_sets(tmp / "sets_read")
        roots["clean_3d"] = clean_3d_set(tmp / "clean_3d")
        roots["score_drift"] = score_drift_set(tmp / "score_drift")
        for name, root in roots.items():
            figures[name] = run_set(script, root, tmp / "run" / name)
            print(f"{name}: {json.dumps(figures[name])}", flush=True)
    from gac_jax.data.files import atomic_write

    with atomic_write(args.out) as f:
        f.write(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
