"""Which blocks of a trained network cost the accuracy in int8: one block quantized at a time.

The exported network's convolutions carry their Flax paths (``backbone/layer2_1/conv1``,
``head/cls_out``, ``up1/gac/extract``, ...). They are grouped into blocks (the backbone's stem
and stages, each kind of head conv, each decoder stage), and for every block the network is
quantized (NNCF, as ``--precision int8``) with *every other block* kept in float32
(``--int8-keep-float``), then evaluated with the guard's metric: the largest change of the 24
Car AP|R40 entries against jax float32 (depth: SILog). The fully quantized network is the
last row. Blocks whose own quantization moves the metric beyond the rule are the ones to
keep in float32 (``evaluate.py ... --precision int8 --int8-keep-float PREFIX``); check the
combination with ``bench_runtime_accuracy.py --keep-float PREFIX[,PREFIX]``.

On a run's 300 val frames one entry's change moves by ~0.4-0.8 AP between disjoint 300-frame
sets for any int8/bf16 perturbation (:mod:`gac_jax.guard.ap_resampling`), so a
single-block row there is mostly noise; ``--guard-data DIR --split S`` (a larger generated
dataset, e.g. 1,500 frames) and ``--bootstrap N`` add each row's paired-bootstrap verdict
(within / beyond / undecided at ~95 %, :mod:`gac_jax.guard.ap_resampling`).

    python benchmarks/bench_int8_sensitivity.py (--detect3d-workdir W | --depth-workdir W)
        [--int8-frames N] [--int8-seed S] [--split S] [--guard-data DIR] [--bootstrap N]
        [--results-dir DIR] [--threads N] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_runtime_accuracy import (  # noqa: E402  (benchmarks/ on sys.path)
    AP_TOLERANCE,
    SILOG_TOLERANCE,
    Combo,
    guard_depth,
    guard_detector,
)
from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.deploy.int8 import DEFAULT_FRAMES, Int8Settings  # noqa: E402


def block_prefix(name: str) -> str:
    """The block of a conv node name, as the prefix its members' names start with:
    ``backbone/layer2_`` (a ResNet stage), ``backbone/conv1`` (the stem), ``head/cls_conv``
    (``cls_conv1``, ``cls_conv2``), ``head/gac/``, ``up1/`` (a decoder stage)."""
    parts = name.split("/")
    if len(parts) == 1:
        return name
    if parts[0] == "backbone":
        stage = parts[1].split("_")[0]
        return f"backbone/{stage}" + ("_" if stage.startswith("layer") else "")
    if parts[0] == "head":
        if len(parts) > 2:
            return f"head/{parts[1]}/"
        return "head/" + re.sub(r"\d+$", "", parts[1])
    return parts[0] + "/"


def conv_blocks(onnx_path: Path) -> dict[str, int]:
    """``{block prefix: number of convs}`` of an exported ``model.onnx``."""
    import onnx

    blocks: dict[str, int] = {}
    for node in onnx.load(str(onnx_path)).graph.node:
        if node.op_type == "Conv":
            key = block_prefix(node.name)
            blocks[key] = blocks.get(key, 0) + 1
    return blocks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detect3d-workdir")
    parser.add_argument("--depth-workdir")
    parser.add_argument("--int8-frames", type=int, default=DEFAULT_FRAMES)
    parser.add_argument("--int8-seed", type=int, default=0)
    parser.add_argument("--split")
    parser.add_argument(
        "--guard-data", help="detector: evaluate on this KITTI-format dataset's --split"
    )
    parser.add_argument(
        "--bootstrap", type=int, default=0, help="detector: bootstrap resamples (0 = off)"
    )
    parser.add_argument("--results-dir", type=Path, help="keep exports and results here")
    parser.add_argument("--threads", type=int)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if bool(args.detect3d_workdir) == bool(args.depth_workdir):
        parser.error("give one of --detect3d-workdir or --depth-workdir")
    print(one_line(describe_machine("numpy", "jax", "openvino", "nncf")), flush=True)
    task = "detect3d" if args.detect3d_workdir else "depth"
    with tempfile.TemporaryDirectory(prefix="bench_int8_sensitivity_") as tmp:
        tmp = Path(tmp)
        if args.results_dir:
            args.results_dir.mkdir(parents=True, exist_ok=True)
            tmp = args.results_dir

        def guard(combos, boots=0):
            if task == "detect3d":
                return guard_detector(
                    args.detect3d_workdir,
                    args.split,
                    args.threads,
                    tmp,
                    combos,
                    args.guard_data,
                    0,
                    boots,
                )
            return guard_depth(args.depth_workdir, args.split, tmp, combos)

        first = guard([Combo("jax", "f32"), Combo("openvino", "f32")])  # writes the export
        export = tmp / ("det_export" if task == "detect3d" else "depth_export")
        blocks = conv_blocks(export / "model.onnx")
        print(f"\nblocks: {blocks}", flush=True)
        combos = [Combo("jax", "f32")]
        for block in [*blocks, None]:  # None: every block in int8
            keep = tuple(re.escape(b) for b in blocks if b != block) if block else ()
            combos.append(
                Combo("openvino", "int8", Int8Settings(args.int8_frames, args.int8_seed, keep))
            )
        result = guard(combos, args.bootstrap)
    labels = list(result["verdicts"])[1:]  # jax f32 first
    folded = result.get("bootstrap", {}).get("runs", {})
    rows = []
    print(
        f"\n{'int8 block (rest float32)':28s} {'convs':>5s} {'largest change':>15s}  verdict"
        + ("  bootstrap verdict: deciding entry (diff, se)" if folded else "")
    )
    for block, label in zip([*blocks, "(all: full int8)"], labels, strict=True):
        v = result["verdicts"][label]
        worst = v["max_abs_diff"] if task == "detect3d" else abs(v["silog_diff"])
        tolerance = AP_TOLERANCE if task == "detect3d" else SILOG_TOLERANCE
        row = {"block": block, "convs": blocks.get(block), "largest_change": worst}
        ok = "within" if worst <= tolerance else "NOT within"
        line = f"{block:28s} {blocks.get(block, sum(blocks.values())):5d} {worst:15.2f}  {ok}"
        if label in folded:
            f = folded[label]
            e = f["entries"][f["worst_entry"]]
            row.update(bootstrap_verdict=f["verdict"], deciding_entry=f["worst_entry"])
            line += f"  {f['verdict']}: {f['worst_entry']} ({e['diff']:+.2f}, {e['se']:.2f})"
        rows.append(row)
        print(line)
    if args.json:
        args.json.write_text(json.dumps({"first": first, "runs": result, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
