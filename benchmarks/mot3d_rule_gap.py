"""What each of AB3DMOT's script's rules costs: its sAMOTA against TrackEval's counting.

    python benchmarks/mot3d_rule_gap.py [--set LABEL_DIR RESULT_DIR ...] [--classes car,pedestrian]

For each set (default: the two generated clip sets of tests/data/tracking/ab3dmot_sets.tar.xz),
class and 3D IoU, sAMOTA by (1) the ``ab3dmot`` rule (the script's), (2) the same with the
tracks' mean scores taken once (the script takes them again in every pass from the previous
means and in floating point a track falls an ulp below its own score, the threshold), (3) also
with the thresholds over the true positives on scored ground truth (the script counts those on
ignored ground truth too), and (4) the ``trackeval`` rule. The steps (2) - (1), (3) - (2) and
(4) - (3) are what the score drift, the recall denominator and the remaining rules
(identity switches, matching, ignored boxes) account for; printed as a markdown table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gac_jax.evaluation.tracking.ab3dmot_rules import ab3dmot_metrics  # noqa: E402
from gac_jax.evaluation.tracking.evaluator import load_tracking_folders  # noqa: E402
from gac_jax.evaluation.tracking.mot3d import MOT3D_IOUS, mot3d_metrics  # noqa: E402

VARIANTS = {
    "script": {},
    "scores once": {"score_drift": False},
    "and scored recall": {"score_drift": False, "scored_recall": True},
}


def gap_rows(name: str, sequences, classes) -> list[str]:
    rows = []
    for cls in classes:
        for iou in MOT3D_IOUS:
            s = [
                100 * ab3dmot_metrics(sequences, cls, iou, **kw)["sAMOTA"]
                for kw in VARIANTS.values()
            ]
            s.append(100 * mot3d_metrics(sequences, cls, iou)["sAMOTA"])
            steps = [b - a for a, b in zip(s, s[1:], strict=False)]
            cells = [f"{v:.2f}" for v in s] + [f"{d:+.2f}" for d in steps]
            rows.append(f"| {name}, {cls.capitalize()}, {iou:.2f} | " + " | ".join(cells) + " |")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--set", nargs=2, action="append", metavar=("LABEL_DIR", "RESULT_DIR"))
    parser.add_argument("--classes", default="car,pedestrian")
    args = parser.parse_args(argv)
    classes = args.classes.split(",")
    head = ["set, class, 3D IoU", "sAMOTA: script", *list(VARIANTS)[1:], "TrackEval's"]
    head += ["score drift", "recall denominator", "the other rules"]
    print("| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    with tempfile.TemporaryDirectory() as tmp:
        if args.set:
            sets = {Path(r).parent.name: (Path(lab), Path(r)) for lab, r in args.set}
        else:
            sys.path.insert(0, str(REPO / "benchmarks"))
            from ab3dmot_oracle import extract_sets

            roots = extract_sets(Path(tmp))
            sets = {
                n: (roots[n] / "label_02", roots[n] / "results") for n in ("clips_a", "clips_b")
            }
        for name, (labels, results) in sets.items():
            for row in gap_rows(name, load_tracking_folders(labels, results), classes):
                print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
