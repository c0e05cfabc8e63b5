"""Official figures of the tracking-evaluation test cases, from the official TrackEval code.

    python benchmarks/trackeval_oracle.py --trackeval /path/to/TrackEval \
        [--out tests/data/tracking/trackeval_figures.json]

``--trackeval`` is a checkout of https://github.com/JonathonLuiten/TrackEval (the official
KITTI tracking evaluation since HOTA). Without it, an installed ``trackeval`` package is used
(PyPI's ``trackeval`` is a port of the same code to numpy 2). The official code still uses
``np.float``/``np.int``/``np.bool``, removed in numpy 2: this script restores them as the
builtins before importing it (the only change; nothing of it is copied or edited).

Each case of ``tests/tracking_cases.py`` is written to a temporary folder in TrackEval's KITTI
layout (with the case's seqmap ``evaluate_tracking.seqmap.training``), evaluated for Car and
Pedestrian with HOTA, CLEAR (threshold 0.5) and Identity, and the combined and per-sequence
figures go to the JSON fixture that tests/test_tracking_eval.py reads.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO / "tests"), str(REPO)]

import tracking_cases  # noqa: E402

# per sequence (the official code leaves MTR/MLR of a sequence without ground truth unset)
from gac_jax.evaluation.tracking.evaluator import SEQUENCE_FIELDS  # noqa: E402

HOTA_FIELDS = ("HOTA", "DetA", "AssA", "DetRe", "DetPr", "AssRe", "AssPr", "LocA")
HOTA_SCALARS = ("HOTA(0)", "LocA(0)")
CLEAR_FIELDS = ("MOTA", "MOTP", "MODA", "sMOTA", "CLR_Re", "CLR_Pr", "MTR", "PTR", "MLR")
CLEAR_COUNTS = ("CLR_TP", "CLR_FN", "CLR_FP", "IDSW", "MT", "PT", "ML", "Frag")
ID_FIELDS = ("IDF1", "IDP", "IDR", "IDTP", "IDFN", "IDFP")


def import_trackeval(checkout: str | None):
    for name, value in (("float", float), ("int", int), ("bool", bool)):
        if not hasattr(np, name):
            setattr(np, name, value)
    if checkout:
        sys.path.insert(0, checkout)
    import trackeval

    return trackeval


def oracle_version(trackeval, checkout: str | None) -> str:
    if checkout:
        rev = subprocess.run(
            ["git", "-C", checkout, "rev-parse", "HEAD"], capture_output=True, text=True
        ).stdout.strip()
        return f"JonathonLuiten/TrackEval@{rev or 'unknown'}"
    return f"trackeval {getattr(trackeval, '__version__', '?')} (PyPI)"


def run_case(trackeval, name: str, work: Path) -> dict:
    gt = work / "gt"
    frames = tracking_cases.write_case(name, gt)  # with its seqmap, as TrackEval reads it
    trackers = work / "trackers"
    (trackers / "t").mkdir(parents=True)
    (gt / "results").rename(trackers / "t" / "data")
    evaluator = trackeval.Evaluator(
        {
            "USE_PARALLEL": False,
            "PRINT_RESULTS": False,
            "PRINT_CONFIG": False,
            "TIME_PROGRESS": False,
            "OUTPUT_SUMMARY": False,
            "OUTPUT_DETAILED": False,
            "PLOT_CURVES": False,
            "LOG_ON_ERROR": None,
        }
    )
    dataset = trackeval.datasets.Kitti2DBox(
        {
            "GT_FOLDER": str(gt),
            "TRACKERS_FOLDER": str(trackers),
            "OUTPUT_FOLDER": str(work / "out"),
            "TRACKERS_TO_EVAL": ["t"],
            "CLASSES_TO_EVAL": ["car", "pedestrian"],
            "SPLIT_TO_EVAL": "training",
            "PRINT_CONFIG": False,
        }
    )
    quiet = {"PRINT_CONFIG": False}
    metrics = [
        trackeval.metrics.HOTA(),
        trackeval.metrics.CLEAR({**quiet, "THRESHOLD": 0.5}),
        trackeval.metrics.Identity({**quiet, "THRESHOLD": 0.5}),
    ]
    res, _ = evaluator.evaluate([dataset], metrics)
    per_seq = res["Kitti2DBox"]["t"]
    out = {}
    for cls in ("car", "pedestrian"):
        out[cls] = figures(per_seq["COMBINED_SEQ"][cls])
        out[cls]["sequences"] = {
            seq: {k: v for k, v in figures(per_seq[seq][cls]).items() if k in SEQUENCE_FIELDS}
            for seq in frames
        }
    return out


def figures(r: dict) -> dict:
    fig = {k: float(np.mean(r["HOTA"][k])) for k in HOTA_FIELDS}
    fig.update({k: float(r["HOTA"][k]) for k in HOTA_SCALARS})
    fig.update({k: float(r["CLEAR"][k]) for k in CLEAR_FIELDS + CLEAR_COUNTS})
    fig.update({k: float(r["Identity"][k]) for k in ID_FIELDS})
    return fig


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trackeval", help="path of a TrackEval checkout")
    parser.add_argument("--out", default=str(REPO / "tests/data/tracking/trackeval_figures.json"))
    args = parser.parse_args(argv)
    trackeval = import_trackeval(args.trackeval)
    figures = {"_oracle": oracle_version(trackeval, args.trackeval)}
    for name in tracking_cases.CASES:
        with tempfile.TemporaryDirectory() as tmp:
            figures[name] = run_case(trackeval, name, Path(tmp))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(figures, indent=1, sort_keys=True) + "\n")
    print(f"wrote {args.out} ({len(tracking_cases.CASES)} cases, {figures['_oracle']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
