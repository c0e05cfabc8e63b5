"""The accuracy guard's verdict file: ``guard.json`` beside the export it guarded.

``python -m gac_jax.cli.guard`` writes ``<export folder>/guard.json`` (the folder that holds
``model.onnx`` / ``model_int8.xml`` of one checkpoint, ``W/export/<step>`` by default):

    {"format": 1, "model": {"weights": "step1750", "onnx_sha256": ...},
     "rule": {...}, "verdicts": {"openvino:int8": {"runtime", "precision", "int8",
     "verdict": "within"|"beyond"|"undecided", "reason", "frames", "guard_set", "created",
     ...}, ...}}

A verdict applies to a run only for the same weights (and exported graph), runtime, precision
and, for int8, the same calibration settings; :func:`guard_status` says which, and
:func:`precision_line` is the line ``evaluate.py`` (and ``predict``) print. Writes are atomic;
a new guard run replaces the verdicts of the precisions it guarded and keeps the others when
the model is the same.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from gac_jax.data.files import atomic_write
from gac_jax.deploy.export import artifact
from gac_jax.deploy.int8 import Int8Settings

GUARD_FILE = "guard.json"
FORMAT = 1


def candidate_key(runtime: str, precision: str, int8: Int8Settings | None = None) -> str:
    """``openvino:int8`` (default int8 settings), ``openvino:int8+heading``, ...; other int8
    settings are compared through the entry's ``int8`` block, not the key."""
    heading = "+heading" if precision == "int8" and int8 and int8.keep_heading else ""
    return f"{runtime}:{precision}{heading}"


def _int8_block(precision: str, int8: Int8Settings | None) -> dict | None:
    if precision != "int8":
        return None
    settings = dataclasses.asdict(int8 or Int8Settings())
    settings["keep_float"] = list(settings["keep_float"])
    return settings


def model_identity(export_dir: str | os.PathLike, weights: str) -> dict:
    """What a verdict belongs to: the weights' tag and the exported graph's sha256 (None when
    the folder holds no export)."""
    try:
        sha = artifact.read_export(Path(export_dir)).get("sha256")
    except (OSError, ValueError):
        sha = None
    return {"weights": weights, "onnx_sha256": sha}


def read_guard(export_dir: str | os.PathLike) -> dict | None:
    """The verdict file of an export folder (None when absent or unreadable)."""
    path = Path(export_dir) / GUARD_FILE
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("format") == FORMAT else None


def write_guard(export_dir: str | os.PathLike, model: dict, rule: dict, verdicts: dict) -> Path:
    """Adds ``verdicts`` (``{key: entry}``) to the folder's verdict file (atomically); keeps
    the stored verdicts of other keys only when they belong to the same ``model``."""
    out = Path(export_dir)
    out.mkdir(parents=True, exist_ok=True)
    stored = read_guard(out)
    kept = stored["verdicts"] if stored and stored.get("model") == model else {}
    data = {"format": FORMAT, "model": model, "rule": rule, "verdicts": {**kept, **verdicts}}
    with atomic_write(out / GUARD_FILE) as f:
        json.dump(data, f, indent=2)
        f.write("\n")
    return out / GUARD_FILE


def verdict_entry(runtime: str, precision: str, int8: Int8Settings | None, **fields) -> dict:
    """One candidate's entry of the verdict file (``fields``: verdict, reason, frames, ...)."""
    entry = {"runtime": runtime, "precision": precision, "int8": _int8_block(precision, int8)}
    return entry | fields


def guard_status(
    export_dir: str | os.PathLike,
    weights: str,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
) -> tuple[str, dict | None]:
    """``(status, entry)``: ``status`` is the guard's verdict (within / beyond / undecided)
    for exactly this model, runtime, precision and int8 calibration, or ``"not guarded"``
    (``entry`` None) when the folder has no such verdict."""
    data = read_guard(export_dir)
    if data is None or data.get("model") != model_identity(export_dir, weights):
        return "not guarded", None
    entry = data["verdicts"].get(candidate_key(runtime, precision, int8))
    if entry is None or entry.get("int8") != _int8_block(precision, int8):
        return "not guarded", None
    return str(entry.get("verdict")), entry


def precision_line(
    workdir: str | os.PathLike,
    detector,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
    export_dir: str | os.PathLike | None = None,
) -> str:
    """One line: which precision runs and whether the guard decided it for this model
    (``detector``: a :class:`~gac_jax.trained.detector.LoadedDetector`; ``export_dir``
    default ``W/export/<step>``), e.g. ``precision: openvino int8; guard: within on 3000
    frames (2026-12-04): ...`` or ``...; not guarded for these weights (...)``."""
    from gac_jax.deploy.runtime_choice import default_export_dir

    export_dir = export_dir or default_export_dir(workdir, detector)
    return describe_precision(export_dir, detector.tag, runtime, precision, int8)


def describe_precision(
    export_dir: str | os.PathLike,
    weights: str,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
) -> str:
    """:func:`precision_line` for any exported model: ``export_dir`` (where its
    ``guard.json`` lies) and ``weights`` (its tag, e.g. ``step875``)."""
    names = {"f32": "float32", "bf16": "bfloat16", "int8": "int8"}
    what = f"{runtime} {names.get(precision, precision)}"
    if int8 is not None and precision == "int8":
        what += " (heading kept in float32)" if int8.keep_heading else ""
    if runtime == "jax" and precision == "f32":
        return f"precision: {what}, the guard's reference"
    status, entry = guard_status(export_dir, weights, runtime, precision, int8)
    if entry is None:
        return (
            f"precision: {what}; not guarded for these weights "
            f"(python -m gac_jax.cli.guard decides it)"
        )
    frames, date = entry.get("frames"), str(entry.get("created", ""))[:10]
    return f"precision: {what}; guard: {status} on {frames} frames ({date}): {entry.get('reason')}"


# ----------------------------------------------------------------------------- the rule

RULE_VERSION = 2  # 1: recall at the deployed threshold only, objects independent, one look


def rule_mismatch(
    entry: dict | None, score_threshold: float | None = None, margin: float | None = None
) -> str | None:
    """Why a stored verdict does not apply to a run with this ``score_threshold`` (the
    deployed ``eval.score_threshold`` or the API's) and ``margin`` (None: not compared);
    None when its rule matches. The rule is the entry's ``rule`` block (detector:
    ``min_score``, ``score_thresholds``, ``margin_points``; depth: ``margin_silog``)."""
    rule = (entry or {}).get("rule")
    if not isinstance(rule, dict) or rule.get("version", 1) < RULE_VERSION:
        return "decided under the earlier recall-only rule; python -m gac_jax.cli.guard re-decides"
    stored = rule.get("min_score")
    moved = stored is not None and score_threshold is not None
    if moved and abs(float(stored) - float(score_threshold)) > 1e-9:
        return f"decided at score threshold {stored}, this run uses {score_threshold}"
    stored = rule.get("margin_points", rule.get("margin_silog"))
    if margin is not None and stored is not None and abs(float(stored) - float(margin)) > 1e-9:
        return f"decided with margin {stored}, this run asks for {margin}"
    return None


def previous_looks(export_dir: str | os.PathLike, model: dict, key: str) -> list[dict]:
    """The earlier guard runs (looks) of candidate ``key`` on this ``model``: ``[{'frames',
    'verdict', 'created'}, ...]`` (a verdict without a ``looks`` record counts as one look);
    the next run is look ``len(...) + 1`` and spends alpha accordingly."""
    stored = read_guard(export_dir)
    if not stored or stored.get("model") != model:
        return []
    entry = stored["verdicts"].get(key)
    if not entry:
        return []
    if isinstance(entry.get("looks"), list):
        return list(entry["looks"])
    return [{k: entry.get(k) for k in ("frames", "verdict", "created")}]
