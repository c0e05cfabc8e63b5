"""Converted (pretrained) weights on disk: the layout the converter writes and the trainer,
the evaluator and the depth trainer read. Needs no torch.

Layout of a converted-weights folder ``OUT`` (what ``python -m gac_jax.weights.convert`` writes; a
workdir-style folder, so :class:`gac_jax.training.checkpointing.Checkpoints` can open it)::

    OUT/checkpoints/0/            orbax checkpoint, step 0, written by Checkpoints(OUT).save
        state = {'params': {...}, 'batch_stats': {...}}    float32 numpy arrays (Flax layout)
        meta  = {'format': 'gac_jax.converted.v1', 'kind': 'torchvision_resnet' or
                 'gac_detector', 'source', 'sha256', 'date', 'model': {...},
                 'shapes': {'params/backbone/conv1/kernel': [[7, 7, 3, 64], 'float32'], ...},
                 'step': 0, ...}
    OUT/conversion.json           the same meta without 'shapes', for people to read

``state`` holds exactly the variables of one Flax module: a
:class:`~gac_jax.models.resnet.ResNet` (kind ``torchvision_resnet``, all converted stages) or a
:class:`~gac_jax.models.detector.Detector` (kind ``gac_detector``). ``meta['model']`` holds the
module's constructor settings (``depth``, ``width``, ``num_stages`` or ``num_classes``,
``num_anchors``, ``offset_formula`` ...).

Readers:

* :func:`load_converted_variables` - the whole variables, checked against a template (the
  evaluator loading the released GAC model; the trainer starting from converted weights);
* :func:`load_backbone_init` / :func:`init_backbone` - only the ResNet trunk, merged into
  freshly initialised variables (the trainer, when ``config.model.pretrained_backbone`` is a
  path); a 3-stage model drops the stored ``layer4``.

Every check names the mismatching leaves ('/'-joined Flax paths) in :class:`WeightsError`.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from flax import traverse_util

from gac_jax.data.files import atomic_write
from gac_jax.training.checkpointing import Checkpoints

CONVERTED_FORMAT = "gac_jax.converted.v1"
CONVERTED_STEP = 0
KINDS = ("torchvision_resnet", "gac_detector")
COLLECTIONS = ("params", "batch_stats")


class WeightsError(ValueError):
    """Weights do not fit (or cannot be read). ``str()`` is a one-line summary; ``details``
    lists the offending keys / leaves, one per entry."""

    def __init__(self, message: str, details: Sequence[str] = ()):
        super().__init__(message)
        self.message = message
        self.details = list(details)

    def __str__(self) -> str:
        return self.message

    def full_text(self, max_lines: int = 60) -> str:
        """The message followed by (at most ``max_lines`` of) the details, one per line."""
        lines = [self.message]
        shown = self.details[:max_lines]
        lines += [f"  {d}" for d in shown]
        if len(self.details) > len(shown):
            lines.append(f"  ... and {len(self.details) - len(shown)} more")
        return "\n".join(lines)


def flat_shapes(variables: Mapping[str, Any]) -> dict[str, tuple[tuple[int, ...], str]]:
    """``{'params/backbone/conv1/kernel': (shape, dtype name), ...}`` of a variables tree
    (arrays or ``jax.ShapeDtypeStruct``)."""
    flat = traverse_util.flatten_dict(dict(variables), sep="/")
    return {k: (tuple(int(n) for n in v.shape), np.dtype(v.dtype).name) for k, v in flat.items()}


def compare_shapes(
    expected: Mapping[str, tuple[tuple[int, ...], str]],
    found: Mapping[str, tuple[tuple[int, ...], str]],
) -> list[str]:
    """Differences between two :func:`flat_shapes` tables as readable lines (empty if equal
    in keys and shapes; dtypes are not compared, values are cast on load)."""
    problems = [
        f"missing in the checkpoint: {k} {list(s)}"
        for k, (s, _) in expected.items()
        if k not in found
    ]
    problems += [
        f"not in the model: {k} {list(s)}" for k, (s, _) in found.items() if k not in expected
    ]
    problems += [
        f"shape mismatch: {k} is {list(found[k][0])} in the checkpoint, {list(s)} in the model"
        for k, (s, _) in expected.items()
        if k in found and tuple(found[k][0]) != tuple(s)
    ]
    return problems


# ---------------------------------------------------------------------------------------------
# writing


def save_converted(
    out_dir: str | os.PathLike,
    variables: Mapping[str, Any],
    meta: Mapping[str, Any],
    overwrite: bool = False,
) -> Path:
    """Writes converted variables in the layout of the module docstring.

    Args:
      out_dir: the folder ``OUT`` (created if needed).
      variables: ``{'params': ..., 'batch_stats': ...}`` (numpy or jax arrays).
      meta: JSON-serialisable facts; must contain ``'kind'`` (one of :data:`KINDS`) and
        ``'model'``; ``format`` and ``shapes`` are added here.
      overwrite: replace an earlier *converted* checkpoint in ``OUT`` (a folder holding any
        other checkpoints, e.g. a training workdir, is never touched).
    Returns:
      The checkpoint folder ``OUT/checkpoints/0``.
    Raises:
      WeightsError: ``OUT`` already holds checkpoints (and not ``overwrite`` of a converted one).
    """
    out_dir = Path(out_dir)
    if meta.get("kind") not in KINDS:
        raise ValueError(f"meta['kind'] must be one of {KINDS}, got {meta.get('kind')!r}")
    if set(variables) - set(COLLECTIONS) or "params" not in variables:
        raise ValueError(f"variables must hold 'params' (+ 'batch_stats'), got {sorted(variables)}")
    ckpt_dir = out_dir / "checkpoints"
    if ckpt_dir.is_dir() and any(ckpt_dir.iterdir()):
        existing = _read_meta_if_converted(out_dir)
        if not overwrite or existing is None:
            what = "converted weights" if existing is not None else "checkpoints"
            hint = " (pass --overwrite to replace them)" if existing is not None else ""
            raise WeightsError(f"{ckpt_dir} already holds {what}; choose an empty folder{hint}")
        shutil.rmtree(ckpt_dir)
    state = {
        c: jax.tree.map(lambda x: np.ascontiguousarray(np.asarray(x)), dict(variables[c]))
        for c in COLLECTIONS
        if c in variables
    }
    state.setdefault("batch_stats", {})
    shapes = {k: [list(s), d] for k, (s, d) in flat_shapes(state).items()}
    full_meta = {**dict(meta), "format": CONVERTED_FORMAT, "shapes": shapes}
    json.dumps(full_meta)  # fail early (before writing) on non-JSON values
    with Checkpoints(out_dir, max_to_keep=1) as ckpts:
        ckpts.save(CONVERTED_STEP, state, full_meta)
    readable = {k: v for k, v in full_meta.items() if k != "shapes"}
    with atomic_write(out_dir / "conversion.json") as f:
        f.write(json.dumps(dict(readable, step=CONVERTED_STEP), indent=2, sort_keys=True) + "\n")
    return ckpt_dir / str(CONVERTED_STEP)


# ---------------------------------------------------------------------------------------------
# reading


def _locate(path: str | os.PathLike) -> tuple[Path, int | None]:
    """``OUT`` or ``OUT/checkpoints/<step>`` -> (workdir, step or None for the latest)."""
    path = Path(path)
    if (path / "checkpoints").is_dir():
        return path, None
    if path.is_dir() and path.name.isdigit() and path.parent.name == "checkpoints":
        return path.parent.parent, int(path.name)
    raise WeightsError(
        f"{path}: no converted weights here (expected {path}/checkpoints/<step>, written by "
        "python -m gac_jax.weights.convert)"
    )


def _read_meta_if_converted(workdir: Path) -> dict | None:
    try:
        with Checkpoints(workdir) as ckpts:
            if ckpts.latest_step() is None:
                return None
            meta = ckpts.restore_meta()
    except (OSError, ValueError, KeyError):
        return None
    return meta if meta.get("format") == CONVERTED_FORMAT else None


def read_converted_meta(path: str | os.PathLike) -> dict:
    """The meta of converted weights at ``OUT`` (or ``OUT/checkpoints/<step>``).

    Raises:
      WeightsError: nothing there, or the checkpoint was not written by the converter.
    """
    workdir, step = _locate(path)
    with Checkpoints(workdir) as ckpts:
        if ckpts.latest_step() is None:
            raise WeightsError(f"{workdir}: no checkpoint in {workdir / 'checkpoints'}")
        if step is not None and step not in ckpts.all_steps():
            raise WeightsError(f"{workdir}: no checkpoint step {step} (have {ckpts.all_steps()})")
        try:
            meta = ckpts.restore_meta(step)
        except (OSError, ValueError, KeyError) as e:
            raise WeightsError(f"{workdir}: cannot read the checkpoint meta ({e})") from e
    if meta.get("format") != CONVERTED_FORMAT or "shapes" not in meta:
        raise WeightsError(
            f"{workdir}: not converted weights (meta format {meta.get('format')!r}, expected "
            f"{CONVERTED_FORMAT!r}); restore training checkpoints with the trainer instead"
        )
    return meta


def restore_converted(path: str | os.PathLike) -> tuple[dict[str, Any], dict]:
    """Restores converted weights as stored: ``({'params', 'batch_stats'} numpy tree, meta)``."""
    meta = read_converted_meta(path)
    workdir, step = _locate(path)
    abstract = traverse_util.unflatten_dict(
        {k: jax.ShapeDtypeStruct(tuple(s), np.dtype(d)) for k, (s, d) in meta["shapes"].items()},
        sep="/",
    )
    for c in COLLECTIONS:
        abstract.setdefault(c, {})
    with Checkpoints(workdir) as ckpts:
        try:
            state, _ = ckpts.restore(abstract, step=step)
        except (OSError, ValueError, KeyError) as e:
            raise WeightsError(f"{workdir}: cannot restore the converted weights ({e})") from e
    state = jax.tree.map(np.asarray, dict(state))
    problems = compare_shapes(flat_shapes(abstract), flat_shapes(state))
    if problems:
        raise WeightsError(f"{workdir}: stored arrays do not match the recorded shapes", problems)
    return state, meta


def _cast_like(values: Mapping[str, Any], template: Mapping[str, Any]) -> dict[str, Any]:
    flat_t = traverse_util.flatten_dict(dict(template), sep="/")
    flat_v = traverse_util.flatten_dict(dict(values), sep="/")
    out = {k: np.asarray(flat_v[k]).astype(t.dtype, copy=False) for k, t in flat_t.items()}
    return traverse_util.unflatten_dict(out, sep="/")


def load_converted_variables(path: str | os.PathLike, template: Mapping[str, Any]) -> dict:
    """The converted variables at ``path``, checked leaf by leaf against ``template``.

    Args:
      path: ``OUT`` or ``OUT/checkpoints/<step>`` written by the converter.
      template: the model's variables ``{'params', 'batch_stats'}`` (arrays or
        ``jax.eval_shape(model.init, ...)``); extra collections are ignored.
    Returns:
      ``{'params': ..., 'batch_stats': ...}`` numpy arrays with the template's structure and
      dtypes (place them on devices as the caller needs).
    Raises:
      WeightsError: missing/extra leaves or shape mismatches, each named in ``details``.
    """
    variables, meta = restore_converted(path)
    template = {c: template[c] for c in COLLECTIONS if c in template}
    template.setdefault("batch_stats", {})
    problems = compare_shapes(flat_shapes(template), flat_shapes(variables))
    if problems:
        raise WeightsError(
            f"{path}: the converted {meta.get('kind')} {meta.get('model')} does not fit the "
            f"model ({len(problems)} problems)",
            problems,
        )
    return _cast_like(variables, template)


def _backbone_subtree(variables: Mapping[str, Any], meta: Mapping[str, Any], path) -> dict:
    if meta.get("kind") == "torchvision_resnet":
        return {c: dict(variables.get(c, {})) for c in COLLECTIONS}
    if meta.get("kind") == "gac_detector":
        return {c: dict(variables.get(c, {}).get("backbone", {})) for c in COLLECTIONS}
    raise WeightsError(f"{path}: converted weights of unknown kind {meta.get('kind')!r}")


_STAGE = re.compile(r"^(?:params|batch_stats)/(layer\d+)_\d+/")


def load_backbone_init(
    path: str | os.PathLike, backbone_variables: Mapping[str, Any]
) -> dict[str, Any]:
    """Converted ResNet weights for a freshly initialised ResNet trunk.

    Args:
      path: converted weights (``OUT`` or ``OUT/checkpoints/<step>``) of kind
        ``torchvision_resnet`` (e.g. ImageNet ``resnet101-5d3b4d8f.pth``) or ``gac_detector``
        (its ``backbone``).
      backbone_variables: ``{'params': ..., 'batch_stats': ...}`` of the
        :class:`~gac_jax.models.resnet.ResNet` to initialise (e.g.
        ``variables['params']['backbone']`` and the same of ``'batch_stats'``).
    Returns:
      ``{'params', 'batch_stats'}`` with the template's structure and dtypes, every leaf taken
      from the file. Stored stages the model does not build (``layer4`` for a 3-stage trunk)
      are dropped.
    Raises:
      WeightsError: a template leaf is not in the file, shapes differ (other depth or width),
        or the file holds blocks inside a stage the model builds but does not have.
    """
    stored, meta = restore_converted(path)
    stored = _backbone_subtree(stored, meta, path)
    template = {c: backbone_variables.get(c, {}) for c in COLLECTIONS}
    want, have = flat_shapes(template), flat_shapes(stored)
    built_stages = {m.group(1) for k in want if (m := _STAGE.match(k))}
    dropped = [
        k
        for k in have
        if k not in want and (m := _STAGE.match(k)) and m.group(1) not in built_stages
    ]
    have = {k: v for k, v in have.items() if k not in dropped}
    problems = compare_shapes(want, have)
    if problems:
        model = meta.get("model", {})
        raise WeightsError(
            f"{path}: the converted ResNet (depth {model.get('depth')}, width "
            f"{model.get('width')}) does not fit this backbone ({len(problems)} problems)",
            problems,
        )
    return _cast_like(stored, template)


def init_backbone(
    variables: Mapping[str, Any], path: str | os.PathLike, backbone: str = "backbone"
) -> dict[str, Any]:
    """``variables`` of a whole model with its ``backbone`` sub-module replaced by
    :func:`load_backbone_init` (everything else, e.g. the detection head, is kept).

    Args:
      variables: ``{'params': ..., 'batch_stats': ...}`` of e.g. a
        :class:`~gac_jax.models.detector.Detector` (``model.init`` output).
      path: converted weights, as for :func:`load_backbone_init`.
      backbone: Flax name of the ResNet sub-module (``'backbone'`` in ``Detector``).
    """
    if backbone not in variables.get("params", {}):
        raise WeightsError(f"the model has no sub-module {backbone!r} to initialise from {path}")
    sub = {c: variables.get(c, {}).get(backbone, {}) for c in COLLECTIONS}
    loaded = load_backbone_init(path, sub)
    out = {c: dict(v) for c, v in variables.items()}
    for c in COLLECTIONS:
        if loaded[c]:
            out[c][backbone] = loaded[c]
    return out
