"""``python -m gac_jax.cli.guard --workdir W`` for a depth workdir: the SILog guard.

    python -m gac_jax.cli.guard --workdir W --candidates openvino:bf16,openvino:int8
        [--guard-data DIR [--split val]] [--frames N] [--step N] [--margin 0.2] [--json OUT]

Runs the depth network of ``W`` with jitted float32 (the reference) and every candidate on
the same frames, each exactly as ``evaluate.py --task depth --runtime R --precision P``
builds it (export and int8 model in ``W/export/step<N>``), and decides per candidate with
:mod:`gac_jax.guard.depth_rule`: the paired per-frame SILog difference ->
within / beyond / undecided (with the frames that would decide). Prints the KITTI depth
metrics of each run, the paired differences and the verdicts, and writes the verdicts to
``W/export/step<N>/guard.json``, which ``evaluate.py --task depth`` and
:meth:`gac_jax.api.DepthPredictor.precision_line` read.

Guard frames: ``--guard-data DIR``, a KITTI-depth root (``DIR/data_depth_annotated``) or a
generated dataset (its ``depth/`` folder is used), split ``--split`` (default ``val``); else
the run's own evaluation data. At least 100 frames (fewer are refused before any model runs);
``--frames N`` (at least 100) takes N frames spread evenly over the drives, both cameras of
each (:func:`gac_jax.guard.depth_rule.spread_frames`), not the first N. Depth
maps go to ``W/eval/guard_<data>_<split>_step<N>/<candidate>/depth``, one PNG per image as
they are made; a rerun resumes them. A rerun on the same model is the next look and spends
less alpha (:mod:`gac_jax.guard.depth_rule`).
"""

from __future__ import annotations

import datetime
from pathlib import Path


def _depth_root(guard_data: Path | None) -> Path | None:
    if guard_data is None:
        return None
    nested = guard_data / "depth"
    if not (guard_data / "data_depth_annotated").is_dir() and nested.is_dir():
        return nested  # a generated dataset: its KITTI-depth part
    return guard_data


def guard_depth_workdir(args, candidates, settings) -> dict:
    """The depth guard (module docstring); ``candidates``: ``[(runtime, precision, _)]``,
    ``settings(keep_heading)``: the int8 settings of the command line. Returns the report."""
    from gac_jax.cli.evaluate_depth import evaluate_workdir
    from gac_jax.data.files import KittiFormatError
    from gac_jax.guard import depth_rule, verdict_file
    from gac_jax.trained.depth import checkpoint_step
    from gac_jax.trained.run_config import load_workdir_config
    from gac_jax.training import workdir_lock

    for runtime, precision, heading in candidates:
        if heading:
            raise KittiFormatError(
                f"{runtime}:{precision}+heading", "'+heading' applies to detectors only"
            )
    workdir = Path(args.workdir)
    config = load_workdir_config(workdir)
    step = checkpoint_step(workdir, args.step)  # each run below restores the weights itself
    root = _depth_root(args.guard_data)
    if root is not None and not root.exists():
        raise KittiFormatError(root, "guard data folder not found")
    split = args.split or ("val" if root is not None else None)
    chosen = _guard_frames(config, root, split, args.frames)
    margin = depth_rule.MARGIN if args.margin is None else args.margin
    alpha = depth_rule.ALPHA if args.alpha is None else args.alpha
    data_name = Path(args.guard_data).resolve().name if root is not None else "own"
    base = workdir / "eval" / f"guard_{data_name}_{split or 'val'}_step{step}"
    export_dir = workdir / "export" / f"step{step}"
    runs = [("jax", "f32", False), *candidates]
    results = {}
    with workdir_lock.hold_if_inside(workdir, None):
        for runtime, precision, _ in runs:
            int8 = settings(False) if precision == "int8" else None
            key = verdict_file.candidate_key(runtime, precision, int8)
            print(f"=== depth {key} ({data_name} {split or 'val'}) ===", flush=True)
            results[key] = evaluate_workdir(
                workdir,
                str(root) if root is not None else None,
                split,
                step,
                base / key.replace(":", "_"),
                runtime,
                precision,
                export_dir,
                int8,
                frames=chosen,
            )
        ref = results["jax:f32"]
        if not ref["per_image"]:
            raise KittiFormatError(root or workdir, "no guard image has depth ground truth")
        report = {"frames": None, "reference": ref["metrics"], "candidates": {}}
        verdicts = {}
        created = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        model = verdict_file.model_identity(export_dir, f"step{step}", ref["weights_sha256"])
        rule = {
            "version": verdict_file.DEPTH_RULE_VERSION,
            "text": "paired per-frame SILog vs jax float32 (gac_jax.guard.depth_rule)",
            "margin_silog": margin,
            "alpha": alpha,
            "alpha_spending": "alpha / 2^k at look k",
            "min_frames": depth_rule.MIN_FRAMES,
            "frames": "all" if chosen is None else "spread evenly over the drives",
        }
        for runtime, precision, _ in candidates:
            int8 = settings(False) if precision == "int8" else None
            key = verdict_file.candidate_key(runtime, precision, int8)
            res = results[key]
            looks = verdict_file.previous_looks(export_dir, model, key)
            try:
                decision = depth_rule.decide_depth(
                    ref["per_image"],
                    res["per_image"],
                    margin,
                    alpha,
                    len(looks) + 1,
                    depth_rule.MIN_FRAMES,
                )
            except ValueError as e:
                raise KittiFormatError(root or workdir, str(e)) from None
            report["frames"] = decision["frames"]
            ms = _model_ms(res)
            report["candidates"][key] = {"decision": decision, "model_ms": ms}
            row = decision["criteria"]["silog"]
            verdicts[key] = verdict_file.verdict_entry(
                runtime,
                precision,
                int8,
                verdict_file.network_identity(export_dir, runtime, precision, int8),
                verdict=decision["verdict"],
                reason=decision["reason"],
                frames=decision["frames"],
                images=decision["images"],
                frames_needed=decision.get("frames_needed"),
                guard_set={"data_root": str(root.resolve()) if root else None, "split": split},
                created=created,
                criteria={"silog": {k: row[k] for k in ("n", "diff", "status")}},
                rule=rule,
                look=decision["look"],
                alpha_look=decision["alpha_look"],
                looks=[
                    *looks,
                    {
                        "frames": decision["frames"],
                        "verdict": decision["verdict"],
                        "created": created,
                    },
                ],
                drives=len({depth_rule.drive_of(r["frame"]) for r in ref["per_image"]}),
            )
        report["guard_file"] = str(verdict_file.write_guard(export_dir, model, rule, verdicts))
    report["reference_ms"] = _model_ms(ref)
    print_depth_report(report)
    return report


def _guard_frames(config, root: Path | None, split: str | None, frames: int | None):
    """The frame ids the guard runs on (None: all), checked before any model runs: at least
    ``MIN_FRAMES`` of them, ``--frames N`` spread evenly over the drives."""
    from gac_jax.cli.evaluate_depth import _data_source
    from gac_jax.data.files import KittiFormatError
    from gac_jax.guard import depth_rule as pdg

    if frames is not None and frames < pdg.MIN_FRAMES:
        raise KittiFormatError(
            "--frames", f"the depth guard needs at least {pdg.MIN_FRAMES} frames, got {frames}"
        )
    source = _data_source(config, str(root) if root is not None else None, split)
    try:
        ids = set(pdg.source_frame_ids(source))
    except ValueError:
        if frames is not None:
            raise KittiFormatError("--frames", "this guard data cannot be sampled") from None
        return None  # counted after the runs (decide_depth refuses too few)
    if len(ids) < pdg.MIN_FRAMES:
        raise KittiFormatError(
            root if root is not None else "guard data",
            f"{len(ids)} frames; the depth guard needs at least {pdg.MIN_FRAMES} frames",
        )
    return None if frames is None or frames >= len(ids) else pdg.spread_frames(sorted(ids), frames)


def _model_ms(result: dict) -> float | None:
    """Model time per image (ms) of a run; None when every image was resumed."""
    n = result.get("num_predicted") or 0
    return 1e3 * result["timings"]["model_s"] / n if n else None


def print_depth_report(report: dict) -> None:
    """Each candidate's metrics next to float32's, the paired differences, the verdicts."""
    from gac_jax.guard.depth_rule import REPORTED

    print(f"\ndepth metrics on {report['frames']} frames (candidate - jax f32, paired)")
    for key, c in report["candidates"].items():
        d = c["decision"]
        print(f"{key}:")
        for m in REPORTED:
            r = d["reported"][m]
            iv = r["interval"]
            print(
                f"  {m:8s} {d['reference'][m]:10.3f} -> {d['candidate'][m]:10.3f}"
                f"  {r['diff']:+9.4f} [{iv[0]:+9.4f}, {iv[1]:+9.4f}]"
            )
    print(f"\nverdicts (gac_jax.guard.depth_rule), written to {report['guard_file']}:")
    for key, c in report["candidates"].items():
        ms = f", model {c['model_ms']:.1f} ms/image" if c["model_ms"] else ""
        print(f"  {key:24s} {c['decision']['verdict']:9s} {c['decision']['reason']}{ms}")
    if report.get("reference_ms"):
        print(f"  (jax:f32 model {report['reference_ms']:.1f} ms/image)")
