"""``python -m gac_jax.cli.guard``: decides whether a runtime/precision keeps a trained model.

    python -m gac_jax.cli.guard --workdir W --candidates openvino:int8,openvino:bf16
        [--guard-data DIR [--split val]] [--frames N] [--step N] [--margin 0.5]
        [--ap-margin 1.0] [--fp-cap 20] [--resamples 200] [--heading-tolerance 30]
        [--int8-frames N] [--int8-seed S] [--threads T] [--json OUT]

Runs the detector of ``W`` (latest or ``--step`` checkpoint) on the guard frames with jitted
float32 (the reference) and with every candidate (``RUNTIME:PRECISION``, ``+heading`` for int8
with the heading kept in float32: ``openvino:int8+heading``), each exactly as ``evaluate.py
--runtime R --precision P [--int8-keep-heading]`` builds it (export and int8 model in
``W/export/<step>``, int8 calibrated on the run's training split), and decides per candidate
with :mod:`gac_jax.guard.detector_rule`: paired recall at 2D@0.7, BEV@0.5/0.7, 3D@0.5/0.7
and heading at the deployed score threshold and at 0.3 / 0.5 / 0.7 / 0.9 above it, false
positives per frame above each, heading and centre error quantile shifts, per class and
difficulty (frames as the unit, tests by betting valid for any per-frame distribution of the
changes within a bound: a frame changes at most its objects, or ``--fp-cap`` false positives,
checked), and every AP entry with a paired frame bootstrap -> within / beyond / undecided
(with the frames that would decide at the next look; a rerun on the same model is the next
look and spends less alpha). Prints the Car AP|R40 table (all frames, difference to
float32), each candidate's criteria that are not within, the matched detections' differences
and the verdicts, and writes the verdicts with their rule to ``W/export/<step>/guard.json``
(:mod:`gac_jax.guard.verdict_file`), which ``evaluate.py`` reads to say whether the
precision it runs was guarded.

Guard frames: ``--guard-data DIR`` (a KITTI-format root, e.g. generated frames the model never
saw: ``python -m gac_jax.data.synthetic --out DIR --num 3200 --seed 2 --val-fraction 0.9375``)
split ``--split`` (default ``val``), else the run's own val split; ``--frames N`` takes the
first N (whole batches). Result files go to ``W/eval/guard_<data>_<split>/<candidate>/data``,
one per frame as they are made, and the guard decides on what they hold; a rerun resumes them
(a folder made from other weights, by their sha256, or another exported network starts again;
one made with other settings is refused). The verdicts are bound to the weights' sha256, the
exported graph, the int8 model, the runtime's version and the score threshold
(:mod:`gac_jax.guard.verdict_file`).

A depth workdir (``python train.py --task depth``) gets the depth guard instead: the paired
per-frame SILog difference, margin 0.2 (:mod:`gac_jax.cli.guard_depth`).
"""

from __future__ import annotations

import argparse
import datetime
import math
import sys
from collections.abc import Sequence
from pathlib import Path

SHOWN_UNDECIDED = 8  # undecided criteria printed per candidate (beyond ones: all)
HELP_CANDIDATES = "RUNTIME:PRECISION[,...], e.g. openvino:int8,openvino:int8+heading,openvino:bf16"


def parse_candidates(text: str) -> list[tuple[str, str, bool]]:
    """``[(runtime, precision, keep_heading), ...]`` of ``--candidates``.

    Raises:
      ValueError: a malformed entry, naming it.
    """
    out = []
    for item in (t.strip() for t in text.split(",") if t.strip()):
        spec, plus, extra = item.partition("+")
        runtime, colon, precision = spec.partition(":")
        if not colon or not runtime or precision not in ("f32", "bf16", "int8"):
            raise ValueError(f"--candidates {item!r}: want RUNTIME:PRECISION (f32, bf16, int8)")
        if plus and (extra != "heading" or precision != "int8"):
            raise ValueError(f"--candidates {item!r}: only int8 takes '+heading'")
        if (runtime, precision) == ("jax", "f32"):
            raise ValueError("--candidates jax:f32 is the reference; it is always run")
        out.append((runtime, precision, bool(plus)))
    if not out:
        raise ValueError("--candidates: give at least one RUNTIME:PRECISION")
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m gac_jax.cli.guard", description=__doc__.splitlines()[0]
    )
    p.add_argument("--workdir", required=True, help="a trained detect3d or depth workdir")
    p.add_argument("--candidates", required=True, help=HELP_CANDIDATES)
    p.add_argument("--guard-data", type=Path, metavar="DIR", help="KITTI-format guard frames")
    p.add_argument("--split", help="split of the guard frames (default val)")
    p.add_argument("--frames", type=int, metavar="N", help="the first N frames (whole batches)")
    p.add_argument("--step", type=int, help="checkpoint step (default: the latest)")
    p.add_argument(
        "--margin", type=float, default=None, help="points of found-rate (0.5); depth: SILog (0.2)"
    )
    p.add_argument("--alpha", type=float, default=None, help="error level (0.05)")
    p.add_argument("--ap-margin", type=float, default=None, help="AP points (1.0)")
    p.add_argument(
        "--fp-cap",
        type=float,
        default=None,
        help="false positives one frame may gain or lose, assumed and checked (20)",
    )
    p.add_argument(
        "--resamples", type=int, default=None, help="frame-bootstrap resamples of AP (200)"
    )
    p.add_argument("--heading-tolerance", type=float, default=None, help="degrees (30)")
    p.add_argument("--int8-frames", type=int, help="calibration frames (as evaluate.py)")
    p.add_argument("--int8-seed", type=int, help="calibration seed (as evaluate.py)")
    p.add_argument(
        "--int8-keep-float",
        action="append",
        metavar="REGEX",
        help="int8 candidates: also keep these layers in float32 (as evaluate.py; repeatable)",
    )
    p.add_argument("--threads", type=int, help="CPU threads")
    p.add_argument("--json", type=Path, help="also write the full result here")
    return p


def _settings(args, keep_heading: bool):
    from gac_jax.deploy.int8 import DEFAULT_FRAMES, DEFAULT_SEED, Int8Settings

    return Int8Settings(
        frames=DEFAULT_FRAMES if args.int8_frames is None else args.int8_frames,
        seed=DEFAULT_SEED if args.int8_seed is None else args.int8_seed,
        keep_float=tuple(args.int8_keep_float or ()),
        keep_heading=keep_heading,
    )


def _folder(key: str, int8) -> str:
    """Result folder name of a candidate; int8 with other than the default calibration or a
    float32 scope gets a hash of its settings too."""
    from gac_jax.deploy.int8 import Int8Settings

    name = key.replace(":", "_").replace("+", "_")
    if int8 is not None and int8 != Int8Settings(keep_heading=int8.keep_heading):
        import hashlib

        name += "_" + hashlib.sha1(repr(int8).encode()).hexdigest()[:8]
    return name


def _predict(workdir, config, step, source, runtime, precision, int8, out, threads, batches):
    """Detections ``{frame id: KittiObjects}`` of one runtime/precision as its resumable
    files in ``out/data`` hold them (a fresh run and a resumed one decide alike), the median
    model time per frame (ms; None when all were resumed), the detector and the exported
    network's identity (None for jax)."""
    import jax.numpy as jnp
    import numpy as np

    from gac_jax.cli.evaluate_detector import run_settings
    from gac_jax.cli.result_folder import check_resumable
    from gac_jax.data.kitti import read_label
    from gac_jax.deploy.runtime_choice import default_export_dir, use_runtime
    from gac_jax.guard.verdict_file import network_identity
    from gac_jax.trained.detector import evaluator_for, load_detector

    dtype = jnp.bfloat16 if (runtime, precision) == ("jax", "bf16") else jnp.float32
    detector = load_detector(workdir, config, step=step, dtype=dtype)
    evaluator = evaluator_for(detector, source, config.data.eval_batch_size)
    network = None
    if runtime != "jax":
        use_runtime(evaluator, detector, workdir, runtime, precision, threads=threads, int8=int8)
        export_dir = default_export_dir(workdir, detector)
        network = network_identity(export_dir, runtime, precision, int8)
    root = Path(source.layout.root) if hasattr(source, "layout") else Path(".")
    settings = run_settings(detector, source.split, root, dtype, runtime, precision, int8, network)
    out.mkdir(parents=True, exist_ok=True)
    check_resumable(out / "run.json", settings, out / "data")
    ids = evaluator.frame_ids()[: batches * evaluator.batch_size]
    if runtime == "jax" and not all((out / "data" / f"{i}.txt").exists() for i in ids):
        evaluator.compile(detector.variables, (config.data.height, config.data.width))
    evaluator.predict_split(detector.variables, out / "data", True, batches)
    per_frame = [b["model_s"] / b["frames"] for b in evaluator.batch_timings if b["frames"]]
    model_ms = 1e3 * float(np.median(per_frame)) if per_frame else None
    # the detections as the result files hold them (boxes to 0.01 px), also for the frames
    # predicted now: a rerun (the next look) resumes from the files and must see the same
    found = {i: read_label(out / "data" / f"{i}.txt", with_score=True) for i in ids}
    return found, model_ms, detector, network


def guard_workdir(args) -> dict:
    """The command as a function (module docstring); returns everything it prints."""
    from gac_jax.builders.datasets import prepare_dataset
    from gac_jax.builders.depth import PRIOR_FILE
    from gac_jax.cli.model_mode import limit_cpu_threads
    from gac_jax.data.files import KittiFormatError
    from gac_jax.data.sources import open_object_source
    from gac_jax.deploy.runtime_choice import default_export_dir, resolve_runtime
    from gac_jax.evaluation.detector_evaluator import ground_truth
    from gac_jax.evaluation.kitti_object import evaluate_detections
    from gac_jax.guard import ap_bootstrap, criteria, detector_rule, verdict_file
    from gac_jax.guard.ap_resampling import car_ap40
    from gac_jax.trained.detector import load_detector
    from gac_jax.trained.operating_point import apply_deploy_threshold
    from gac_jax.trained.run_config import load_run_config
    from gac_jax.training import workdir_lock

    candidates = parse_candidates(args.candidates)
    if args.fp_cap is not None and not args.fp_cap > 0:
        raise KittiFormatError("--fp-cap", f"must be positive, got {args.fp_cap}")
    threads = limit_cpu_threads(args.threads)
    for runtime, precision, _ in candidates:
        resolve_runtime(runtime, precision)  # exits 2 with one line when it cannot run here
    workdir = Path(args.workdir)
    if not (workdir / "config.json").is_file():
        raise KittiFormatError(workdir, "not a trained workdir (no config.json)")
    if (workdir / PRIOR_FILE).is_file():  # a depth run
        from gac_jax.cli.guard_depth import guard_depth_workdir

        return guard_depth_workdir(args, candidates, lambda heading: _settings(args, heading))
    config = load_run_config(workdir, None, None, None)
    root = Path(args.guard_data) if args.guard_data else Path(prepare_dataset(config.data))
    split = args.split or ("val" if args.guard_data else config.data.val_split)
    source = open_object_source(root, split, use_right_image=False)
    total = len(source)
    if total == 0:
        raise KittiFormatError(root, f"no frames in split {split!r}")
    frames = min(args.frames or total, total)
    if frames < 1:
        raise KittiFormatError(root, f"--frames must be at least 1, got {args.frames}")
    batch = config.data.eval_batch_size
    batches = math.ceil(frames / batch)
    margin = detector_rule.MARGIN if args.margin is None else args.margin
    alpha = detector_rule.ALPHA if args.alpha is None else args.alpha
    tol = criteria.HEADING_TOLERANCE_DEG
    tol = tol if args.heading_tolerance is None else args.heading_tolerance
    # the verdicts hold at the threshold the run is deployed at (its recorded operating point
    # where its config asks for one), and at the grid's thresholds above it
    deployed = load_detector(workdir, config, step=args.step)
    try:
        print(apply_deploy_threshold(workdir, deployed, explicit=False), flush=True)
    except ValueError as e:  # an unknown eval.deploy_threshold
        raise KittiFormatError(workdir / "config.json", str(e)) from None
    min_score = float(config.eval.score_threshold)
    thresholds = criteria.score_thresholds(min_score)
    ap_margin = detector_rule.AP_MARGIN if args.ap_margin is None else args.ap_margin
    fp_cap = detector_rule.FP_CAP if args.fp_cap is None else args.fp_cap
    resamples = ap_bootstrap.RESAMPLES if args.resamples is None else args.resamples
    if resamples < 2:
        raise KittiFormatError("--resamples", f"must be at least 2, got {resamples}")
    classes = tuple(config.data.classes)
    base = workdir / "eval" / f"guard_{root.resolve().name}_{split}"
    runs = [("jax", "f32", False), *candidates]
    results, speed, networks = {}, {}, {}
    with workdir_lock.hold_if_inside(workdir, None):
        for runtime, precision, heading in runs:
            key = verdict_file.candidate_key(
                runtime, precision, _settings(args, heading) if precision == "int8" else None
            )
            print(f"=== {key} on {frames} frames of {root} ({split}) ===", flush=True)
            int8 = _settings(args, heading) if precision == "int8" else None
            out = base / _folder(key, int8)
            dets, ms, detector, network = _predict(
                workdir, config, args.step, source, runtime, precision, int8, out, threads, batches
            )
            results[key], speed[key], networks[key] = dets, ms, network
        ids = list(results["jax:f32"])
        gt = [ground_truth(source, i) for i in range(len(ids))]
        ref = [results["jax:f32"][i] for i in ids]
        export_dir = default_export_dir(workdir, detector)
        ap_ref = car_ap40(evaluate_detections(gt, ref, classes=("Car",)))
        report = {"frames": len(ids), "reference_ap": ap_ref, "candidates": {}}
        verdicts = {}
        created = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
        model = verdict_file.model_identity(export_dir, detector.tag, detector.weights_sha256)
        rule = _rule(margin, ap_margin, alpha, tol, min_score, thresholds, resamples, fp_cap)
        for runtime, precision, heading in candidates:
            int8 = _settings(args, heading) if precision == "int8" else None
            key = verdict_file.candidate_key(runtime, precision, int8)
            cand = [results[key][i] for i in ids]
            tables = criteria.guard_tables(gt, ref, cand, classes, min_score, tol, thresholds)
            ap = ap_bootstrap.paired_ap_bootstrap(gt, ref, cand, classes, resamples)
            looks = verdict_file.previous_looks(export_dir, model, key)
            decision = detector_rule.decide(
                tables, len(ids), margin, alpha, len(looks) + 1, ap, ap_margin, fp_cap
            )
            ap = car_ap40(evaluate_detections(gt, cand, classes=("Car",)))
            matched = detector_rule.matched_differences(ref, cand)
            report["candidates"][key] = {
                "decision": decision,
                "ap": ap,
                "matched": matched,
                "model_ms": speed[key],
            }
            verdicts[key] = verdict_file.verdict_entry(
                runtime,
                precision,
                int8,
                networks[key],
                verdict=decision["verdict"],
                reason=decision["reason"],
                frames=len(ids),
                frames_needed=decision.get("frames_needed"),
                guard_set={"data_root": str(root.resolve()), "split": split},
                created=created,
                criteria={n: _stored(r) for n, r in decision["criteria"].items()},
                matched=matched,
                rule=rule,
                look=decision["look"],
                alpha_look=decision["alpha_look"],
                looks=[
                    *looks,
                    {"frames": len(ids), "verdict": decision["verdict"], "created": created},
                ],
            )
        report["guard_file"] = str(verdict_file.write_guard(export_dir, model, rule, verdicts))
    print_report(report, speed["jax:f32"])
    return report


def _rule(margin, ap_margin, alpha, tol, min_score, thresholds, resamples, fp_cap) -> dict:
    """The rule a verdict was decided under (stored with it; see
    :func:`gac_jax.guard.verdict_file.rule_mismatch`)."""
    from gac_jax.guard.criteria import QUANTILES
    from gac_jax.guard.verdict_file import RULE_VERSION

    return {
        "version": RULE_VERSION,
        "text": "paired recall at each score threshold, false positives per frame above each, "
        "heading and centre error quantile shifts, and every AP entry vs jax float32 "
        "(gac_jax.guard.detector_rule); frames as the unit",
        "margin_points": margin,
        "ap_margin_points": ap_margin,
        "alpha": alpha,
        "alpha_spending": "alpha / 2^k at look k",
        "interval": "tests by betting on the per-frame changes (gac_jax.guard."
        "frame_betting): a frame changes at most its objects, no frame has more than the "
        "largest guard frame, at most fp_cap false positives per frame (checked); AP: "
        "diff -+ z * paired frame-bootstrap se",
        "fp_cap": fp_cap,
        "heading_tolerance_deg": tol,
        "min_score": min_score,
        "score_thresholds": list(thresholds),
        "error_quantiles": list(QUANTILES),
        "bootstrap_resamples": resamples,
    }


def _stored(row: dict) -> dict:
    """A criterion as the verdict file keeps it."""
    keys = ("kind", "n", "ref_only", "cand_only", "diff", "bound", "over_cap", "se", "limit")
    keys += ("status",)
    return {k: row[k] for k in keys if k in row}


def print_report(report: dict, ref_ms) -> None:
    """The AP table, each candidate's criteria and matched differences, the verdicts."""
    ref = report["reference_ap"]
    cands = report["candidates"]
    print(f"\nCar AP|R40 on {report['frames']} frames (difference to jax f32)")
    print(f"{'entry':26s}{'jax:f32':>9s}" + "".join(f"{k:>22s}" for k in cands))
    for entry, v in ref.items():
        cells = "".join(
            f"{c['ap'][entry]:>14.2f} ({c['ap'][entry] - v:+5.2f})" for c in cands.values()
        )
        print(f"{entry.removeprefix('Car '):26s}{v:9.2f}{cells}")
    for key, c in cands.items():
        d, m = c["decision"], c["matched"]
        rows = d["criteria"]
        beyond = {n: r for n, r in rows.items() if r["status"] == "beyond"}
        open_ = [n for n, r in rows.items() if r["status"] == "undecided"]
        shown = beyond | {n: rows[n] for n in open_[:SHOWN_UNDECIDED]}
        within = sum(r["status"] == "within" for r in rows.values())
        print(
            f"\n{key}: look {d['look']} (alpha {d['alpha_look']:.4g}); "
            f"{within} of {len(rows)} criteria within their margins"
            + ("; the others (lost / gained of n, or AP +- bootstrap se; points):" if shown else "")
        )
        for name, r in shown.items():
            iv = r["within_interval"] if r["status"] != "beyond" else r["beyond_interval"]
            what = (
                f"AP {r['diff']:+6.2f} +- {r['se']:.2f}"
                if r["kind"] == "ap"
                else f"{r['ref_only']:4d} / {r['cand_only']:<4d} of {r['n']:6d}  {r['diff']:+6.2f}"
            )
            print(f"  {name:34s} {what} [{iv[0]:+6.2f}, {iv[1]:+6.2f}]  {r['status']}")
        if len(open_) > SHOWN_UNDECIDED:
            print(f"  ... and {len(open_) - SHOWN_UNDECIDED} more undecided (all in --json)")
        print(
            f"  matched detections {m['matched']} of {m['reference_detections']} "
            f"({m['detections']} candidate); |diff| median / p95 / max: "
            + ", ".join(
                f"{name} {m[k]['median']:.3g} / {m[k]['p95']:.3g} / {m[k]['max']:.3g}"
                for name, k in (
                    ("score", "score"),
                    ("centre m", "centre_m"),
                    ("dims m", "dimensions_m"),
                    ("heading deg", "heading_deg"),
                )
            )
            + f"; heading flips > 90 deg: {m['heading_flips']} "
            f"({100 * m['heading_flip_share']:.2f} %)"
        )
    print(f"\nverdicts (gac_jax.guard.detector_rule), written to {report['guard_file']}:")
    for key, c in cands.items():
        ms = f", model {c['model_ms']:.1f} ms/frame" if c["model_ms"] else ""
        print(f"  {key:24s} {c['decision']['verdict']:9s} {c['decision']['reason']}{ms}")
    if ref_ms:
        print(f"  (jax:f32 model {ref_ms:.1f} ms/frame)")


def main(argv: Sequence[str] | None = None) -> int:
    """Exit code 0 (verdicts written), 2 (bad input or workdir in use), 1 (disk failure)."""
    from gac_jax.cpu_backend import apply_default_xla_flags

    apply_default_xla_flags()  # before JAX starts its backend
    import json

    from gac_jax.data.files import KittiFormatError, atomic_write
    from gac_jax.data.io_errors import error_line, exit_code
    from gac_jax.training.workdir_lock import WorkdirBusyError

    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        parse_candidates(args.candidates)
    except ValueError as e:
        parser.error(str(e))
    try:
        report = guard_workdir(args)
        if args.json:
            with atomic_write(args.json) as f:
                json.dump(report, f, indent=2, default=str)
    except (KittiFormatError, WorkdirBusyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {error_line(e, args.workdir)}", file=sys.stderr)
        return exit_code(e)
    return 0


if __name__ == "__main__":
    sys.exit(main())
