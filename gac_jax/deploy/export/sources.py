"""What gets exported: a trained network with its config, weights origin and decoding facts.

:class:`ExportSource` is built from a training workdir (or converted detector weights) by
:func:`load_source` (the ``python -m gac_jax.deploy.export`` command) or from an already loaded
model by :func:`detector_source` / :func:`depth_source` (``evaluate.py`` / ``predict`` with
``--runtime``). :func:`export_source` writes the folder; :func:`ensure_export` reuses a
matching one, exports into an empty one and refuses a stale or corrupted one.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path
from typing import Any

import ml_collections

from gac_jax.data.files import KittiFormatError
from gac_jax.deploy.export import artifact
from gac_jax.trained.fingerprint import short, weights_sha256

TASKS = ("detect3d", "depth")


@dataclasses.dataclass
class ExportSource:
    """A network ready to export. ``weights``: ``{'step': N}`` (a workdir checkpoint) or
    ``{'checkpoint': absolute path}`` (converted weights), with ``'sha256'``: the identity of
    the variables (:func:`gac_jax.trained.fingerprint.weights_sha256`), which an existing
    export must match; ``image_size``: (H, W) input."""

    task: str
    config: ml_collections.ConfigDict
    model: Any
    variables: dict
    weights: dict
    image_size: tuple[int, int]
    network_config: dict
    decoding: dict
    workdir: str | None = None

    def expected(self) -> dict:
        return {
            "task": self.task,
            "weights": self.weights,
            "input_size": list(self.image_size),
            "network_config": self.network_config,
        }


def _weights(step: int | None, checkpoint, variables, sha256: str | None = None) -> dict:
    sha256 = sha256 or weights_sha256(variables)
    if checkpoint is not None:
        return {"checkpoint": str(Path(checkpoint).resolve()), "sha256": sha256}
    return {"step": int(step), "sha256": sha256}


def detector_source(
    config, model, variables, *, step=None, checkpoint=None, workdir=None, weights_sha256=None
):
    """:class:`ExportSource` of a loaded detector (``model``: the float32 ``Detector``;
    ``weights_sha256``: the variables' hash when already known, else computed)."""
    from gac_jax.builders.detect3d import anchor_layout, filter_options, sign_axis

    d = config.data
    layout = anchor_layout(config)
    network_config = {
        "model": config.model.to_dict(),
        "classes": list(d.classes),
        "num_anchors": layout.anchors_per_cell,
        "input": {"crop_top": d.crop_top, "height": d.height, "width": d.width},
    }
    priors = Path(workdir) / "anchor_priors.npz" if workdir else None
    decoding = {
        "outputs": {
            "cls_logits": "(B, N, K) class logits",
            "sign_logits": "(B, N) logit of cos(alpha) > 0",
            "reg": "(B, N, 12) regression [dx dy dw dh cdx cdy z sin2a cos2a w3d h3d l3d]",
        },
        "anchor_index": "(row * Wf + col) * A + a",
        "anchors": config.anchors.to_dict(),
        "num_anchors": layout.anchors_per_cell,
        "sign_axis": sign_axis(config),
        "priors_file": str(priors.resolve()) if priors and priors.exists() else None,
        "priors_sha256": (
            artifact.sha256_bytes(priors.read_bytes()) if priors and priors.exists() else None
        ),
        "ground_filter": config.anchors.filter,
        "filter_options": filter_options(config),
        "eval": config.eval.to_dict(),
        "transform": "crop top crop_top rows, resize to height, crop/pad width; ImageNet "
        "normalisation (gac_jax.builders.detect3d.eval_transform)",
    }
    return ExportSource(
        "detect3d",
        config,
        model,
        variables,
        _weights(step, checkpoint, variables, weights_sha256),
        (d.height, d.width),
        network_config,
        decoding,
        str(workdir) if workdir else None,
    )


def depth_source(
    config, model, variables, *, step, workdir=None, weights_sha256=None
) -> ExportSource:
    """:class:`ExportSource` of a loaded depth U-Net (input: ``height`` x ``eval_width``)."""
    d = config.data
    network_config = {
        "model": config.model.to_dict(),
        "prior_mean": float(model.prior_mean),
        "input": {"crop_height": d.crop_height, "height": d.height, "eval_width": d.eval_width},
    }
    decoding = {
        "outputs": {
            "log_depth": "(B, H, W) natural-log depth in metres (the scale_1 head, prior mean "
            "folded into its bias)"
            if model.output_prior == "mean"
            else "(B, H, W) natural-log depth in metres (the scale_1 head plus the road's log "
            "depth at every pixel, from P2 and plane, at most prior_max_depth)",
            "depth": "(B, H, W) metres = exp(log_depth)",
        },
        "prior_mean": float(model.prior_mean),
        "transform": "bottom crop_height rows, resize to height, the left eval_width columns; "
        "ImageNet normalisation (gac_jax.builders.depth.eval_transform)",
    }
    return ExportSource(
        "depth",
        config,
        model,
        variables,
        _weights(step, None, variables, weights_sha256),
        (d.height, d.eval_width),
        network_config,
        decoding,
        str(workdir) if workdir else None,
    )


def load_source(
    task: str,
    *,
    workdir: str | os.PathLike | None = None,
    step: int | None = None,
    checkpoint: str | os.PathLike | None = None,
    config_spec: str | None = None,
    overrides: list[str] | None = None,
) -> ExportSource:
    """The network of a training workdir (or converted detector weights + ``--config``).

    Raises:
      KittiFormatError: missing workdir/config/checkpoint, or weights that do not fit.
    """
    if task not in TASKS:
        raise ValueError(f"task must be one of {TASKS}, got {task!r}")
    if task == "depth":
        from gac_jax.trained.depth import restore_depth_model

        if checkpoint is not None or config_spec:
            raise KittiFormatError(
                checkpoint or config_spec,
                "depth networks are exported from their training workdir (--workdir W)",
            )
        if overrides:
            raise KittiFormatError(
                Path(workdir) / "config.json",
                "depth exports use the workdir's config as trained; overrides do not apply",
            )
        config, model, variables, step = restore_depth_model(workdir, step)
        return depth_source(config, model, variables, step=step, workdir=workdir)

    from gac_jax.builders.detect3d import anchor_layout, build_model
    from gac_jax.trained.detector import load_variables, variables_template
    from gac_jax.trained.run_config import load_run_config

    config = load_run_config(workdir or ".", config_spec, overrides)
    model = build_model(config, anchor_layout(config).anchors_per_cell)
    template = variables_template(model, config)
    variables, step = load_variables(workdir, template, step=step, checkpoint=checkpoint)
    return detector_source(
        config, model, variables, step=step, checkpoint=checkpoint, workdir=workdir
    )


def export_source(
    source: ExportSource, out_dir: str | os.PathLike, opset: int = artifact.DEFAULT_OPSET
) -> dict:
    """Builds the ONNX graph of ``source``, checks it and writes ``out_dir``; returns the meta."""
    import onnx

    from gac_jax.deploy.export.networks import depth_graph, detector_graph

    build = detector_graph if source.task == "detect3d" else depth_graph
    graph = build(source.model, source.variables, source.image_size, opset)
    onnx.checker.check_model(graph)
    meta = {
        **source.expected(),
        "source": {"workdir": source.workdir, **source.weights},
        "opset": opset,
        "inputs": {
            "images": ["batch", *source.image_size, 3],
            "P2": ["batch", 3, 4],
            "plane": ["batch", 4],
        },
        "decoding": source.decoding,
        "config": source.config.to_dict(),
    }
    return artifact.write_export(out_dir, graph.SerializeToString(), meta)


def _stored_weights(meta: dict) -> dict:
    return meta.get("weights") if isinstance(meta.get("weights"), dict) else {}


def will_write(source: ExportSource, out_dir: str | os.PathLike) -> bool:
    """Whether :func:`ensure_export` would write ``out_dir``: no export there yet, or one of
    other weights (a damaged one is refused, not rewritten, so it counts as no write)."""
    out = Path(out_dir)
    if not (out / artifact.EXPORT_FILE).exists() and not (out / artifact.MODEL_FILE).exists():
        return True
    try:
        meta = json.loads((out / artifact.EXPORT_FILE).read_text())
    except (OSError, ValueError):
        return False
    return (
        not isinstance(meta, dict)
        or _stored_weights(meta).get("sha256") != (source.weights["sha256"])
    )


def ensure_export(
    source: ExportSource, out_dir: str | os.PathLike, opset: int = artifact.DEFAULT_OPSET
) -> tuple[dict, bool]:
    """``(meta, exported_now)``: the export of ``source`` in ``out_dir``, written if absent.

    An export of other weights (another sha256: a model retrained to the same step, a
    checkpoint replaced, an export from before weights were hashed) is replaced, saying why in
    one line; its int8 model and guard verdicts are then stale by their own records
    (:mod:`gac_jax.deploy.int8` compares the ``model.onnx`` sha256,
    :mod:`gac_jax.guard.verdict_file` the weights' sha256).

    Raises:
      KittiFormatError: an existing export that is corrupted or made for another config or
        input size.
    """
    out = Path(out_dir)
    if not (out / artifact.EXPORT_FILE).exists() and not (out / artifact.MODEL_FILE).exists():
        return export_source(source, out, opset), True
    meta = artifact.read_export(out)
    stored = _stored_weights(meta)
    if stored.get("sha256") != source.weights["sha256"]:
        print(
            f"exporting again into {out}: the export there was made from other weights "
            f"(sha256 {short(stored.get('sha256'))}, these are "
            f"{short(source.weights['sha256'])})",
            flush=True,
        )
        return export_source(source, out, opset), True
    artifact.check_export(out, meta, source.expected())
    return meta, False
