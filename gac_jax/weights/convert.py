"""Import PyTorch weights: torchvision ImageNet ResNets and the authors' GAC checkpoint.

Command line (``torch`` is an optional extra: ``pip install 'gac-jax[torch]'``)::

    # ImageNet backbone (torchvision resnet{18,34,50,101}-*.pth) -> ResNet variables, 4 stages
    python -m gac_jax.weights.convert torchvision-resnet [--depth 101] IN.pth OUT_DIR

    # the released GroundAware_pretrained.pth (or any reference GroundAwareYolo3D state dict)
    python -m gac_jax.weights.convert gac IN.pth OUT_DIR [--config configs/FILE.py[:ARG]]
        [--depth D] [--width W] [--num-classes K] [--num-anchors A]
        [--offset-formula reference_v1|reference|paper]

Both write the layout of :mod:`gac_jax.weights.pretrained` (``OUT_DIR/checkpoints/0`` +
``OUT_DIR/conversion.json``). Architecture settings come, in increasing priority, from the
file itself (depth from the block counts, width from ``conv1``, classes / anchors / branch
widths from the head's conv shapes), from ``--config`` (``model.backbone_depth``,
``model.backbone_width``, ``model.num_classes`` or ``len(data.classes)``,
``model.num_anchors`` or ``len(anchors.ratios) * len(anchors.scales)`` (or
``anchors.num_scales``),
``model.cls_features``, ``model.reg_features``, ``model.regression_block``) and from the
flags; a disagreement with the file is an error naming the keys. ``--offset-formula`` is a
property of how the weights were *trained* (it changes no weight) and defaults to
``reference_v1``, the release-1.0 GAC base offset the released weights were trained with
(reference_impl.md §3.4 step 4, Appendix B); it is recorded in the meta, and the config's
``model.gac.offset_formula`` is only compared against it (a note is printed when they give
different offsets: ``paper`` and ``reference`` are the same formula, only ``reference_v1``
differs).

Every tensor must be used exactly once (BatchNorm counters and the reference's loss-weight
buffers are deliberately ignored, torchvision's ``fc`` too) and every Flax leaf filled; else
the command prints a one-line error plus the offending keys and exits with status 2.
Reading the ``.pth`` file and the architecture off its keys:
:mod:`gac_jax.weights.torch_state_dict`.
"""

from __future__ import annotations

import argparse
import datetime
import re
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from gac_jax.models import naming
from gac_jax.models.detector import Detector
from gac_jax.models.ground_aware_conv import OFFSET_FORMULAS
from gac_jax.models.resnet import RESNET_SPECS, ResNet
from gac_jax.weights.pretrained import WeightsError, save_converted
from gac_jax.weights.torch_state_dict import (
    GAC_PREFIX,
    describe_resnet,
    gac_head_layout,
    read_torch_state_dict,
    resnet_layout,
    sha256_file,
)

RELEASED_OFFSET_FORMULA = "reference_v1"
TORCHVISION_IGNORED = (r"fc\.weight", r"fc\.bias")


# ---------------------------------------------------------------------------------------------
# conversion with checks


def _abstract_variables(model, *args) -> dict[str, Any]:
    variables = jax.eval_shape(lambda: model.init(jax.random.key(0), *args, train=False))
    return {c: variables[c] for c in ("params", "batch_stats") if c in variables}


def _natural(text: str) -> list:
    """Sort key that orders ``layer3_6`` before ``layer3_10``."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def _group_by_module(paths: list[str]) -> list[str]:
    """``['params/a/b/kernel', 'batch_stats/a/c/mean', ...]`` -> ``['a/b (params/kernel)',
    'a/c (batch_stats/mean, ...)']`` in natural order."""
    groups: dict[str, list[str]] = {}
    for path in paths:
        collection, *module, leaf = path.split("/")
        groups.setdefault("/".join(module), []).append(f"{collection}/{leaf}")
    return [f"{m} ({', '.join(sorted(groups[m]))})" for m in sorted(groups, key=_natural)]


def convert_checked(
    state_dict: Mapping[str, Any],
    rules,
    template: Mapping[str, Any],
    ignored=(),
    what: str = "the model",
    hint: str = "",
) -> naming.Conversion:
    """:func:`naming.convert_state_dict` that insists on a complete, exact conversion.

    Raises:
      WeightsError: listing every shape mismatch, every unused tensor and every unfilled Flax
        leaf (the message says how many of each; ``hint`` is appended).
    """
    mismatched: list[str] = []
    try:
        conversion = naming.convert_state_dict(state_dict, rules, template, ignored)
    except ValueError:
        usable = {}
        for key, value in state_dict.items():  # find every offender, not just the first
            try:
                naming.convert_state_dict({key: value}, rules, template, ignored)
                usable[key] = value
            except ValueError as e:
                mismatched.append(f"shape mismatch: {e}")
        conversion = naming.convert_state_dict(usable, rules, template, ignored)
    if mismatched or not conversion.complete:
        counts = []
        if mismatched:
            counts.append(f"{len(mismatched)} shape mismatches")
        if conversion.unused:
            counts.append(f"{len(conversion.unused)} unused tensors")
        if conversion.missing:
            counts.append(f"{len(conversion.missing)} Flax leaves not filled")
        details = mismatched + [f"unused tensor: {u}" for u in conversion.unused]
        details += [f"not filled: {m}" for m in _group_by_module(conversion.missing)]
        raise WeightsError(f"the weights do not fit {what}: {', '.join(counts)}{hint}", details)
    return conversion


def convert_torchvision_resnet(
    state_dict: Mapping[str, Any], depth: int | None = None, num_stages: int = 4
) -> tuple[dict[str, Any], dict[str, Any]]:
    """torchvision ResNet state dict -> variables of ``ResNet(depth, num_stages, width)``.

    ``depth`` defaults to the one the block counts imply; the width is read from ``conv1``.
    ``fc.*`` is ignored; for ``num_stages < 4`` ``layer4.*`` must be absent (use 4 and let
    :func:`gac_jax.weights.pretrained.load_backbone_init` drop it). Returns ``(variables, model)``
    with ``model = {'depth', 'width', 'num_stages'}``.
    """
    layout = resnet_layout(state_dict)
    if layout["width"] is None:
        raise WeightsError("not a torchvision ResNet state dict: no 'conv1.weight' key")
    depth = layout["depth"] if depth is None else depth
    if depth is None:
        raise WeightsError(
            f"cannot tell the ResNet depth of {describe_resnet(layout)}; pass --depth"
        )
    model = {"depth": int(depth), "width": layout["width"], "num_stages": int(num_stages)}
    template = _abstract_variables(
        ResNet(depth=model["depth"], num_stages=num_stages, width=model["width"]),
        jnp.zeros((1, 64, 64, 3)),
    )
    hint = ""
    if layout["depth"] != depth or len(layout["blocks"]) != num_stages:
        hint = f" (the file holds {describe_resnet(layout)})"
    what = f"a {num_stages}-stage ResNet-{depth} of width {model['width']}"
    conversion = convert_checked(
        state_dict, naming.resnet_rules(), template, TORCHVISION_IGNORED, what, hint
    )
    return conversion.variables, model


def gac_model_settings(
    state_dict: Mapping[str, Any],
    config=None,
    overrides: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Detector settings for a reference GAC state dict: file < ``config`` < ``overrides``.

    Returns ``{'depth', 'width', 'num_classes', 'num_anchors', 'cls_features',
    'reg_features', 'regression_block', 'offset_formula'}``; ``offset_formula`` comes only from
    ``overrides`` (default ``reference_v1``), see the module docstring.
    """
    backbone = resnet_layout(state_dict, GAC_PREFIX)
    settings: dict[str, Any] = {"depth": backbone["depth"], "width": backbone["width"]}
    settings |= gac_head_layout(state_dict)
    settings |= {"regression_block": "gac", "offset_formula": RELEASED_OFFSET_FORMULA}
    if config is not None:
        from_config = config_model_settings(config)
        from_config.pop("offset_formula")  # describes the model to run, not these weights
        settings |= {k: v for k, v in from_config.items() if v is not None}
    settings |= {k: v for k, v in (overrides or {}).items() if v is not None}
    missing = [
        k for k in ("depth", "width", "num_classes", "num_anchors") if settings.get(k) is None
    ]
    if missing:
        raise WeightsError(
            f"cannot tell {', '.join(missing)} from the file (not a GroundAwareYolo3D state "
            "dict?); pass them as flags or with --config"
        )
    if settings["regression_block"] != "gac":
        raise WeightsError(
            f"regression_block {settings['regression_block']!r}: the reference weights are of "
            "GroundAwareYolo3D, i.e. regression_block 'gac'"
        )
    if settings["offset_formula"] not in OFFSET_FORMULAS:
        raise WeightsError(f"offset_formula must be one of {OFFSET_FORMULAS}")
    return settings


def _get(config, dotted: str):
    node = config
    for part in dotted.split("."):
        try:
            if part not in node:
                return None
            node = node[part]
        except TypeError:
            return None
    return node


def config_model_settings(config) -> dict[str, Any]:
    """Detector settings found in a config (None where absent); see the module docstring."""
    classes = _get(config, "data.classes")
    num_classes = _get(config, "model.num_classes")
    if num_classes is None and classes is not None:
        num_classes = len(classes)
    num_anchors = _get(config, "model.num_anchors")
    ratios = _get(config, "anchors.ratios")
    scales = _get(config, "anchors.scales")
    if scales is None:
        scales = _get(config, "anchors.num_scales")
    if num_anchors is None and ratios is not None and scales is not None:
        num_scales = scales if isinstance(scales, int) else len(scales)
        num_anchors = len(ratios) * num_scales
    return {
        "depth": _get(config, "model.backbone_depth"),
        "width": _get(config, "model.backbone_width"),
        "num_classes": num_classes,
        "num_anchors": num_anchors,
        "cls_features": _get(config, "model.cls_features"),
        "reg_features": _get(config, "model.reg_features"),
        "regression_block": _get(config, "model.regression_block"),
        "offset_formula": _get(config, "model.gac.offset_formula"),
    }


def make_detector(settings: Mapping[str, Any]) -> Detector:
    kwargs = {k: settings[k] for k in ("depth", "width", "num_classes", "num_anchors")}
    kwargs |= {k: settings[k] for k in ("cls_features", "reg_features") if k in settings}
    return Detector(
        **kwargs,
        regression_block=settings.get("regression_block", "gac"),
        offset_formula=settings.get("offset_formula", RELEASED_OFFSET_FORMULA),
    )


def convert_gac(state_dict: Mapping[str, Any], settings: Mapping[str, Any]) -> dict[str, Any]:
    """Reference ``GroundAwareYolo3D`` state dict -> ``Detector`` variables (checked)."""
    template = _abstract_variables(
        make_detector(settings), jnp.zeros((1, 64, 64, 3)), jnp.zeros((1, 3, 4))
    )
    file_backbone = resnet_layout(state_dict, GAC_PREFIX)
    file_head = gac_head_layout(state_dict)
    disagree = [
        f"{k}={settings[k]} (file: {v})"
        for k, v in {
            **file_head,
            "depth": file_backbone["depth"],
            "width": file_backbone["width"],
        }.items()
        if v is not None and settings.get(k) is not None and settings[k] != v
    ]
    hint = f" (asked for {', '.join(disagree)})" if disagree else ""
    what = (
        f"a Detector(depth={settings['depth']}, width={settings['width']}, "
        f"num_classes={settings['num_classes']}, num_anchors={settings['num_anchors']})"
    )
    conversion = convert_checked(
        state_dict, naming.detector_rules(), template, naming.DETECTOR_IGNORED, what, hint
    )
    return conversion.variables


# ---------------------------------------------------------------------------------------------
# command line


def _source_meta(path: Path, kind: str, model: Mapping[str, Any]) -> dict[str, Any]:
    import torch

    return {
        "kind": kind,
        "source": str(path.resolve()),
        "sha256": sha256_file(path),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "torch_version": torch.__version__,
        "model": dict(model),
    }


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m gac_jax.weights.convert",
        description="Convert PyTorch weights to gac-jax (orbax) checkpoints.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    rn = sub.add_parser("torchvision-resnet", help="torchvision ImageNet ResNet -> ResNet")
    rn.add_argument("input", type=Path, help="torchvision resnet*.pth")
    rn.add_argument("out_dir", type=Path, help="output folder (gets checkpoints/0)")
    rn.add_argument("--depth", type=int, choices=sorted(RESNET_SPECS), help="default: from file")
    rn.add_argument("--num-stages", type=int, default=4, choices=(1, 2, 3, 4))
    rn.add_argument("--overwrite", action="store_true", help="replace earlier converted weights")

    gac = sub.add_parser("gac", help="reference GroundAwareYolo3D state dict -> Detector")
    gac.add_argument("input", type=Path, help="e.g. GroundAware_pretrained.pth")
    gac.add_argument("out_dir", type=Path, help="output folder (gets checkpoints/0)")
    gac.add_argument("--config", help="config file[:arg] whose model the weights must fit")
    gac.add_argument("--depth", type=int, choices=sorted(RESNET_SPECS))
    gac.add_argument("--width", type=int, help="ResNet base width (64)")
    gac.add_argument("--num-classes", type=int)
    gac.add_argument("--num-anchors", type=int)
    gac.add_argument(
        "--offset-formula",
        choices=OFFSET_FORMULAS,
        default=RELEASED_OFFSET_FORMULA,
        help="GAC base offset the weights were trained with (default %(default)s: release 1.0)",
    )
    gac.add_argument("--overwrite", action="store_true", help="replace earlier converted weights")
    return parser


# 'paper' and 'reference' are one formula written two ways (h (v - cy) / (2 EL - h)); only
# release 1.0's 'reference_v1' (missing parentheses) gives other offsets.
_FORMULA_VALUES = {"paper": "paper", "reference": "paper", "reference_v1": "reference_v1"}


def offset_formula_note(config_name, configured: str | None, trained: str) -> str | None:
    """The note printed when the config would run the weights with other GAC offsets.

    ``configured``: the config's ``model.gac.offset_formula`` (None: no config / not set);
    ``trained``: the formula the weights are recorded as trained with. None when both give
    the same offsets ('paper' and 'reference' are algebraically identical).
    """
    if configured is None or _FORMULA_VALUES.get(configured) == _FORMULA_VALUES[trained]:
        return None
    return (
        f"note: {config_name} sets model.gac.offset_formula={configured!r}, but these "
        f"weights are recorded as trained with {trained!r}, whose GAC offsets differ; run them "
        f"with model.gac.offset_formula={trained}"
    )


def run(args: argparse.Namespace) -> Path:
    """Runs a parsed command; returns the checkpoint folder. Raises WeightsError."""
    state_dict = read_torch_state_dict(args.input)
    if args.command == "torchvision-resnet":
        variables, model = convert_torchvision_resnet(state_dict, args.depth, args.num_stages)
        kind = "torchvision_resnet"
    else:
        config = None
        if args.config:
            from gac_jax.config import ConfigError, load_config

            try:
                config = load_config(args.config)
            except ConfigError as e:
                raise WeightsError(str(e)) from e
        flags = {
            "depth": args.depth,
            "width": args.width,
            "num_classes": args.num_classes,
            "num_anchors": args.num_anchors,
            "offset_formula": args.offset_formula,
        }
        model = gac_model_settings(state_dict, config, flags)
        variables = convert_gac(state_dict, model)
        configured = config_model_settings(config).get("offset_formula") if config else None
        note = offset_formula_note(args.config, configured, model["offset_formula"])
        if note:
            print(note, file=sys.stderr)
        kind = "gac_detector"
    meta = _source_meta(args.input, kind, model)
    return save_converted(args.out_dir, variables, meta, overwrite=args.overwrite)


def main(argv: list[str] | None = None) -> int:
    """CLI entry point; returns the exit status (0 ok, 2 bad weights / files / arguments)."""
    args = _parser().parse_args(argv)
    try:
        path = run(args)
    except WeightsError as e:
        print(f"error: {e.full_text()}", file=sys.stderr)
        return 2
    except OSError as e:  # e.g. OUT_DIR not writable
        print(f"error: cannot write {args.out_dir}: {e}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
