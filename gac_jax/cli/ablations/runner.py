"""The ablation runner: trains each row of an ablation over several seeds, writes docs/ablations.md.

Run from the repository root (it starts ``train.py`` and ``evaluate.py`` of the checkout)::

    # detection, the six rows of the paper's Table 3, three seeds each
    python -m gac_jax.cli.ablations --rows baseline,nofilter,ohem,conv,disparity,deformable \\
        --seeds 0,1,2 --out workdirs/ablations
    # depth: Base U-Net vs GAC U-Net
    python -m gac_jax.cli.ablations --task depth --rows base,gac --seeds 0,1 \\
        --out workdirs/ablations
    # the report alone, from whatever exists
    python -m gac_jax.cli.ablations --report-only --out workdirs/ablations
    # multi-rig data: GAC with the frames' planes vs the fixed 1.65 m plane vs a plain conv,
    # also on the held-out rigs, as its own section of the report
    python -m gac_jax.cli.ablations --rows baseline,conv,fixedplane --seeds 0,1,2 \\
        --config configs/detect3d_default.py:multirig --eval-splits val_heldout \\
        --section multirig --out workdirs/ablations_multirig
    # the same for depth: Base U-Net vs GAC U-Net with the frames' planes vs the fixed plane
    python -m gac_jax.cli.ablations --task depth --rows base,gac,fixedplane --seeds 0,1 \\
        --config configs/depth_default.py:multirig --eval-splits val_heldout \\
        --section multirig --out workdirs/ablations_multirig

One workdir per (row, seed): ``OUT/<task>/<row>/seed_<s>``, trained by ``train.py --task T
--config CONFIG:<variant> --workdir W seed=<s> [overrides]`` in a child process (its output
goes to ``W/train.log`` and to this terminal). ``seed`` sets the model init, the dropout keys
and the training-data order (the generated dataset itself is fixed by
``data.synthetic.seed``). A run the runner saw finish (exit 0) gets ``W/ablation_run.json``
and is skipped afterwards (``--eval-splits``: each finished run is then evaluated once on
those splits by ``evaluate.py --workdir W --split S --json W/ablation_eval/S.json``); any
other workdir is handed to ``train.py`` again, which resumes
from its last checkpoint (and redoes only the unwritten result files of an interrupted final
evaluation). ``OUT/plan.json`` records each task's config, overrides, rows and seeds: a later
call with another config or other overrides for the same task is refused, so one table never
mixes two set-ups. The report (:mod:`gac_jax.cli.ablations.report`) reads only what the
trainer wrote
and lists unfinished seeds as such.

Rows: detection ``baseline`` (the GAC model), ``nofilter``, ``ohem``, ``conv``, ``disparity``,
``deformable`` (variants of ``configs/detect3d_default.py``, see ``configs/detect3d_kitti.py``);
depth ``base`` (``configs/depth_default.py:base``) and ``gac`` (the default); ``fixedplane``
(either task; not a paper row: the GAC model with the frames' plane files ignored).
``--section NAME`` writes the tables of this ``--out`` as a named block of the report that
later calls for other ``--out`` folders (and the paper's tables) keep. Exit status: 0 when
every requested run finished, 1 if one failed (the others still ran), 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from gac_jax.cli.ablations.report import (
    DONE_MARKER,
    FAILED_MARKER,
    PLAN,
    REPO,
    TASKS,
    compose_report,
    eval_file,
    last_train_step,
    read_plan,
    run_command,
    run_dir,
)
from gac_jax.cpu_backend import cpu_model
from gac_jax.data.files import atomic_write

DEFAULT_CONFIGS = {"detect3d": "configs/detect3d_default.py", "depth": "configs/depth_default.py"}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--task", choices=sorted(TASKS), default="detect3d")
    p.add_argument("--rows", help="comma-separated rows (default: all rows of the task)")
    p.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    p.add_argument("--out", required=True, help="folder of the run workdirs and plan.json")
    p.add_argument("--config", help="config file[:variant] (default: the task's default config)")
    p.add_argument("--report", default=str(REPO / "docs" / "ablations.md"), help="markdown out")
    p.add_argument("--report-only", action="store_true", help="write the report, train nothing")
    p.add_argument(
        "--eval-splits",
        default="",
        help="comma-separated extra splits every finished run is evaluated on "
        "(evaluate.py --workdir W --split S), e.g. val_heldout of :multirig",
    )
    p.add_argument(
        "--section",
        help="write this --out's tables as the named section of the report (kept apart from "
        "the paper's tables and from other sections), e.g. multirig",
    )
    p.add_argument("--title", help="heading of the task's tables (default: the paper's table)")
    p.add_argument("overrides", nargs="*", help="config overrides for every run, key.sub=value")
    return p.parse_args(argv)


def config_spec(config: str, variant: str) -> str:
    """``FILE[:a,b]`` plus a row variant -> ``FILE:a,b,variant`` (a Windows-free split)."""
    path, _, own = config.partition(":")
    parts = [v for v in (*own.split(","), variant) if v]
    return f"{path}:{','.join(parts)}" if parts else path


def update_plan(out: Path, task: str, entry: dict) -> dict:
    """Adds the requested rows/seeds to ``OUT/plan.json``; refuses a different set-up."""
    path = out / PLAN
    plan = json.loads(path.read_text()) if path.exists() else {}
    old = plan.get(task)
    if old is not None:
        for key in ("config", "overrides", "section"):
            if old.get(key) != entry.get(key):
                print(
                    f"error: {path} holds {task} runs with {key}={old[key]!r}, not "
                    f"{entry[key]!r}; use another --out to run a different set-up",
                    file=sys.stderr,
                )
                raise SystemExit(2)
        splits = old.get("eval_splits", [])
        entry = dict(
            old,
            rows=old["rows"] + [r for r in entry["rows"] if r not in old["rows"]],
            seeds=sorted(set(old["seeds"]) | set(entry["seeds"])),
            eval_splits=splits + [s for s in entry["eval_splits"] if s not in splits],
            title=entry.get("title") or old.get("title"),
        )
    entry["command"] = run_command(task, entry, out)
    plan[task] = entry
    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as f:
        json.dump(plan, f, indent=2)
    return plan


def run_one(task: str, spec: str, workdir: Path, seed: int, overrides: list[str]) -> int:
    """Trains (or resumes) one workdir in a child ``train.py``; returns its exit status.

    Exit 0 with a final ``metrics.json`` -> ``ablation_run.json`` (final step, wall time of
    all attempts, CPU); anything else -> ``ablation_failed.json`` (the next call resumes).
    """
    cmd = [sys.executable, "train.py", "--task", task, "--config", spec, "--workdir", str(workdir)]
    cmd += [f"seed={seed}", *overrides]
    workdir.mkdir(parents=True, exist_ok=True)
    (workdir / FAILED_MARKER).unlink(missing_ok=True)
    print(f"[ablation] {shlex.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    code = None
    try:
        with open(workdir / "train.log", "a") as log:
            log.write(f"\n[ablation] {time.strftime('%Y-%m-%d %H:%M:%S')} {shlex.join(cmd)}\n")
            child = subprocess.Popen(
                cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
            )
            for line in child.stdout:
                sys.stdout.write(line)
                log.write(line)
            code = child.wait()
    finally:  # also on Ctrl-C (the child got the SIGINT too): keep the attempt's wall time
        wall = time.perf_counter() - t0 + _previous_wall(workdir)
        with atomic_write(workdir / "wall.json") as f:
            json.dump({"wall_s": round(wall, 1)}, f)
    status = {"returncode": code, "wall_s": round(wall, 1), "command": cmd}
    steps = [int(p.parent.name[5:]) for p in workdir.glob("results/step_*/metrics.json")]
    if code == 0 and steps:
        status |= {
            "final_step": max(steps),
            "machine": f"{cpu_model()}, {os.cpu_count()} cores",
            "finished": time.strftime("%Y-%m-%d %H:%M:%S"),
        }
        with atomic_write(workdir / DONE_MARKER) as f:
            json.dump(status, f, indent=2)
        return 0
    if code == 0:
        code = status["returncode"] = 1
        status["error"] = "train.py exited 0 but wrote no results/step_*/metrics.json"
    status["last_step"] = last_train_step(workdir)
    with atomic_write(workdir / FAILED_MARKER) as f:
        json.dump(status, f, indent=2)
    return code


def evaluate_split(task: str, workdir: Path, split: str) -> int:
    """Evaluates a finished run on ``split`` (``evaluate.py --workdir``) into ``eval_file``;
    returns the exit status. Done once: an existing file is kept."""
    target = eval_file(workdir, split)
    if target.exists():
        return 0
    cmd = [sys.executable, "evaluate.py", "--task", task, "--workdir", str(workdir)]
    cmd += ["--split", split, "--json", str(target)]
    print(f"[ablation] {shlex.join(cmd)}", flush=True)
    target.parent.mkdir(parents=True, exist_ok=True)
    with open(workdir / f"eval_{split}.log", "a") as log:
        log.write(f"\n[ablation] {time.strftime('%Y-%m-%d %H:%M:%S')} {shlex.join(cmd)}\n")
        log.flush()
        code = subprocess.run(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT).returncode
    if code != 0:
        print(f"[ablation] {shlex.join(cmd)}: exit {code} (see {log.name})", flush=True)
    return code


def _previous_wall(workdir: Path) -> float:
    """Wall time of the earlier attempts on ``workdir`` (``wall.json``)."""
    path = workdir / "wall.json"
    return json.loads(path.read_text())["wall_s"] if path.exists() else 0.0


def main(argv=None) -> int:
    args = parse_args(argv)
    if not (REPO / "train.py").is_file():
        print(
            f"error: {REPO / 'train.py'}: not found; the ablation runner trains with the "
            "repository's train.py and evaluate.py, so it runs from a checkout of gac-jax",
            file=sys.stderr,
        )
        return 2
    task = TASKS[args.task]
    rows = args.rows.split(",") if args.rows else list(task.rows)
    unknown = [r for r in rows if r not in task.variants]
    if unknown:
        print(
            f"error: unknown {args.task} rows {unknown}; known: {list(task.variants)}",
            file=sys.stderr,
        )
        return 2
    try:
        seeds = [int(s) for s in args.seeds.split(",")]
    except ValueError:
        print(
            f"error: --seeds must be comma-separated integers, got {args.seeds!r}", file=sys.stderr
        )
        return 2
    out = Path(args.out).resolve()
    splits = [s for s in args.eval_splits.split(",") if s]
    config = args.config or DEFAULT_CONFIGS[args.task]
    failed = []
    if not args.report_only:
        entry = {"config": config, "overrides": list(args.overrides), "rows": rows}
        entry |= {"seeds": seeds, "eval_splits": splits, "section": args.section}
        entry |= {"title": args.title}
        update_plan(out, args.task, entry)
        # Seed-major: every row gets its first seed before any row gets a second one.
        todo = [(seed, row) for seed in seeds for row in rows]
        for seed, row in todo:
            workdir = run_dir(out, args.task, row, seed)
            if (workdir / DONE_MARKER).exists():
                print(f"[ablation] {args.task} {row} seed {seed}: finished, skipped")
                code = 0
            else:
                spec = config_spec(config, task.variants[row])
                code = run_one(args.task, spec, workdir, seed, args.overrides)
            for split in splits if code == 0 else ():
                if evaluate_split(args.task, workdir, split) != 0:
                    failed.append(f"{row} seed {seed} on {split}")
            if code != 0:
                failed.append(f"{row} seed {seed} (exit {code})")
                print(f"[ablation] {args.task} {row} seed {seed}: exit {code}", flush=True)
                if code == 75:  # stopped on SIGTERM after a checkpoint: stop here, rerun resumes
                    break
    plan_sections = [e.get("section") for e in read_plan(out).values() if e.get("section")]
    section = args.section or next(iter(plan_sections), None)
    report = Path(args.report)
    old = report.read_text() if report.exists() else ""
    with atomic_write(report) as f:
        f.write(compose_report(old, out, section))
    print(f"[ablation] wrote {report}")
    if failed:
        print("[ablation] not finished: " + ", ".join(failed), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
