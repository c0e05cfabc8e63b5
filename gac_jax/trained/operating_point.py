"""The deployed score threshold of a trained detector: its operating point, bound to its weights.

Every evaluation of a detector on a labelled split (the trainer's at the end of a run,
``evaluate.py``) writes ``operating_point.json`` beside its ``metrics.json``: the score
threshold of best F-beta on that split (:mod:`gac_jax.evaluation.operating_point`; beta from
``eval.operating_point_beta``, 1 where absent), with its sweep of precision and recall, the
step and the sha256 of the weights it was chosen for. A record made with another beta than the
run config's now (an override, or a record from before the key) is chosen again from its sweep
with the config's beta: no evaluation has to run again.

Where a run's config says ``eval.deploy_threshold = 'operating_point'`` (the default
detector's), the deployment (``gac_jax.cli.predict``, the streams, :class:`Detector3D`, the
guard) runs at that threshold: the file of the trainer's evaluation
(``WORKDIR/results/step_N/``) or, failing that, of ``evaluate.py`` on the config's val split
(``WORKDIR/eval/<val_split>_stepN/``), for the weights loaded (the sha256 must match). A
threshold given explicitly (``--score-threshold``, ``score_threshold=``, an
``eval.score_threshold=`` override) wins; without a matching file, or with
``eval.deploy_threshold = 'score_threshold'`` (or absent, as in runs made before the key
existed), the deployment runs at ``eval.score_threshold``, the evaluation's threshold.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from gac_jax.data.files import atomic_write
from gac_jax.evaluation.operating_point import check_beta, chosen_threshold, describe, rule
from gac_jax.trained.detector import LoadedDetector

FILE = "operating_point.json"
MODES = ("operating_point", "score_threshold")


def write_operating_point(
    out_dir: str | os.PathLike, record: dict, detector_step: int | None, sha256: str, split: str
) -> Path:
    """Writes ``record`` (:func:`gac_jax.evaluation.operating_point.operating_point`) with the
    step, weights sha256 and split it was chosen on to ``out_dir/operating_point.json``."""
    path = Path(out_dir) / FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    body = {"step": detector_step, "weights_sha256": sha256, "split": split, **record}
    with atomic_write(path) as f:
        json.dump(body, f, indent=2)
        f.write("\n")
    return path


def deploy_mode(config) -> str:
    """``eval.deploy_threshold`` of a run config (``'score_threshold'`` where absent)."""
    mode = config.eval.get("deploy_threshold", "score_threshold")
    if mode not in MODES:
        raise ValueError(f"eval.deploy_threshold must be one of {MODES}, got {mode!r}")
    return mode


def find_operating_point(workdir: str | os.PathLike, detector: LoadedDetector) -> dict | None:
    """The recorded operating point of ``detector``'s weights in ``workdir`` (module docstring;
    with ``'path'`` added), or None where no file of these weights has one."""
    if detector.step is None:
        return None
    workdir = Path(workdir)
    val = detector.config.data.val_split
    for folder in (f"results/step_{detector.step}", f"eval/{val}_step{detector.step}"):
        path = workdir / folder / FILE
        try:
            record = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError):
            continue
        if not isinstance(record, dict) or record.get("threshold") is None:
            continue
        if record.get("weights_sha256") != detector.weights_sha256:
            continue
        return {**rechosen(record, detector.config), "path": str(path)}
    return None


def rechosen(record: dict, config) -> dict:
    """``record`` with its threshold chosen from its sweep by ``config``'s
    ``eval.operating_point_beta`` (``record`` itself where it was chosen with that beta)."""
    beta = check_beta(config.eval.get("operating_point_beta", 1.0))
    if float(record.get("beta", 1.0)) == beta or not record.get("sweep"):
        return record
    threshold = chosen_threshold(record["sweep"], beta)
    if threshold is None:
        return record
    return {**record, "threshold": threshold, "beta": beta, "rule": rule(beta)}


def apply_deploy_threshold(
    workdir: str | os.PathLike, detector: LoadedDetector, explicit: bool
) -> str:
    """Sets ``detector.config.eval.score_threshold`` to the deployed threshold; returns one
    line saying which it is and where it came from.

    Args:
      workdir: the run folder; detector: its loaded weights.
      explicit: the caller was given a threshold (it stays).
    """
    e = detector.config.eval
    if explicit:
        return f"score threshold {float(e.score_threshold):.2f} (given)"
    if deploy_mode(detector.config) != "operating_point":
        return f"score threshold {float(e.score_threshold):.2f} (eval.score_threshold)"
    record = find_operating_point(workdir, detector)
    if record is None:
        return (
            f"score threshold {float(e.score_threshold):.2f} (eval.score_threshold: no operating "
            f"point recorded for {detector.weights}; python evaluate.py --task detect3d "
            f"--workdir {workdir} records one)"
        )
    e.score_threshold = float(record["threshold"])
    where = Path(record["path"]).parent
    return f"{describe(record)} on split {record.get('split')!r}, from {where}"
