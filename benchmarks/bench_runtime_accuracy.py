"""Accuracy guard of the deployment runtimes: a trained model under every runtime/precision.

Evaluates a trained detection workdir (Car AP|R40, every entry) and/or a trained depth
workdir (SILog, absRel) on the run's val split with ``jax f32`` (the reference), ``jax bf16``,
``onnxruntime f32``, ``openvino f32``, ``openvino bf16``, ``openvino int8`` (NNCF, calibrated
on ``--int8-frames`` training frames) and, per ``--keep-float REGEX[,REGEX...]``, the mixed
int8 network with those layers in float32 (those that can run here; ``--combos`` picks), through
the same code as ``evaluate.py --runtime ... --precision ... [--int8-keep-float ...]``, and
prints each metric, its difference to ``jax f32`` and the verdict of the rule in
docs/inference.md: a precision is recommended only if every Car AP|R40 entry stays within 0.5
AP (depth: SILog within 0.2) of float32.

``--matched-workdir W`` (optionally ``--checkpoint C --config F`` for converted weights, and
``--data``/``--matched-split`` for the frames, default the real frames in ``tests/data/kitti``)
compares *detections* instead of AP: each runtime's detections are matched to jax float32's
(same class, 2D IoU >= 0.5, greedy by score) and the matched share, the largest score and
3D-location differences are reported (for models whose val split is not here, e.g. the
converted authors' model on real frames).

    python benchmarks/bench_runtime_accuracy.py [--detect3d-workdir W] [--depth-workdir W]
        [--matched-workdir W [--checkpoint C --config F] [--data D] [--matched-split S]]
        [--combos jax:f32,openvino:int8,...] [--keep-float REGEX[,REGEX]] [--int8-frames N]
        [--split S] [--guard-data DIR] [--folds K] [--bootstrap N] [--results-dir DIR]
        [--threads N] [--json OUT]

A detector guard's difference is only as good as its frame count: ``--bootstrap N`` (default
200) gives every entry's paired-frame-bootstrap standard error and decides the ~95 % verdict
(within / beyond / undecided; :mod:`gac_jax.guard.ap_resampling`); ``--folds K`` adds
the spread a guard of ``1/K`` of the frames would see. ``--guard-data DIR`` evaluates on a
larger generated set.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.data.files import KittiFormatError  # noqa: E402
from gac_jax.deploy.int8 import DEFAULT_FRAMES, Int8Settings  # noqa: E402
from gac_jax.deploy.runtimes import (  # noqa: E402
    RUNTIME_PRECISIONS,
    RuntimeUnavailableError,
    check_runtime,
)
from gac_jax.guard.ap_resampling import (  # noqa: E402
    bootstrap_differences,
    car_ap40,
    fold_differences,
)

REPO = Path(__file__).resolve().parents[1]
REAL_FRAMES = REPO / "tests" / "data" / "kitti" / "object"  # split "labeled"
AP_TOLERANCE = 0.5  # AP points, every Car AP|R40 entry
SILOG_TOLERANCE = 0.2


@dataclasses.dataclass(frozen=True)
class Combo:
    """One runtime/precision of the guard; ``int8``: the calibration (int8 only)."""

    runtime: str
    precision: str
    int8: Int8Settings | None = None

    @property
    def label(self) -> str:
        keep = self.int8.keep_float if self.int8 else ()
        seed = f" seed{self.int8.seed}" if self.int8 and self.int8.seed else ""
        return f"{self.runtime} {self.precision}{seed}" + (
            f" f32[{','.join(keep)}]" if keep else ""
        )

    @property
    def slug(self) -> str:
        """A folder name for the label (long scopes shortened to a hash)."""
        import hashlib

        slug = "".join(c if c.isalnum() else "_" for c in self.label)
        if len(slug) > 60:
            slug = slug[:40] + "_" + hashlib.sha1(self.label.encode()).hexdigest()[:10]
        return slug


def available(args) -> list[Combo]:
    """The combos of ``--combos`` (default all) that run here, int8 ones per ``--keep-float``."""
    wanted = RUNTIME_PRECISIONS
    if args.combos:
        wanted = [tuple(c.split(":")) for c in args.combos.split(",")]
    combos = []
    for runtime, precision in wanted:
        try:
            check_runtime(runtime, precision)
        except RuntimeUnavailableError as e:
            print(f"skip {runtime} {precision}: {e}")
            continue
        if precision != "int8":
            combos.append(Combo(runtime, precision))
            continue
        for keep in ["", *args.keep_float]:
            scope = tuple(p for p in keep.split(",") if p)
            for seed in args.int8_seeds:
                settings = Int8Settings(args.int8_frames, seed, scope)
                combos.append(Combo(runtime, precision, settings))
    if not combos or combos[0] != Combo("jax", "f32"):
        combos.insert(0, Combo("jax", "f32"))  # the reference
    return combos


@contextlib.contextmanager
def skipped_on_error():
    """Yields a list that gets the error when the block raises KittiFormatError (printed)."""
    errors: list[str] = []
    try:
        yield errors
    except KittiFormatError as e:
        errors.append(str(e))
        print(f"  skip: {e}", file=sys.stderr)


def run_detector(workdir, combo: Combo, tmp: Path, split, threads, where=None) -> dict:
    """``evaluate.py --task detect3d`` model mode under ``combo`` (results in ``tmp_<combo>``,
    the export in ``tmp_export``), quietly; returns its summary."""
    from gac_jax.cli.evaluate_detector import evaluate_detector_workdir

    with contextlib.redirect_stdout(io.StringIO()):
        return evaluate_detector_workdir(
            workdir,
            **(where or {}),
            split=split,
            threads=threads,
            out_dir=Path(f"{tmp}_{combo.slug}"),
            runtime=combo.runtime,
            precision=combo.precision,
            export_dir=Path(f"{tmp}_export"),
            int8=combo.int8,
        )


def guard_detector(
    workdir: str,
    split,
    threads,
    tmp: Path,
    combos: list[Combo],
    data=None,
    k: int = 0,
    boots: int = 0,
) -> dict:
    """Every combo on the run's val split (or ``data``'s ``split``); ``k`` >= 2 folds add
    each entry's fold spread, ``boots`` >= 2 bootstrap resamples its standard error, each
    with the ~95 % verdict of :mod:`gac_jax.guard.ap_resampling`."""
    runs, result_dirs = {}, {}
    where = {"data_root": data} if data else None
    for combo in combos:
        label = combo.label
        print(f"\n=== detector, {label} ===", flush=True)
        with skipped_on_error() as skipped:  # e.g. a --keep-float scope this net lacks
            summary = run_detector(workdir, combo, tmp / "det", split, threads, where)
        if skipped:
            continue
        runs[label] = {"ap": car_ap40(summary["metrics"]), "speed": summary["speed"]}
        result_dirs[label] = Path(summary["result_dir"])
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
    out = {"runs": runs, "verdicts": verdicts}
    if len(result_dirs) > 1 and (k >= 2 or boots >= 2):
        out.update(detector_spread(result_dirs, k, boots))
    return out


def detector_spread(result_dirs: dict[str, Path], k: int, boots: int) -> dict:
    """:func:`~gac_jax.guard.ap_resampling.fold_differences` (``k`` >= 2) and
    :func:`~gac_jax.guard.ap_resampling.bootstrap_differences` (``boots`` >= 2) of every
    combo against jax f32 (the frames and labels of the evaluation, from the result folder's
    ``run.json``)."""
    from gac_jax.data.kitti import KittiObjectLayout, read_split

    ref = result_dirs["jax f32"]
    settings = json.loads((ref.parent / "run.json").read_text())
    layout = KittiObjectLayout(settings["data_root"])
    ids = read_split(layout.split_file(settings["split"]))
    labels = layout.root / "training" / "label_2"
    others = {label: d for label, d in result_dirs.items() if label != "jax f32"}
    out = {}
    if k >= 2:
        res = out["folds"] = fold_differences(labels, ref, others, ids, k, AP_TOLERANCE)
        print(
            f"\n{k} disjoint folds of {min(res['fold_frames'])}-{max(res['fold_frames'])} of "
            f"the {res['frames']} frames (fold std: what a guard of one fold sees):"
        )
        print(f"{'runtime':28s} {'verdict':>10s}  deciding entry: diff, fold std, se; largest std")
        for label, r in res["runs"].items():
            e = r["entries"][r["worst_entry"]]
            spread = max(v["fold_std"] for v in r["entries"].values())
            print(
                f"{label:28s} {r['verdict']:>10s}  {r['worst_entry']}: {e['diff']:+.2f}, "
                f"{e['fold_std']:.2f}, {e['se']:.2f}; {spread:.2f}"
            )
    if boots >= 2:
        res = out["bootstrap"] = bootstrap_differences(
            labels, ref, others, ids, boots, AP_TOLERANCE
        )
        print(
            f"\npaired frame bootstrap, {boots} resamples of the {res['frames']} frames; "
            f"verdict at 2 standard errors (rule: every entry within {AP_TOLERANCE} AP):"
        )
        print(f"{'runtime':28s} {'verdict':>10s}  deciding entry: diff, se, median, 95 % interval")
        for label, r in res["runs"].items():
            e = r["entries"][r["worst_entry"]]
            lo, hi = e["ci95"]
            print(
                f"{label:28s} {r['verdict']:>10s}  {r['worst_entry']}: {e['diff']:+.2f}, "
                f"{e['se']:.2f}, {e['median']:+.2f}, [{lo:+.2f}, {hi:+.2f}]"
            )
    return out


def guard_depth(workdir: str, split, tmp: Path, combos: list[Combo]) -> dict:
    from gac_jax.cli.evaluate_depth import evaluate_workdir

    runs = {}
    for combo in combos:
        label = combo.label
        print(f"\n=== depth, {label} ===", flush=True)
        with contextlib.redirect_stdout(io.StringIO()), skipped_on_error() as skipped:
            result = evaluate_workdir(
                workdir,
                split=split,
                out=tmp / f"depth_{combo.slug}",
                runtime=combo.runtime,
                precision=combo.precision,
                export_dir=tmp / "depth_export",
                int8=combo.int8,
            )
        if skipped:
            continue
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


def match_detections(reference: Path, other: Path) -> dict:
    """Detections of ``other`` matched to ``reference``'s (result folders of the same frames;
    :func:`gac_jax.guard.detector_rule.match_detections`: same class, 2D IoU >= 0.5,
    greedily in the reference's score order)."""
    import numpy as np

    from gac_jax.data.kitti import read_label
    from gac_jax.guard.detector_rule import match_detections as match

    n_ref = n_other = matched = 0
    score_d, loc_d = [], []
    for path in sorted(reference.glob("*.txt")):
        a, b = read_label(path, True), read_label(other / path.name, True)
        n_ref, n_other = n_ref + len(a), n_other + len(b)
        i, j = match(a, b)
        matched += len(i)
        score_d += list(np.abs(a.score[i] - b.score[j]))
        loc_d += list(np.linalg.norm(a.location[i] - b.location[j], axis=-1))
    return {
        "reference_detections": n_ref,
        "detections": n_other,
        "matched": matched,
        "matched_share": matched / max(n_ref, 1),
        "max_score_diff": float(max(score_d, default=0.0)),
        "median_score_diff": float(np.median(score_d)) if score_d else 0.0,
        "max_location_diff_m": float(max(loc_d, default=0.0)),
        "median_location_diff_m": float(np.median(loc_d)) if loc_d else 0.0,
    }


def guard_matched(args, tmp: Path, combos: list[Combo]) -> dict:
    """Every combo on ``--data``'s ``--matched-split``, detections matched to jax f32's."""
    dirs = {}
    for combo in combos:
        print(f"\n=== matched detections, {combo.label} ===", flush=True)
        where = {"config_spec": args.config, "checkpoint": args.checkpoint}
        where |= {"overrides": args.matched_overrides, "data_root": args.data}
        summary = run_detector(
            args.matched_workdir, combo, tmp / "matched", args.matched_split, args.threads, where
        )
        dirs[combo.label] = Path(summary["result_dir"])
    ref = dirs["jax f32"]
    out = {}
    print(
        f"\n{'runtime':28s} {'dets':>5s} {'matched':>8s} {'max|dscore|':>11s} {'max|dxyz| m':>11s}"
    )
    for label, d in dirs.items():
        m = out[label] = match_detections(ref, d)
        print(
            f"{label:28s} {m['detections']:5d} {m['matched']:4d}/{m['reference_detections']:<4d}"
            f"{m['max_score_diff']:11.3f} {m['max_location_diff_m']:11.3f}"
        )
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detect3d-workdir", help="a trained detection workdir")
    parser.add_argument("--depth-workdir", help="a trained depth workdir")
    parser.add_argument("--matched-workdir", help="detections matched to jax f32's (see above)")
    parser.add_argument("--checkpoint", help="--matched-workdir: converted weights")
    parser.add_argument("--config", help="--matched-workdir: config of --checkpoint")
    parser.add_argument("--data", default=str(REAL_FRAMES), help="--matched-workdir: frames")
    parser.add_argument("--matched-split", default="labeled", help="--matched-workdir: split")
    parser.add_argument("--matched-overrides", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--combos", help="runtime:precision,... (default: all that run here)")
    parser.add_argument(
        "--keep-float",
        action="append",
        default=[],
        metavar="REGEX[,REGEX]",
        help="an int8 row with these layers kept in float32 (repeatable)",
    )
    parser.add_argument("--int8-frames", type=int, default=DEFAULT_FRAMES)
    parser.add_argument(
        "--int8-seeds",
        type=lambda t: [int(x) for x in t.split(",")],
        default=[0],
        metavar="S[,S]",
        help="an int8 row per calibration seed (the frames drawn; default 0)",
    )
    parser.add_argument("--split", help="default: each run's val split")
    parser.add_argument(
        "--guard-data",
        metavar="DIR",
        help="detector: evaluate on this KITTI-format root (e.g. a larger generated set, "
        "python -m gac_jax.data.synthetic --out DIR ...) instead of the run's own data; int8 "
        "is then calibrated on DIR's train split",
    )
    parser.add_argument(
        "--folds",
        type=int,
        default=5,
        help="detector: disjoint frame folds for the fold spread and the ~95%% verdict "
        "(gac_jax.guard.ap_resampling; default 5, 0 = off)",
    )
    parser.add_argument(
        "--bootstrap",
        type=int,
        default=200,
        metavar="N",
        help="detector: paired frame bootstrap resamples for the standard error that decides "
        "the ~95%% verdict (default 200, 0 = off)",
    )
    parser.add_argument(
        "--results-dir",
        type=Path,
        help="keep the exports and result folders here (default: a temporary folder)",
    )
    parser.add_argument("--threads", type=int)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if not (args.detect3d_workdir or args.depth_workdir or args.matched_workdir):
        parser.error("give --detect3d-workdir, --depth-workdir and/or --matched-workdir")
    print(one_line(describe_machine("numpy", "jax", "onnxruntime", "openvino", "nncf")))
    combos = available(args)
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench_runtime_accuracy_") as tmp:
        if args.results_dir:
            args.results_dir.mkdir(parents=True, exist_ok=True)
            tmp = args.results_dir
        if args.detect3d_workdir:
            out["detect3d"] = guard_detector(
                args.detect3d_workdir,
                args.split,
                args.threads,
                Path(tmp),
                combos,
                args.guard_data,
                args.folds,
                args.bootstrap,
            )
        if args.depth_workdir:
            out["depth"] = guard_depth(args.depth_workdir, args.split, Path(tmp), combos)
        if args.matched_workdir:
            out["matched"] = guard_matched(args, Path(tmp), combos)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
