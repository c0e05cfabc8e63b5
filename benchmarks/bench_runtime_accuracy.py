"""Accuracy guard of the deployment runtimes: a trained model under every runtime/precision.

Evaluates a trained detection workdir (Car AP|R40, every entry) and/or a trained depth
workdir (SILog, absRel) on the run's val split with ``jax f32`` (the reference), ``jax bf16``,
``onnxruntime f32``, ``openvino f32`` and ``openvino bf16`` (those that can run here), through
the same code as ``evaluate.py --runtime ... --precision ...``, and prints each metric, its
difference to ``jax f32`` and the verdict of the rule in docs/inference.md: a precision is
recommended only if every Car AP|R40 entry stays within 0.5 AP (depth: SILog within 0.2) of
float32.

    python benchmarks/bench_runtime_accuracy.py [--detect3d-workdir W] [--depth-workdir W]
        [--split S] [--threads N] [--json OUT]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

from machine_info import describe_machine, one_line  # noqa: E402  (benchmarks/ on sys.path)

from gac_jax.deploy.runtimes import RuntimeUnavailableError, check_runtime  # noqa: E402
from gac_jax.evaluation.kitti_object import DIFFICULTIES  # noqa: E402

COMBOS = (
    ("jax", "f32"),
    ("jax", "bf16"),
    ("onnxruntime", "f32"),
    ("openvino", "f32"),
    ("openvino", "bf16"),
)
AP_TOLERANCE = 0.5  # AP points, every Car AP|R40 entry
SILOG_TOLERANCE = 0.2


def car_ap40(metrics: dict) -> dict[str, float]:
    out = {}
    for iou, kinds in metrics["ap40"]["Car"].items():
        for kind, values in kinds.items():
            for name, v in zip(DIFFICULTIES, values, strict=True):
                out[f"Car {iou} {kind} {name}"] = float(v)
    return out


def available() -> list[tuple[str, str]]:
    combos = []
    for runtime, precision in COMBOS:
        try:
            check_runtime(runtime, precision)
        except RuntimeUnavailableError as e:
            print(f"skip {runtime} {precision}: {e}")
            continue
        combos.append((runtime, precision))
    return combos


def guard_detector(workdir: str, split, threads, tmp: Path) -> dict:
    from gac_jax.cli.evaluate_detector import evaluate_detector_workdir

    runs = {}
    for runtime, precision in available():
        label = f"{runtime} {precision}"
        print(f"\n=== detector, {label} ===", flush=True)
        with contextlib.redirect_stdout(io.StringIO()):
            summary = evaluate_detector_workdir(
                workdir,
                split=split,
                threads=threads,
                out_dir=tmp / f"det_{runtime}_{precision}",
                runtime=runtime,
                precision=precision,
                export_dir=tmp / "det_export",
            )
        runs[label] = {"ap": car_ap40(summary["metrics"]), "speed": summary["speed"]}
        print(f"  model {summary['speed'].get('model_ms_median', float('nan')):.1f} ms/frame")
    ref = runs["jax f32"]["ap"]
    print(f"\n{'Car AP|R40 entry':28s}" + "".join(f"{k:>18s}" for k in runs))
    for entry in ref:
        cells = "".join(
            f"{r['ap'][entry]:10.2f} ({r['ap'][entry] - ref[entry]:+5.2f})" for r in runs.values()
        )
        print(f"{entry:28s}{cells}")
    verdicts = {}
    for label, r in runs.items():
        worst = max(abs(r["ap"][k] - ref[k]) for k in ref)
        verdicts[label] = {"max_abs_diff": worst, "within_tolerance": worst <= AP_TOLERANCE}
        ok = "within" if worst <= AP_TOLERANCE else "NOT within"
        print(f"{label:18s} largest |diff| {worst:.2f} AP: {ok} {AP_TOLERANCE} AP of jax f32")
    return {"runs": runs, "verdicts": verdicts}


def guard_depth(workdir: str, split, tmp: Path) -> dict:
    from gac_jax.cli.evaluate_depth import evaluate_workdir

    runs = {}
    for runtime, precision in available():
        label = f"{runtime} {precision}"
        print(f"\n=== depth, {label} ===", flush=True)
        with contextlib.redirect_stdout(io.StringIO()):
            result = evaluate_workdir(
                workdir,
                split=split,
                out=tmp / f"depth_{runtime}_{precision}",
                runtime=runtime,
                precision=precision,
                export_dir=tmp / "depth_export",
            )
        m = result["metrics"]
        runs[label] = {"silog": float(m["silog"]), "abs_rel": float(m["abs_rel"])}
    ref = runs["jax f32"]
    verdicts = {}
    print(f"\n{'runtime':18s} {'SILog':>8s} {'diff':>7s} {'absRel %':>9s} {'diff':>7s}")
    for label, r in runs.items():
        d = r["silog"] - ref["silog"]
        print(
            f"{label:18s} {r['silog']:8.3f} {d:+7.3f} {r['abs_rel']:9.3f} "
            f"{r['abs_rel'] - ref['abs_rel']:+7.3f}"
        )
        verdicts[label] = {"silog_diff": d, "within_tolerance": abs(d) <= SILOG_TOLERANCE}
    return {"runs": runs, "verdicts": verdicts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detect3d-workdir", help="a trained detection workdir")
    parser.add_argument("--depth-workdir", help="a trained depth workdir")
    parser.add_argument("--split", help="default: each run's val split")
    parser.add_argument("--threads", type=int)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not args.detect3d_workdir and not args.depth_workdir:
        parser.error("give --detect3d-workdir and/or --depth-workdir")
    print(one_line(describe_machine("numpy", "jax", "onnxruntime", "openvino")), flush=True)
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench_runtime_accuracy_") as tmp:
        if args.detect3d_workdir:
            out["detect3d"] = guard_detector(
                args.detect3d_workdir, args.split, args.threads, Path(tmp)
            )
        if args.depth_workdir:
            out["depth"] = guard_depth(args.depth_workdir, args.split, Path(tmp))
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
