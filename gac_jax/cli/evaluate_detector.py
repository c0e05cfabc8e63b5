"""``evaluate.py --task detect3d --workdir W``: checkpoint -> KITTI result files -> AP table.

    python evaluate.py --task detect3d --workdir W [--config C] [--data DIR] [--split val]
        [--step N | --checkpoint DIR] [--batch-size B] [--save-images K] [--threads T]
        [--json OUT] [key.sub=value ...]

Restores the latest (or ``--step``) training checkpoint of ``W`` (or converted
weights, ``--checkpoint DIR --config C``), rebuilds model, anchors and priors
from ``W/config.json`` and ``W/anchor_priors.npz``, compiles the predict
function once for the evaluation batch shape and writes one KITTI result file
per frame to ``W/eval/<split>_step<N>/data/`` as it goes; an interrupted run
resumes without redoing finished frames (``run.json`` there records the settings,
and a folder made with other settings is refused rather than mixed; the command holds the
workdir's lock meanwhile, so it refuses a workdir that training writes to). Then prints
the AP table (``--json``: the offline mode's JSON), frames/s split into model,
post-processing and I/O time, and writes everything to ``metrics.json`` there.

Loading the detector (config + model + anchors/priors + weights of a workdir):
:mod:`gac_jax.trained.detector`, shared with ``python -m gac_jax.cli.predict``.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from gac_jax.builders.datasets import prepare_dataset
from gac_jax.cli.model_mode import limit_cpu_threads, xla_thread_count
from gac_jax.cli.result_folder import check_resumable
from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.data.sources import open_object_source
from gac_jax.deploy.int8 import Int8Settings, int8_settings
from gac_jax.deploy.runtime_choice import (
    default_export_dir,
    resolve_runtime,
    run_suffix,
    use_runtime,
)
from gac_jax.drawing.detection_pictures import save_evaluation_pictures
from gac_jax.evaluation.ap_table import format_table
from gac_jax.evaluation.operating_point import describe
from gac_jax.guard.verdict_file import network_identity, precision_line
from gac_jax.trained.detector import LoadedDetector, evaluator_for, load_detector

# imported from here by tests and benchmarks (explicit re-exports)
from gac_jax.trained.detector import postprocess_config as postprocess_config
from gac_jax.trained.operating_point import write_operating_point
from gac_jax.trained.run_config import load_run_config
from gac_jax.training import workdir_lock


def run_settings(
    detector: LoadedDetector,
    split: str,
    root: Path,
    dtype,
    runtime: str = "jax",
    precision: str = "f32",
    int8: Int8Settings | None = None,
    network: dict | None = None,
) -> dict:
    """What the result files of a run depend on (compared when resuming,
    :func:`gac_jax.cli.result_folder.check_resumable`); ``network``: for an exported network
    its :func:`gac_jax.guard.verdict_file.network_identity`."""
    c = detector.config
    return (
        {
            # the workdir's own checkpoints by step (the workdir may move), converted ones by path
            "weights": detector.tag if detector.step is not None else detector.weights,
            "weights_sha256": detector.weights_sha256,
            "split": split,
            "data_root": str(Path(root).resolve()),
            "dtype": jnp.dtype(dtype).name,
            "input": {k: c.data[k] for k in ("crop_top", "height", "width")},
            "classes": list(c.data.classes),
            "anchors": c.anchors.to_dict(),
            "model": c.model.to_dict(),
            "eval": {k: v for k, v in c.eval.to_dict().items() if k != "num_pictures"},
        }
        | ({"runtime": runtime, "precision": precision} if runtime != "jax" else {})
        | ({"int8": dataclasses.asdict(int8)} if precision == "int8" and int8 else {})
        | ({"network": network} if network is not None else {})
    )


def timing_summary(timings: dict, batch_timings: list[dict]) -> dict[str, float]:
    """Per-frame means and medians (ms) of model / post-processing / I/O, and frames/s."""
    frames = timings.get("num_frames", 0.0)
    out: dict[str, float] = {"frames": frames}
    if not frames:
        return out
    total = timings["model_s"] + timings["postprocess_s"] + timings["io_s"]
    out["frames_per_s"] = frames / total if total > 0 else float("inf")
    for key in ("model", "postprocess", "io"):
        per_frame = [b[f"{key}_s"] / b["frames"] for b in batch_timings if b["frames"]]
        out[f"{key}_ms_mean"] = 1e3 * timings[f"{key}_s"] / frames
        out[f"{key}_ms_median"] = 1e3 * float(np.median(per_frame))
    return out


def format_timing(summary: dict[str, float], compile_s: float | None, threads: int) -> str:
    if not summary.get("frames"):
        return "no frame predicted in this run (all results were already there)\n"
    s = summary
    lines = [
        f"speed ({threads} CPU threads): {s['frames_per_s']:.2f} frames/s end to end over "
        f"{int(s['frames'])} frames",
        "  per frame, median (mean): "
        f"model {s['model_ms_median']:.1f} ({s['model_ms_mean']:.1f}) ms, "
        f"post-processing {s['postprocess_ms_median']:.1f} ({s['postprocess_ms_mean']:.1f}) ms, "
        f"I/O {s['io_ms_median']:.1f} ({s['io_ms_mean']:.1f}) ms",
    ]
    if compile_s is not None:
        lines.append(f"  compile (once, not included): {compile_s:.1f} s")
    return "\n".join(lines) + "\n"


def format_candidates(summary: dict) -> str:
    """One line on the candidate cap (:meth:`DetectionEvaluator.candidate_summary`)."""
    if not summary.get("frames"):
        return ""
    cap = "every anchor" if summary["top_k"] is None else f"top_k {summary['top_k']}"
    return (
        f"candidates ({cap}, {summary['kept_per_frame']} per frame): "
        f"{summary['frames_over_cap']} of {summary['frames']} frames had more anchors above the "
        f"score threshold, lost before NMS (max {summary['max_candidates']} in one frame)\n"
    )


def evaluate_detector_workdir(
    workdir: str | os.PathLike,
    *,
    config_spec: str | None = None,
    overrides: list[str] | None = None,
    data_root: str | os.PathLike | None = None,
    split: str | None = None,
    step: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    batch_size: int | None = None,
    save_images: int = 0,
    threads: int | None = None,
    dtype: Any = jnp.float32,
    out_dir: str | os.PathLike | None = None,
    runtime: str = "jax",
    precision: str = "f32",
    export_dir: str | os.PathLike | None = None,
    int8: Int8Settings | None = None,
) -> dict:
    """The model mode as a function (see the module docstring); prints as it goes.

    Returns:
      ``{'metrics': <offline-mode result dict>, 'timings', 'speed', 'compile_s',
      'num_frames', 'candidates' (the candidate-cap counter), 'predicted', 'resumed',
      'result_dir', 'weights', 'threads'}``.
    """
    threads = limit_cpu_threads(threads)
    workdir = Path(workdir)
    if not workdir.is_dir() and not (checkpoint is not None and config_spec):
        raise KittiFormatError(workdir, "workdir not found")
    config = load_run_config(workdir, config_spec, overrides, data_root)
    if runtime == "jax" and precision == "bf16":
        dtype = jnp.bfloat16
    onnx = runtime != "jax"
    detector = load_detector(
        workdir, config, step=step, checkpoint=checkpoint, dtype=jnp.float32 if onnx else dtype
    )
    split = split or config.data.val_split
    root = prepare_dataset(config.data)
    source = open_object_source(root, split, use_right_image=False)
    batch_size = batch_size or config.data.eval_batch_size
    evaluator = evaluator_for(detector, source, batch_size)
    suffix = run_suffix(runtime, precision)
    out = Path(out_dir) if out_dir else workdir / "eval" / f"{split}_{detector.tag}{suffix}"
    result_dir = out / "data"
    if precision == "int8":
        int8 = int8 or Int8Settings()
    compile_s, network = None, None
    if onnx:  # load (or export) first: a refused export leaves no run.json behind
        compile_s = use_runtime(
            evaluator,
            detector,
            workdir,
            runtime,
            precision,
            export_dir=export_dir,
            threads=threads,
            int8=int8,
        )
        exported = export_dir or default_export_dir(workdir, detector)
        network = network_identity(exported, runtime, precision, int8)
    settings = run_settings(detector, split, root, dtype, runtime, precision, int8, network)
    check_resumable(out / "run.json", settings, result_dir)
    print(precision_line(workdir, detector, runtime, precision, int8, export_dir), flush=True)
    ids = evaluator.frame_ids()
    resumed = sum((result_dir / f"{fid}.txt").exists() for fid in ids)
    print(
        f"evaluating {detector.weights} on split {split!r} of {root}: {len(ids)} frames "
        f"({resumed} already done) -> {result_dir}",
        flush=True,
    )
    if resumed < len(ids) and not onnx:
        compile_s = evaluator.compile(detector.variables, (config.data.height, config.data.width))
    result = evaluator.evaluate(detector.variables, result_dir, resume=True)
    speed = timing_summary(result["timings"], evaluator.batch_timings)
    threads = xla_thread_count() or threads  # the compute threads XLA actually started
    print(format_table(result["metrics"]), end="")
    if onnx:
        print(f"network: exported ONNX in {runtime} ({precision})")
    print(format_timing(speed, compile_s, threads), end="")
    print(format_candidates(result["candidates"]), end="", flush=True)
    record = result["operating_point"]
    write_operating_point(out, record, detector.step, detector.weights_sha256, split)
    print(f"{describe(record)} on split {split!r}", flush=True)
    pictures = save_evaluation_pictures(
        source, result_dir, save_images, tuple(config.data.classes), out / "pictures"
    )
    if pictures:
        print(f"{len(pictures) - 1} pictures and grid.png in {out / 'pictures'}")
    summary = {
        "metrics": result["metrics"],
        "timings": result["timings"],
        "speed": speed,
        "compile_s": compile_s,
        "num_frames": result["num_frames"],
        "candidates": result["candidates"],
        "operating_point": record,
        "predicted": int(result["timings"]["num_frames"]),
        "resumed": resumed,
        "result_dir": str(result_dir),
        "weights": detector.weights,
        "threads": threads,
        "runtime": runtime,
        "precision": precision,
    }
    with atomic_write(out / "metrics.json") as f:
        json.dump(summary, f, indent=2)
        f.write("\n")
    return summary


def run_model_mode(args, parser) -> dict:
    """``evaluate.py --task detect3d --workdir ...``: returns the offline mode's result dict."""
    if args.label_dir or args.result_dir:
        parser.error("--workdir (model mode) and --label-dir/--result-dir are exclusive")
    if args.checkpoint and args.step is not None:
        parser.error("--step selects a checkpoint of the workdir; it cannot go with --checkpoint")
    if args.checkpoint and not args.config and not (Path(args.workdir) / "config.json").exists():
        parser.error("--checkpoint (converted weights) needs --config")
    if args.export and (args.runtime or "jax") == "jax":
        parser.error("--export only applies with --runtime onnxruntime|openvino")
    runtime, precision = resolve_runtime(args.runtime, args.precision)
    try:
        threads = limit_cpu_threads(args.threads)
        int8 = int8_settings(args)
    except ValueError as e:
        parser.error(str(e))
    with workdir_lock.hold_if_inside(args.workdir, None):  # results go to W/eval/
        summary = _evaluate(args, threads, runtime, precision, int8)
    return summary["metrics"]


def _evaluate(args, threads: int, runtime: str, precision: str, int8) -> dict:
    return evaluate_detector_workdir(
        args.workdir,
        config_spec=args.config,
        overrides=args.overrides,
        data_root=args.data,
        split=args.split,
        step=args.step,
        checkpoint=args.checkpoint,
        batch_size=args.batch_size,
        save_images=args.save_images,
        threads=threads,
        runtime=runtime,
        precision=precision,
        export_dir=args.export,
        int8=int8,
    )
