"""Does bfloat16 compute keep a trained detector's AP? float32 vs bfloat16 on one workdir.

Evaluates the latest checkpoint of a trained detection workdir on its val split twice,
with ``Detector(dtype=float32)`` and ``Detector(dtype=bfloat16)`` (float32 parameters,
as ``benchmarks/bench_evaluate.py`` times them), and prints every AP of both, their
difference and the model time per frame. The issue's rule: use bfloat16 only where it is
both faster and within 0.5 AP.

    python benchmarks/bench_bf16_accuracy.py --workdir workdirs/detect3d_detect3d_default
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

# Measure what train.py / evaluate.py run with (GAC_JAX_DEFAULT_XLA_FLAGS=0: JAX's own).
apply_default_xla_flags()

import jax.numpy as jnp  # noqa: E402
from machine_info import describe_machine, one_line  # noqa: E402  (benchmarks/ on sys.path)

from gac_jax.cli.evaluate_detector import evaluate_detector_workdir  # noqa: E402
from gac_jax.evaluation.kitti_object import DIFFICULTIES  # noqa: E402


def flat_ap(metrics: dict) -> dict[str, float]:
    """``{'ap40/Car/0.70/3d/moderate': value, ...}`` for every entry of a result dict."""
    out = {}
    for ap, classes in metrics.items():
        if not ap.startswith("ap"):
            continue
        for cls, ious in classes.items():
            for iou, kinds in ious.items():
                for kind, values in kinds.items():
                    for name, v in zip(DIFFICULTIES, values, strict=True):
                        out[f"{ap}/{cls}/{iou}/{kind}/{name}"] = float(v)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workdir", required=True, help="a trained detect3d workdir")
    parser.add_argument("--split", help="default: the run's val split")
    parser.add_argument("--threads", type=int)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    print(one_line(describe_machine("numpy", "jax")), flush=True)
    runs = {}
    with tempfile.TemporaryDirectory(prefix="bench_bf16_") as tmp:
        for name in ("float32", "bfloat16"):
            print(f"\n=== {name} ===", flush=True)
            summary = evaluate_detector_workdir(
                args.workdir,
                split=args.split,
                threads=args.threads,
                dtype=getattr(jnp, name),
                out_dir=Path(tmp) / name,
            )
            runs[name] = {"ap": flat_ap(summary["metrics"]), "speed": summary["speed"]}
    f32, b16 = runs["float32"]["ap"], runs["bfloat16"]["ap"]
    diffs = {k: b16[k] - f32[k] for k in f32}
    print(f"\n{'metric':40s} {'float32':>8s} {'bfloat16':>9s} {'diff':>7s}")
    for k in f32:
        if "/Car/" in k and k.startswith("ap40"):
            print(f"{k:40s} {f32[k]:8.2f} {b16[k]:9.2f} {diffs[k]:+7.2f}")
    worst = max(diffs, key=lambda k: abs(diffs[k]))
    print(f"largest |difference| over all {len(diffs)} APs: {diffs[worst]:+.2f} ({worst})")
    for name, run in runs.items():
        s = run["speed"]
        print(
            f"{name}: model {s['model_ms_median']:.1f} ms/frame (median), "
            f"{s['frames_per_s']:.2f} frames/s end to end"
        )
    if args.json:
        args.json.write_text(json.dumps({"runs": runs, "max_abs_diff": abs(diffs[worst])}))


if __name__ == "__main__":
    main()
