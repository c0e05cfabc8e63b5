"""The accuracy guard's verdict file: ``guard.json`` beside the export it guarded.

``python -m gac_jax.cli.guard`` writes ``<export folder>/guard.json`` (the folder that holds
``model.onnx`` / ``model_int8.xml`` of one checkpoint, ``W/export/<step>`` by default):

    {"format": 2,
     "model": {"weights": "step1750", "weights_sha256": ..., "onnx_sha256": ...},
     "rule": {...the latest run's rule...},
     "verdicts": {"openvino:int8": {"runtime", "precision", "int8", "network": {"onnx_sha256",
        "int8_sha256", "libraries"}, "verdict": "within"|"beyond"|"undecided", "reason",
        "frames", "guard_set", "created", "criteria", "rule": {"version": 3, "min_score",
        "score_thresholds", "margin_points", "ap_margin_points", "alpha", "alpha_spending",
        ...}, "look", "alpha_look", "looks": [{"frames", "verdict", "created"}, ...]}, ...}}

A verdict is bound to the weights it was made for by their hash (the sha256 of every array,
:func:`gac_jax.trained.fingerprint.weights_sha256`), not by the step: a model retrained to the
same step is "not guarded". It applies to a run only for the same weights, exported graph,
int8 model (its IR's identity, always: an int8 model calibrated on another split, seed or
data root is "not guarded", saying what differs), runtime and quantizer versions, runtime,
precision, int8 calibration settings, the rule's version and its score threshold
(:func:`rule_mismatch`); :func:`verdict_for` says which and why not, and
:func:`precision_line` is the line ``evaluate.py`` (and ``predict``) print. Writes are
atomic; a new guard run replaces the verdicts of the precisions it guarded and keeps the
others when the model is the same.
Verdict files of an earlier format are not read (their rule and identity were weaker).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from gac_jax.data.files import atomic_write
from gac_jax.deploy.export import artifact
from gac_jax.deploy.int8 import Int8Settings
from gac_jax.trained.fingerprint import short

GUARD_FILE = "guard.json"
FORMAT = 2
# the packages whose version is part of a network's identity, per runtime (+ NNCF for int8)
RUNTIME_LIBRARIES = {"onnxruntime": ("onnxruntime",), "openvino": ("openvino",)}


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


def model_identity(export_dir: str | os.PathLike, weights: str, weights_sha256: str) -> dict:
    """What a verdict file belongs to: the weights' tag and hash, and the exported graph's
    sha256 (None when the folder holds no export)."""
    meta = _read_export(export_dir)
    return {
        "weights": weights,
        "weights_sha256": weights_sha256,
        "onnx_sha256": meta.get("sha256") if meta else None,
    }


def _read_export(export_dir) -> dict | None:
    try:
        return artifact.read_export(Path(export_dir))
    except (OSError, ValueError):
        return None


def network_identity(
    export_dir: str | os.PathLike,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
) -> dict:
    """What the results of an exported network depend on besides the weights: the
    ``model.onnx`` sha256, for int8 the IR's identity (:func:`gac_jax.deploy.int8.ir_sha256`)
    and what it was made from (the
    ``export.json`` int8 block: source graph, calibration, float32 scope), and the versions of
    the runtime (and NNCF for int8) installed now."""
    meta = _read_export(export_dir) or {}
    names = RUNTIME_LIBRARIES.get(runtime, (runtime,)) + (("nncf",) if precision == "int8" else ())
    out = {"onnx_sha256": meta.get("sha256"), "libraries": artifact.library_versions(names)}
    if precision == "int8":
        block = meta.get("int8") or {}
        out["int8_sha256"] = block.get("ir_sha256")
        out["int8_made_from"] = {
            k: block.get(k) for k in ("source_sha256", "calibration", "keep_float")
        }
    return out


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


def verdict_entry(
    runtime: str, precision: str, int8: Int8Settings | None, network: dict, **fields
) -> dict:
    """One candidate's entry of the verdict file (``network``: :func:`network_identity` of
    the network that ran; ``fields``: verdict, reason, frames, ...)."""
    entry = {"runtime": runtime, "precision": precision, "int8": _int8_block(precision, int8)}
    return entry | {"network": network} | fields


def verdict_for(
    export_dir: str | os.PathLike,
    weights: str,
    weights_sha256: str,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
    score_threshold: float | None = None,
) -> tuple[str, dict | None, str]:
    """``(status, entry, why)``: ``status`` is the guard's verdict (within / beyond /
    undecided) for exactly these weights (by hash), exported network, runtime and quantizer
    versions, precision, int8 calibration and score threshold (None: not compared), or
    ``"not guarded"`` with ``entry`` None and ``why`` saying in a few words what differs."""
    data = read_guard(export_dir)
    if data is None:
        return "not guarded", None, "no verdict for this export"
    stored = data.get("model") or {}
    if stored.get("weights_sha256") != weights_sha256:
        return (
            "not guarded",
            None,
            f"the verdicts are for other weights (sha256 {short(stored.get('weights_sha256'))}, "
            f"these are {short(weights_sha256)})",
        )
    if stored != model_identity(export_dir, weights, weights_sha256):
        return "not guarded", None, "the exported graph differs from the one guarded"
    entry = data["verdicts"].get(candidate_key(runtime, precision, int8))
    if entry is None or entry.get("int8") != _int8_block(precision, int8):
        return "not guarded", None, "no verdict for this runtime, precision and int8 settings"
    why = rule_mismatch(entry, score_threshold)
    if why:
        return "not guarded", None, why
    why = _network_differs(entry.get("network") or {}, export_dir, runtime, precision, int8)
    if why:
        return "not guarded", None, why
    return str(entry.get("verdict")), entry, ""


def _network_differs(guarded: dict, export_dir, runtime, precision, int8) -> str | None:
    now = network_identity(export_dir, runtime, precision, int8)
    for name, version in (guarded.get("libraries") or {}).items():
        if now["libraries"].get(name) != version:
            return f"guarded with {name} {version}, this is {now['libraries'].get(name)}"
    # the int8 model that runs is the one in the folder (built before this line is asked for):
    # its IR must be the guarded one, whatever it was made from
    if precision == "int8" and now["int8_sha256"] != guarded.get("int8_sha256"):
        return "the int8 model differs from the one guarded: " + _int8_difference(
            guarded.get("int8_made_from") or {}, now["int8_made_from"], now["int8_sha256"]
        )
    return None


def _int8_difference(guarded: dict, now: dict, ir_sha256: str | None) -> str:
    """What differs between the guarded int8 model's recipe and the one in the folder."""
    if ir_sha256 is None:
        return "no int8 model in the export folder"
    if guarded.get("source_sha256") != now.get("source_sha256"):
        return "made from another model.onnx"
    cal_then, cal_now = guarded.get("calibration") or {}, now.get("calibration") or {}
    moved = [k for k in sorted(set(cal_then) | set(cal_now)) if cal_then.get(k) != cal_now.get(k)]
    if moved:
        shown = ", ".join(f"{k} {cal_then.get(k)!r} -> {cal_now.get(k)!r}" for k in moved[:3])
        return f"calibrated otherwise ({shown})"
    if guarded.get("keep_float") != now.get("keep_float"):
        return "other layers kept in float32"
    return "its IR's sha256 differs"


def precision_line(
    workdir: str | os.PathLike,
    detector,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
    export_dir: str | os.PathLike | None = None,
) -> str:
    """One line: which precision runs and whether the guard decided it for this model
    (``detector``: a :class:`~gac_jax.trained.detector.LoadedDetector`, whose weights' hash
    and ``eval.score_threshold`` the verdict must match; ``export_dir`` default
    ``W/export/<step>``), e.g. ``precision: openvino int8; guard: within on 3000 frames
    (2026-12-04): ...`` or ``...; not guarded for these weights (...)``."""
    from gac_jax.deploy.runtime_choice import default_export_dir

    export_dir = export_dir or default_export_dir(workdir, detector)
    return describe_precision(
        export_dir,
        detector.tag,
        runtime,
        precision,
        int8,
        weights_sha256=detector.weights_sha256,
        score_threshold=float(detector.config.eval.score_threshold),
    )


def describe_precision(
    export_dir: str | os.PathLike,
    weights: str,
    runtime: str,
    precision: str,
    int8: Int8Settings | None = None,
    *,
    weights_sha256: str,
    score_threshold: float | None = None,
) -> str:
    """:func:`precision_line` for any exported model: ``export_dir`` (where its
    ``guard.json`` lies), ``weights`` (its tag, e.g. ``step875``) and ``weights_sha256``
    (:func:`gac_jax.trained.fingerprint.weights_sha256` of the weights that run)."""
    names = {"f32": "float32", "bf16": "bfloat16", "int8": "int8"}
    what = f"{runtime} {names.get(precision, precision)}"
    if int8 is not None and precision == "int8":
        what += " (heading kept in float32)" if int8.keep_heading else ""
    if runtime == "jax" and precision == "f32":
        return f"precision: {what}, the guard's reference"
    status, entry, why = verdict_for(
        export_dir, weights, weights_sha256, runtime, precision, int8, score_threshold
    )
    if entry is None:
        return (
            f"precision: {what}; not guarded for these weights: {why} "
            f"(python -m gac_jax.cli.guard decides it)"
        )
    frames, date = entry.get("frames"), str(entry.get("created", ""))[:10]
    return f"precision: {what}; guard: {status} on {frames} frames ({date}): {entry.get('reason')}"


# ----------------------------------------------------------------------------- the rule

# 1: recall at the deployed threshold only, objects independent, one look; 2: every count
# criterion, frames as the unit through a design effect estimated from the frames (not valid
# for rare bursts of changes); 3: tests by betting within per-frame bounds
RULE_VERSION = 3
DEPTH_RULE_VERSION = 2  # the depth guard's rule (per-frame SILog) did not change with 3
_EARLIER = {
    1: "decided under the earlier recall-only rule",
    2: "decided under the earlier rule, whose intervals did not hold when changes come in "
    "rare bursts",
}


def rule_mismatch(
    entry: dict | None, score_threshold: float | None = None, margin: float | None = None
) -> str | None:
    """Why a stored verdict does not apply to a run with this ``score_threshold`` (the
    deployed ``eval.score_threshold`` or the API's) and ``margin`` (None: not compared);
    None when its rule matches. The rule is the entry's ``rule`` block (detector:
    ``min_score``, ``score_thresholds``, ``margin_points``; depth: ``margin_silog``)."""
    rule = (entry or {}).get("rule")
    version = rule.get("version", 1) if isinstance(rule, dict) else 1
    depth = isinstance(rule, dict) and "margin_silog" in rule
    if version < (DEPTH_RULE_VERSION if depth else RULE_VERSION):
        return f"{_EARLIER.get(version, _EARLIER[1])}; python -m gac_jax.cli.guard re-decides"
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
