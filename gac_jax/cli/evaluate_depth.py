"""``evaluate.py``'s depth model mode: a trained depth workdir, or a no-learning baseline.

    python evaluate.py --task depth --workdir W [--data DIR] [--split val] [--step N]
                       [--out DIR] [--json OUT]
    python evaluate.py --task depth --baseline {ground-plane,row-mean} (--data DIR | --workdir W)
                       [--split val] [--out DIR] [--json OUT]

``--data`` is a KITTI-depth root (frames of ``data_depth_annotated/<split>``) or a
``depth_selection`` folder (``val_selection_cropped``, or the anonymous test set: PNGs are
written, nothing is scored). Without it, the workdir's own evaluation data is used. The
model mode writes 16-bit PNGs, pictures and ``metrics.json`` to ``--out`` (default
``W/eval/step_N_<split>``); the baseline writes PNGs only when ``--out`` is given.
Baselines: ``ground-plane`` (the ground depth of each frame's plane, its
``planes/<drive>/<frame>.txt`` file, else a camera 1.65 m above a flat road; with a workdir
whose config has ``data.use_planes = False`` always the latter) and ``row-mean`` (each row's
mean log-depth over the ``train`` split of the same data,
:mod:`gac_jax.evaluation.depth_baselines`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from gac_jax.cli.result_folder import check_resumable
from gac_jax.data import transforms
from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.deploy.int8 import Int8Settings, int8_settings
from gac_jax.deploy.runtime_choice import resolve_runtime, run_suffix, runtime_predictor
from gac_jax.evaluation.depth_baselines import RowMeanPredictor, fit_row_log_depth
from gac_jax.evaluation.depth_evaluator import (
    BASELINE_CAMERA_HEIGHT,
    BASELINE_MAX_DEPTH,
    DepthEvaluator,
    GroundPlanePredictor,
)
from gac_jax.evaluation.depth_metrics import format_depth_table
from gac_jax.guard.verdict_file import describe_precision, network_identity
from gac_jax.trained.depth import restore_depth_model
from gac_jax.trained.fingerprint import weights_sha256
from gac_jax.trained.run_config import load_workdir_config
from gac_jax.training import workdir_lock

BASELINES = ("ground-plane", "row-mean")


def _data_source(config, data: str | None, split: str | None):
    from gac_jax.builders import depth as builders

    if data is not None:
        if not Path(data).exists():
            raise KittiFormatError(data, "data folder not found")
        cameras = tuple(config.data.val_cameras) if config is not None else (2, 3)
        return builders.open_eval_data(Path(data), split or "val", cameras)
    return builders.eval_source(config, builders.depth_root(config.data), split)


def _tag(source, split: str | None) -> str:
    """Names an evaluation: the selection folder's name, or the split."""
    items = getattr(source, "items", None)
    if items:
        return items[0].image.parent.parent.name
    return split or getattr(source, "split", "val")


def evaluate_workdir(
    workdir: str | Path,
    data: str | None = None,
    split: str | None = None,
    step: int | None = None,
    out: str | Path | None = None,
    runtime: str = "jax",
    precision: str = "f32",
    export_dir: str | Path | None = None,
    int8: Int8Settings | None = None,
    max_batches: int | None = None,
    frames: list[str] | None = None,
) -> dict:
    """Runs a trained depth model over a split; returns the evaluator's result dict (with
    each scored image's metrics in ``per_image``; ``metrics.json`` keeps the rest).
    ``frames``: only these frame ids (both cameras; None: all).

    ``runtime`` / ``precision``: see :func:`runtime_predictor`; a non-default pair adds
    ``_<runtime>_<precision>`` to the default output folder. ``max_batches``: only the first
    batches of the split (None: all).
    """
    from gac_jax.builders import depth as builders

    config, model, variables, step = restore_depth_model(workdir, step)
    sha = weights_sha256(variables)
    source = _data_source(config, data, split)
    if frames is not None:
        from gac_jax.guard.depth_rule import sample_source

        source = sample_source(source, frames)
    name = f"step_{step}_{_tag(source, split)}{run_suffix(runtime, precision)}"
    out = Path(out) if out else Path(workdir) / "eval" / name
    evaluator = builders.make_evaluator(config, source)
    predictor = runtime_predictor(
        config, model, variables, step, workdir, runtime, precision, export_dir, int8, sha
    )
    guarded = Path(export_dir) if export_dir else Path(workdir) / "export" / f"step{step}"
    int8_used = (int8 or Int8Settings()) if precision == "int8" else None
    settings = {
        "weights": f"step{step}",
        "weights_sha256": sha,
        "data": str(Path(data).resolve()) if data else None,
        "split": split,
        "runtime": runtime,
        "precision": precision,
        "int8": dataclasses.asdict(int8_used) if int8_used else None,
    }
    if runtime != "jax":
        settings["network"] = network_identity(guarded, runtime, precision, int8_used)
    out.mkdir(parents=True, exist_ok=True)
    check_resumable(out / "run.json", settings, out / "depth")
    print(
        describe_precision(
            guarded, f"step{step}", runtime, precision, int8_used, weights_sha256=sha
        ),
        flush=True,
    )
    result = evaluator.evaluate(predictor, out / "depth", out / "pictures", max_batches=max_batches)
    result["step"] = step
    result["weights_sha256"] = sha
    result["runtime"] = {"runtime": runtime, "precision": precision} | (
        {"int8": dataclasses.asdict(int8 or Int8Settings())} if precision == "int8" else {}
    )
    with atomic_write(out / "metrics.json") as f:
        json.dump({k: v for k, v in result.items() if k != "per_image"}, f, indent=2)
    print(
        f"{result['num_frames']} frames, step {step} of {workdir}, predictions in {out / 'depth'}"
    )
    return result


def evaluate_baseline(
    name: str = "ground-plane",
    data: str | None = None,
    split: str | None = None,
    workdir: str | Path | None = None,
    out: str | Path | None = None,
) -> dict:
    """Scores a no-learning baseline (:data:`BASELINES`) on a split's original-size GT."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r} (known: {', '.join(BASELINES)})")
    if data is None and workdir is None:
        raise ValueError("the baseline needs --data or --workdir (whose data it then uses)")
    config = load_workdir_config(workdir) if workdir is not None else None
    source = _data_source(config, data, split)
    # The baseline reads only P2 and the geometry: a small fixed view keeps batches cheap.
    from gac_jax.builders.datasets import plane_ops

    planes = plane_ops(config.data) if config is not None else []
    view = transforms.Compose([*planes, transforms.Resize(32, 128)])
    evaluator = DepthEvaluator(source, view, batch_size=8, num_pictures=0)
    if name == "ground-plane":
        predictor = GroundPlanePredictor(BASELINE_CAMERA_HEIGHT, BASELINE_MAX_DEPTH)
        described = {"camera_height": BASELINE_CAMERA_HEIGHT, "max_depth": BASELINE_MAX_DEPTH}
    else:
        fit_on = _data_source(config, data, "train")
        predictor = RowMeanPredictor(fit_row_log_depth(fit_on))
        described = {"fitted_on": "train", "fitted_frames": len(fit_on)}
    result = evaluator.evaluate(predictor, Path(out) if out else None, resume=False)
    result["baseline"] = {"name": name, **described}
    print(f"{result['num_frames']} frames, {name} baseline")
    return result


def run(args: argparse.Namespace) -> dict:
    """Dispatch of ``evaluate.py --task depth --workdir/--baseline``; prints the table.

    Holds the workdir's lock when an output lies inside it (the model mode's default ``--out``,
    ``--json``, the export of ``--runtime``).
    """
    if args.baseline:
        outputs = [p for p in (args.out, args.json) if p]  # it writes nothing else
    else:
        outputs = [args.out, *([args.json] if args.json else [])]  # --out None: W/eval/...
    with workdir_lock.hold_if_inside(args.workdir, *outputs):
        result = _run(args)
    if result["metrics"]:
        print(format_depth_table(result["metrics"], result["num_scored"]), end="")
    else:
        print("no ground truth: predictions written, nothing scored")
    return result


def _run(args: argparse.Namespace) -> dict:
    if args.baseline:
        result = evaluate_baseline(args.baseline, args.data, args.split, args.workdir, args.out)
    else:
        export = getattr(args, "export", None)
        runtime, precision = resolve_runtime(
            getattr(args, "runtime", None), getattr(args, "precision", None)
        )
        try:
            int8 = int8_settings(args)
        except ValueError as e:
            raise KittiFormatError("evaluate.py", str(e)) from None
        if export and runtime == "jax":
            raise KittiFormatError(
                export, "--export only applies with --runtime onnxruntime|openvino"
            )
        result = evaluate_workdir(
            args.workdir,
            args.data,
            args.split,
            args.step,
            args.out,
            runtime,
            precision,
            export,
            int8,
        )
    return result
