"""Reads the runs of the ablation runner (``python -m gac_jax.cli.ablations``) and writes
docs/ablations.md.

Pure file reading and arithmetic (no JAX): every number in the report comes from a metrics
file the trainer wrote (``WORKDIR/results/step_N/metrics.json``, N the run's last step) of
a run the runner saw finish (``WORKDIR/ablation_run.json``). Runs that are missing,
interrupted or failed are listed as such and left out of the statistics. The report names no
folder of the machine that ran it: a run folder inside the repository is written relative to
it, one outside as ``workdirs/<its name>`` (:func:`shown`), so the command it prints reruns
the section from any checkout.
"""

from __future__ import annotations

import json
import math
import re
import shlex
import statistics
from dataclasses import dataclass, field
from pathlib import Path

DONE_MARKER = "ablation_run.json"
FAILED_MARKER = "ablation_failed.json"
PLAN = "plan.json"
REPO = Path(__file__).resolve().parents[3]
RUNNER = "python -m gac_jax.cli.ablations"

from gac_jax.cli.ablations.rows import (  # noqa: E402  (after the constants it shares)
    PAPER_DEPTH,
    PAPER_DEPTH_NAMES,
    PAPER_TABLE3,
    PAPER_TABLE3_NAMES,
    VARIANTS_TEXT,
    paper_table3_from_tex,
)

__all__ = ["PAPER_TABLE3", "paper_table3_from_tex", "render", "compose_report"]


@dataclass(frozen=True)
class Task:
    """What the report shows for one task: metric name -> path into ``metrics.json``.

    ``rows``: the default rows (the paper's); ``variants``: every row the runner knows
    (row -> config variant), the defaults and the extra ones (``fixedplane``).
    """

    name: str
    rows: tuple[str, ...]
    variants: dict[str, str]  # row -> config variant
    metrics: dict[str, tuple[str, ...]]
    higher_is_better: bool
    paper: dict[str, dict]
    paper_names: dict[str, str]


# Car AP|R40, moderate (index 1); "0.70" / "0.50" are the strict / loose settings.
DETECTION = Task(
    name="detect3d",
    rows=("baseline", "nofilter", "ohem", "conv", "disparity", "deformable"),
    variants={r: r for r in PAPER_TABLE3} | {"fixedplane": "fixedplane"},
    metrics={
        "3D@0.7": ("ap40", "Car", "0.70", "3d"),
        "3D@0.5": ("ap40", "Car", "0.50", "3d"),
        "BEV@0.5": ("ap40", "Car", "0.50", "bev"),
        "2D@0.7": ("ap40", "Car", "0.70", "bbox"),
    },
    higher_is_better=True,
    paper={r: {k: v[1] for k, v in m.items()} for r, m in PAPER_TABLE3.items()},
    paper_names=PAPER_TABLE3_NAMES,
)
DEPTH = Task(
    name="depth",
    rows=("base", "gac"),
    variants={"base": "base", "gac": "", "fixedplane": "fixedplane"},
    metrics={"SILog": ("silog",), "absRel %": ("abs_rel",), "iRMSE": ("irmse",)},
    higher_is_better=False,
    paper={
        r: {"SILog": v["silog"], "absRel %": v["abs_rel"], "iRMSE": v["irmse"]}
        for r, v in PAPER_DEPTH.items()
    },  # fmt: skip
    paper_names=PAPER_DEPTH_NAMES,
)
TASKS = {"detect3d": DETECTION, "depth": DEPTH}
TITLES = {"detect3d": "Detection (paper Table 3)", "depth": "Depth (Base U-Net vs GAC U-Net)"}


def run_dir(out: Path, task: str, row: str, seed: int) -> Path:
    return Path(out) / task / row / f"seed_{seed}"


@dataclass
class RunResult:
    """One (row, seed): ``status`` is 'done', 'interrupted', 'failed' or 'not started'."""

    seed: int
    status: str
    values: dict[str, float] = field(default_factory=dict)
    step: int | None = None
    note: str = ""


def last_train_step(workdir: Path) -> int | None:
    """Last step the trainer logged in ``metrics.jsonl`` (None without one)."""
    path = workdir / "metrics.jsonl"
    if not path.exists():
        return None
    step = None
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue  # a torn last line of a killed run
        if record.get("kind") == "train":
            step = record["step"]
    return step


def _dig(tree, keys: tuple[str, ...]):
    for key in keys:
        tree = tree[key]
    return tree


def eval_file(workdir: Path, split: str) -> Path:
    """Where the runner keeps a finished run's evaluation on an extra split
    (``evaluate.py --workdir W --split S --json``: the metrics dict itself)."""
    return Path(workdir) / "ablation_eval" / f"{split}.json"


def read_run(task: Task, workdir: Path, seed: int, split: str | None = None) -> RunResult:
    """The result of one run, from the files in its workdir (see the module docstring).

    ``split``: an extra split the runner evaluated the finished run on (``eval_file``),
    instead of the trainer's final evaluation on the config's val split.
    """
    done = workdir / DONE_MARKER
    if done.exists():
        marker = json.loads(done.read_text())
        step = int(marker["final_step"])
        if split is None:
            metrics_file = workdir / "results" / f"step_{step}" / "metrics.json"
        else:
            metrics_file = eval_file(workdir, split)
        if not metrics_file.exists():
            if split is not None:
                return RunResult(seed, "not evaluated", step=step, note=f"{split}: not yet")
            return RunResult(seed, "failed", step=step, note=f"{metrics_file} missing")
        metrics = json.loads(metrics_file.read_text())
        # The trainer's results and evaluate.py --task depth --json keep the metrics under
        # "metrics"; evaluate.py --task detect3d --json writes the metrics dict itself.
        if split is None or task.name == "depth":
            metrics = metrics["metrics"]
        values = {}
        for name, keys in task.metrics.items():
            value = _dig(metrics, keys)
            values[name] = float(value[1] if isinstance(value, list) else value)
        note = marker.get("machine", "")
        if marker.get("wall_s"):
            note = f"{marker['wall_s'] / 60:.0f} min, {note}".rstrip(", ")
        return RunResult(seed, "done", values, step, note)
    if (workdir / FAILED_MARKER).exists():
        code = json.loads((workdir / FAILED_MARKER).read_text())["returncode"]
        step = last_train_step(workdir)
        if code is not None and (code < 0 or code == 75):  # signal / SIGTERM stop: resumable
            note = f"killed by signal {-code}" if code < 0 else "stopped on SIGTERM (exit 75)"
            return RunResult(seed, "interrupted", step=step, note=note)
        return RunResult(seed, "failed", step=step, note=f"exit {code}")
    if workdir.exists():
        return RunResult(seed, "interrupted", step=last_train_step(workdir))
    return RunResult(seed, "not started")


@dataclass
class RowStats:
    row: str
    runs: list[RunResult]

    def values(self, metric: str) -> list[float]:
        return [r.values[metric] for r in self.runs if r.status == "done"]

    def summary(self, metric: str) -> dict | None:
        v = self.values(metric)
        if not v:
            return None
        return {
            "n": len(v),
            "mean": statistics.fmean(v),
            "std": statistics.stdev(v) if len(v) > 1 else math.nan,
            "min": min(v),
            "max": max(v),
        }


def collect(task: Task, out: Path, rows, seeds, split: str | None = None) -> list[RowStats]:
    return [
        RowStats(row, [read_run(task, run_dir(out, task.name, row, s), s, split) for s in seeds])
        for row in rows
    ]


def _cell(s: dict | None, requested: int) -> str:
    if s is None:
        return "no finished run"
    if s["n"] == 1:
        return f"{s['mean']:.2f} (1 of {requested} seeds, no spread)"
    text = f"{s['mean']:.2f} ± {s['std']:.2f} [{s['min']:.2f}, {s['max']:.2f}]"
    return text if s["n"] == requested else f"{text} ({s['n']} of {requested} seeds)"


def compare(task: Task, base: RowStats, other: RowStats, metric: str) -> str | None:
    """One clause: does ``other`` differ from ``base`` beyond the seed spread on ``metric``?

    "Beyond the spread" = both rows have at least 2 finished seeds and their [min, max]
    ranges over seeds do not overlap. Returns None when a row has fewer than 2 seeds.
    """
    a, b = base.summary(metric), other.summary(metric)
    if a is None or b is None or a["n"] < 2 or b["n"] < 2:
        return None
    diff = b["mean"] - a["mean"]
    exceeds = b["min"] > a["max"] or b["max"] < a["min"]
    if abs(diff) < 0.005:
        word = "equal means"
    else:
        better = diff > 0 if task.higher_is_better else diff < 0
        word = "better" if better else "worse"
    parts = [word, "beyond the seed spread" if exceeds else "within the seed spread"]
    paper_base = task.paper.get(base.row, {}).get(metric)
    paper_other = task.paper.get(other.row, {}).get(metric)
    if exceeds and paper_base is not None and paper_other is not None:
        paper_diff = paper_other - paper_base
        same = (paper_diff > 0) == (diff > 0)
        parts.append(f"paper {paper_diff:+.2f}, " + ("same sign" if same else "opposite sign"))
    return (
        f"{metric} {diff:+.2f} ({', '.join(parts[:2])}" + "".join(f"; {p}" for p in parts[2:]) + ")"
    )


def sentences(task: Task, stats: list[RowStats]) -> list[str]:
    by_row = {s.row: s for s in stats}
    base_row = task.rows[0]
    base = by_row.get(base_row)
    out = []
    if base is None:
        return [f"No {base_row} row was run, so no row is compared with it."]
    beyond, within, unknown = [], [], []
    for s in stats:
        if s.row == base_row:
            continue
        clauses = [compare(task, base, s, m) for m in task.metrics]
        if any(c is None for c in clauses):
            unknown.append(s.row)
            continue
        for clause in clauses:
            (beyond if "beyond the seed spread" in clause else within).append(f"`{s.row}` {clause}")
    if beyond:
        out.append(
            f"Differences from `{base_row}` beyond the seed spread (min-max ranges over seeds "
            "do not overlap): " + "; ".join(beyond) + "."
        )
    elif within:
        out.append(f"No difference from `{base_row}` exceeds the seed spread.")
    else:
        out.append(f"No row can be compared with `{base_row}` yet.")
    if within:
        out.append("Within the seed spread (not conclusive): " + "; ".join(within) + ".")
    if unknown:
        out.append(
            "Not compared (fewer than 2 finished seeds in the row or in "
            f"`{base_row}`): " + ", ".join(f"`{r}`" for r in unknown) + "."
        )
    return out


def task_section(task: Task, out: Path, plan: dict) -> str:
    """One task's section: its set-up, the tables on the config's val split and on every
    extra split of ``plan['eval_splits']``, and what differs beyond the seed spread."""
    rows, seeds = plan["rows"], plan["seeds"]
    lines = []
    lines.append(f"## {plan.get('title') or TITLES[task.name]}\n")
    extra = " ".join(plan.get("overrides", [])) or "none"
    lines.append(
        f"Config `{plan['config']}` (row = variant), overrides: `{extra}`; seeds "
        f"{', '.join(map(str, seeds))} (the seed sets the model init, dropout and the data "
        f"order; the generated dataset is the same for all). Runs in `{shown(out)}/{task.name}`:\n"
    )
    lines.append(f"```bash\n{run_command(task.name, plan, out)}\n```\n")
    for split in (None, *plan.get("eval_splits", [])):
        lines.extend(_split_tables(task, out, rows, seeds, split))
    return "\n".join(lines)


def _split_tables(task: Task, out: Path, rows, seeds, split: str | None) -> list[str]:
    stats = collect(task, out, rows, seeds, split)
    where = "the generated val split" if split is None else f"the generated split `{split}`"
    lines = [] if split is None else [f"### On split `{split}`\n"]
    if task.name == "detect3d":
        lines.append(
            f"Car AP|R40 in %, **moderate**, on {where}: mean ± sample std "
            "[min, max] over the finished seeds. Paper: KITTI val, Table 3 (3D only).\n"
        )
    else:
        lines.append(
            f"KITTI depth metrics on {where} (lower is better): mean ± sample "
            "std [min, max] over the finished seeds. Paper: KITTI depth val.\n"
        )
    names = list(task.metrics)
    paper_cols = [m for m in names if any(m in task.paper.get(r, {}) for r in rows)]
    header = ["row", *[f"paper {m}" for m in paper_cols], *names, "seeds done"]
    lines.append("| " + " | ".join(header) + " |")
    lines.append("|" + "---|" * len(header))
    for s in stats:
        paper = [
            f"{task.paper[s.row][m]:.2f}" if m in task.paper.get(s.row, {}) else "-"
            for m in paper_cols
        ]
        cells = [_cell(s.summary(m), len(seeds)) for m in names]
        done = sum(r.status == "done" for r in s.runs)
        lines.append(
            f"| `{s.row}` | " + " | ".join([*paper, *cells, f"{done}/{len(seeds)}"]) + " |"
        )
    lines.append("")
    lines.append("Each seed (" + ", ".join(names) + "):\n")
    lines.append("| row | seed | status | " + " | ".join(names) + " | note |")
    lines.append("|" + "---|" * (len(names) + 4))
    for s in stats:
        for r in s.runs:
            status = r.status if r.step is None else f"{r.status} (step {r.step})"
            vals = [f"{r.values[m]:.2f}" if r.status == "done" else "-" for m in names]
            lines.append(
                f"| `{s.row}` | {r.seed} | {status} | " + " | ".join(vals) + f" | {r.note} |"
            )
    lines.append("")
    for sentence in sentences(task, stats):
        lines.extend([sentence, ""])
    return lines


def shown(path: Path, repo: Path = REPO) -> str:
    """How the report writes a run folder: relative to the repository when ``path`` is inside
    it, else ``workdirs/<folder name>`` (where the printed command puts the runs on another
    checkout); never an absolute path of the machine that ran them."""
    path = Path(path).resolve()
    repo = Path(repo).resolve()
    if path.is_relative_to(repo):
        return path.relative_to(repo).as_posix() or "."
    return f"workdirs/{path.name}"


def run_command(task: str, entry: dict, out: Path) -> str:
    """The command that (re)runs every row and seed of a plan entry, ``--out`` as
    :func:`shown` writes it."""
    parts = [*shlex.split(RUNNER), "--task", task]
    parts += ["--rows", ",".join(entry["rows"]), "--seeds", ",".join(map(str, entry["seeds"]))]
    parts += ["--out", shown(out), "--config", entry["config"]]
    if entry.get("eval_splits"):
        parts += ["--eval-splits", ",".join(entry["eval_splits"])]
    for key in ("section", "title"):
        if entry.get(key):
            parts += [f"--{key}", entry[key]]
    return shlex.join([*parts, *entry["overrides"]])


def read_plan(out: Path) -> dict:
    path = Path(out) / PLAN
    return json.loads(path.read_text()) if path.exists() else {}


def render(out: Path, plan: dict | None = None) -> str:
    """The whole report: header, the rows, each task of ``OUT/plan.json`` (or ``plan``)."""
    plan = read_plan(out) if plan is None else plan
    parts = [
        "# Ablations with seed spread (generated)\n",
        f"Written by `{RUNNER}` (see [results](results.md#the-ablation-runner)) from the runs "
        "it finished; do not edit by hand. Rerun a section's command from the repository root "
        "to finish its missing seeds (finished runs are skipped, interrupted ones resume) and "
        "to rewrite this file; `--report-only --out DIR` rewrites it from what exists. Run "
        "folders are written relative to the repository (`workdirs/<name>` for a folder "
        "outside it).\n",
        "These are numbers **on the embedded generated dataset**, not KITTI: they say whether "
        "each design choice helps here and by more than the seed-to-seed spread; the paper's "
        "columns are its KITTI numbers, for the direction of each difference only. A run's "
        "note gives its training wall time (all attempts, including any time the machine "
        "spent on other jobs, e.g. a detection and a depth run side by side: not a speed "
        "measurement; see [performance](performance.md) for that) and CPU.\n",
        VARIANTS_TEXT,
    ]
    for name, task in TASKS.items():
        if name in plan:
            parts.append(task_section(task, Path(out), plan[name]))
        else:
            rows = ",".join(task.rows)
            parts.append(
                f"## {TITLES[name]}\n\nNot run yet (no `{name}` runs in `{shown(out)}`). "
                "Command:\n\n"
                f"```bash\n{RUNNER} --task {name} --rows {rows} "
                f"--seeds 0,1,2 --out workdirs/ablations\n```\n"
            )
    return "\n".join(parts)


def _section_marks(name: str) -> tuple[str, str]:
    return (
        f"<!-- ablation section {name}: written by {RUNNER} --section {name}; do not edit "
        "by hand -->",
        f"<!-- end of ablation section {name} -->",
    )


SECTION_RE = re.compile(
    r"<!-- ablation section (?P<name>[\w.-]+):.*?-->\n.*?<!-- end of ablation section "
    r"(?P=name) -->\n?",
    re.S,
)


def render_section(out: Path, name: str) -> str:
    """The tasks of ``OUT/plan.json`` as one named section (between markers), for a report
    that also shows other experiments (another ``--out``), e.g. the multi-rig runs."""
    plan = read_plan(out)
    start, end = _section_marks(name)
    body = [task_section(TASKS[t], Path(out), plan[t]) for t in TASKS if t in plan]
    return "\n".join([start, *body, end]) + "\n"


def compose_report(old: str, out: Path, section: str | None = None) -> str:
    """The report file after a runner call: ``section=None`` rewrites the main part (the
    paper's tables, :func:`render`) and keeps every named section of ``old``; a named
    section replaces its earlier version in place or is appended, the rest of ``old`` kept."""
    blocks = {m["name"]: m.group(0) for m in SECTION_RE.finditer(old)}
    if section is None:
        kept = "".join(b if b.endswith("\n") else b + "\n" for b in blocks.values())
        return render(out) + ("\n" + kept if kept else "")
    new = render_section(out, section)
    if section in blocks:
        return old.replace(blocks[section], new)
    if not old:
        old = render(out, plan={})  # the header and the rows; the main runs not run yet
    return old.rstrip("\n") + "\n\n" + new
