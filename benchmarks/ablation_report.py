"""Reads the ablation runs of ``benchmarks/ablation_table.py`` and writes docs/ablations.md.

Pure file reading and arithmetic (no JAX): every number in the report comes from a metrics
file the trainer wrote (``WORKDIR/results/step_N/metrics.json``, N the run's last step) of
a run the runner saw finish (``WORKDIR/ablation_run.json``). Runs that are missing,
interrupted or failed are listed as such and left out of the statistics.
"""

from __future__ import annotations

import json
import math
import re
import statistics
from dataclasses import dataclass, field
from pathlib import Path

DONE_MARKER = "ablation_run.json"
FAILED_MARKER = "ablation_failed.json"
PLAN = "plan.json"
REPO = Path(__file__).resolve().parents[1]

# Paper Table 3 ("3D Detection Ablation Study Results of Car on KITTI Validation Set",
# paper_gac.tex, tab:ablation_study), 3D AP|R40 easy / moderate / hard in %.
PAPER_TABLE3 = {
    "baseline": {"3D@0.7": (23.63, 16.16, 12.06), "3D@0.5": (60.92, 42.18, 32.02)},
    "nofilter": {"3D@0.7": (21.39, 14.35, 11.11), "3D@0.5": (59.76, 41.00, 31.10)},
    "ohem": {"3D@0.7": (22.45, 15.10, 11.29), "3D@0.5": (60.71, 42.01, 31.88)},
    "conv": {"3D@0.7": (21.57, 15.26, 11.35), "3D@0.5": (58.17, 41.17, 32.58)},
    "disparity": {"3D@0.7": (22.13, 15.42, 11.34), "3D@0.5": (60.13, 41.62, 33.07)},
    "deformable": {"3D@0.7": (22.16, 15.71, 11.75), "3D@0.5": (62.24, 43.93, 33.76)},
}
PAPER_TABLE3_NAMES = {
    "baseline": "Baseline Model",
    "nofilter": "w/o Anchor Filtering",
    "ohem": "w OHEM",
    "conv": "w Conv",
    "disparity": "w DisparityConv",
    "deformable": "w Deformable Conv",
}
# Paper depth table (tab:depth_validation_results, KITTI depth val).
PAPER_DEPTH = {
    "base": {"silog": 12.78, "sq_rel": 3.11, "abs_rel": 10.12, "irmse": 13.46},
    "gac": {"silog": 12.13, "sq_rel": 2.61, "abs_rel": 9.41, "irmse": 12.65},
}
PAPER_DEPTH_NAMES = {"base": "Base U-Net", "gac": "Ours"}


@dataclass(frozen=True)
class Task:
    """What the report shows for one task: metric name -> path into ``metrics.json``."""

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
    variants={r: r for r in PAPER_TABLE3},
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
    variants={"base": "base", "gac": ""},
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


def read_run(task: Task, workdir: Path, seed: int) -> RunResult:
    """The result of one run, from the files in its workdir (see the module docstring)."""
    done = workdir / DONE_MARKER
    if done.exists():
        marker = json.loads(done.read_text())
        step = int(marker["final_step"])
        metrics_file = workdir / "results" / f"step_{step}" / "metrics.json"
        if not metrics_file.exists():
            return RunResult(seed, "failed", step=step, note=f"{metrics_file} missing")
        metrics = json.loads(metrics_file.read_text())["metrics"]
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


def collect(task: Task, out: Path, rows, seeds) -> list[RowStats]:
    return [
        RowStats(row, [read_run(task, run_dir(out, task.name, row, s), s) for s in seeds])
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
    rows, seeds = plan["rows"], plan["seeds"]
    stats = collect(task, out, rows, seeds)
    lines = []
    lines.append(f"## {TITLES[task.name]}\n")
    extra = " ".join(plan.get("overrides", [])) or "none"
    lines.append(
        f"Config `{plan['config']}` (row = variant), overrides: `{extra}`; seeds "
        f"{', '.join(map(str, seeds))} (the seed sets the model init, dropout and the data "
        f"order; the generated dataset is the same for all). Runs in `{shown(out / task.name)}`:\n"
    )
    if plan.get("command"):
        lines.append(f"```bash\n{plan['command']}\n```\n")
    if task.name == "detect3d":
        lines.append(
            "Car AP|R40 in %, **moderate**, on the generated val split: mean ± sample std "
            "[min, max] over the finished seeds. Paper: KITTI val, Table 3 (3D only).\n"
        )
    else:
        lines.append(
            "KITTI depth metrics on the generated val split (lower is better): mean ± sample "
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
    return "\n".join(lines)


def shown(path: Path) -> str:
    """``path`` relative to the repository when it is inside it (stable across checkouts)."""
    path = Path(path).resolve()
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def read_plan(out: Path) -> dict:
    path = Path(out) / PLAN
    return json.loads(path.read_text()) if path.exists() else {}


def render(out: Path) -> str:
    plan = read_plan(out)
    parts = [
        "# Ablations with seed spread (generated)\n",
        "Written by `benchmarks/ablation_table.py` from the runs it finished; do not edit by "
        "hand. Rerun a section's command to finish its missing seeds (finished runs are "
        "skipped, interrupted ones resume) and to rewrite this file; `--report-only --out DIR` "
        "rewrites it from what exists.\n",
        "These are numbers **on the embedded generated dataset**, not KITTI: they say whether "
        "each design choice helps here and by more than the seed-to-seed spread; the paper's "
        "columns are its KITTI numbers, for the direction of each difference only. A run's "
        "note gives its training wall time (all attempts, including any time the machine "
        "spent on other jobs, e.g. a detection and a depth run side by side: not a speed "
        "measurement; see `benchmarks/bench_train_step.py` for that) and CPU.\n",
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
                f"```bash\npython benchmarks/ablation_table.py --task {name} --rows {rows} "
                f"--seeds 0,1,2 --out workdirs/ablations\n```\n"
            )
    return "\n".join(parts)


VARIANTS_TEXT = """## The rows

Detection rows are variants of `configs/detect3d_default.py` (the same names work on
`configs/detect3d_kitti.py`, e.g. `configs/detect3d_kitti.py:ohem`):
"""

VARIANT_ROWS = (
    (
        "baseline",
        "nothing: ground-aware convolution (GAC) in the regression branch, ground-plane anchor "
        "filter in training and at test",
    ),
    ("nofilter", "`anchors.filter=False`: every anchor is used in training and at test"),
    (
        "ohem",
        "no ground-plane filter; in training, per image, the easiest half of the negative "
        "anchors leaves the loss (`loss.ohem_drop_fraction=0.5`); no filter at test",
    ),
    ("conv", "GAC replaced by conv3x3 C->C + ReLU"),
    ("disparity", "GAC replaced by conv3x3 over [disparity prior map, features] (C+1 -> C) + ReLU"),
    (
        "deformable",
        "GAC replaced by a modulated deformable conv v2 3x3 C->C + ReLU "
        "(`gac_jax/models/deformable_conv.py`): per-pixel tap offsets and masks from a "
        "zero-initialised 3x3 conv as in DCNv2, so it starts as half a plain conv",
    ),
)
VARIANTS_TEXT += "\n| row | paper Table 3 | what changes |\n|---|---|---|\n" + "".join(
    f"| `{row}` | {PAPER_TABLE3_NAMES[row]} | {text} |\n" for row, text in VARIANT_ROWS
)
VARIANTS_TEXT += """
OHEM exactly (`gac_jax/detection/detection_loss.py`, `ohem_negative_mask`): the paper says only "we
filter out half of the easy negative anchors during training". Here, per image `j`, after
the usual assignment (positive at IoU >= 0.5, negative below 0.4, ignored between), the
`floor(0.5 * num_neg_j)` negatives with the lowest classification loss (the focal loss of the
anchor summed over classes, computed before the reference's zeroing of losses below 1e-5;
among equal losses the lower anchor index goes first) are treated like ignored anchors: they
add nothing to the focal-loss sum and are not counted in the normaliser `num_pos_j +
num_neg_j`, just as anchors removed by the ground filter are not. The selection is per image
(not per batch: the ground filter, which removes about half of the negatives, is per image
too, and a per-image choice does not depend on how a batch is split over devices), it carries
no gradient, and positives, ignored anchors and the regression terms are unchanged. It acts on
top of the focal loss, which already down-weights easy negatives by `p^2`: the dropped half
contributes little loss anyway, so the main effect is the smaller normaliser (about twice the
classification loss per anchor, as with the ground filter) and that the easiest half gives no
gradient at all.

Depth rows: `base` = `configs/depth_default.py:base` (the paper's "Base U-Net", no GAC) and
`gac` = `configs/depth_default.py` (the GAC U-Net).
"""


def paper_table3_from_tex(tex: str) -> dict[str, dict[str, tuple[float, ...]]]:
    """Parses tab:ablation_study of the paper source (to check :data:`PAPER_TABLE3`)."""
    start = tex.index(r"\caption{3D Detection Ablation Study")
    body = tex[start : tex.index(r"\end{tabular*}", start)]
    out = {}
    for row, name in PAPER_TABLE3_NAMES.items():
        line = next(ln for ln in body.splitlines() if name in ln)
        numbers = [float(x) for x in re.findall(r"(\d+\.\d+)", line)]
        out[row] = {"3D@0.7": tuple(numbers[:3]), "3D@0.5": tuple(numbers[3:6])}
    return out
