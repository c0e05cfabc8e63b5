"""PyTorch state-dict keys -> Flax variable paths, as data, plus the conversion routine.

A torch key is split into its *module* path and its *leaf* (``layer1.0.bn1.running_mean``
-> ``layer1.0.bn1`` + ``running_mean``). A :class:`Rule` maps the module path (regex,
full match) to a Flax module path (``'/'``-separated template, ``\\1`` etc. for groups); its
``kind`` says how each leaf lands in the Flax variables:

==============  ====================  ===================================  ==================
kind            torch leaf            Flax leaf                            transform
==============  ====================  ===================================  ==================
``conv``        ``weight`` [O,I,h,w]  ``params/<module>/kernel`` [h,w,I,O] OIHW -> HWIO
``conv``        ``bias``              ``params/<module>/bias``             none
``batch_norm``  ``weight``            ``params/<module>/scale``            none
``batch_norm``  ``bias``              ``params/<module>/bias``             none
``batch_norm``  ``running_mean``      ``batch_stats/<module>/mean``        none
``batch_norm``  ``running_var``       ``batch_stats/<module>/var``         none
``batch_norm``  ``num_batches_tracked``  (ignored: Flax BN keeps no counter)
``gate``        ``alpha`` [1]         ``params/<module>/alpha`` [1]        none
==============  ====================  ===================================  ==================

Rule tables: :func:`resnet_rules` (torchvision ResNet keys, any prefix), :data:`HEAD_RULES`
(the reference ``GroundAwareHead``, prefix ``bbox_head.``), :func:`detector_rules` (the
whole reference ``GroundAwareYolo3D`` -> :class:`gac_jax.models.detector.Detector`) and
:func:`depth_unet_rules` (the reference ``MonoDepth`` ->
:class:`gac_jax.models.depth_unet.DepthUNet`). :data:`DETECTOR_IGNORED` lists reference
buffers that are loss constants, not model state; :data:`DEPTH_UNET_IGNORED` the depth net's
``prior_mean`` (a module constant).

:func:`convert_state_dict` applies a table to a flat ``{key: numpy array}`` dict and reports
what was ignored, what matched nothing (``unused``) and which Flax leaves stayed unfilled
(``missing``); it needs no torch.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from flax import traverse_util


def _identity(x: np.ndarray) -> np.ndarray:
    return x


def _oihw_to_hwio(x: np.ndarray) -> np.ndarray:
    if x.ndim != 4:
        raise ValueError(f"conv weight must be 4-D OIHW, got shape {x.shape}")
    return np.transpose(x, (2, 3, 1, 0))


# kind -> torch leaf -> (collection, flax leaf, transform); None = known and ignored.
LEAF_MAPS: dict[str, dict[str, tuple[str, str, Callable[[np.ndarray], np.ndarray]] | None]] = {
    "conv": {
        "weight": ("params", "kernel", _oihw_to_hwio),
        "bias": ("params", "bias", _identity),
    },
    "batch_norm": {
        "weight": ("params", "scale", _identity),
        "bias": ("params", "bias", _identity),
        "running_mean": ("batch_stats", "mean", _identity),
        "running_var": ("batch_stats", "var", _identity),
        "num_batches_tracked": None,
    },
    "gate": {"alpha": ("params", "alpha", _identity)},
}


@dataclasses.dataclass(frozen=True)
class Rule:
    """``torch``: regex fully matching a torch module path; ``flax``: Flax module path
    template ('/'-separated, may use the regex groups); ``kind``: a key of :data:`LEAF_MAPS`."""

    torch: str
    flax: str
    kind: str

    def __post_init__(self):
        if self.kind not in LEAF_MAPS:
            raise ValueError(f"unknown rule kind {self.kind!r}; choose one of {sorted(LEAF_MAPS)}")


def resnet_rules(torch_prefix: str = "", flax_prefix: str = "") -> tuple[Rule, ...]:
    """Rules for torchvision ResNet keys -> :class:`gac_jax.models.resnet.ResNet`.

    Args:
      torch_prefix: prefix of the backbone keys, e.g. ``'core.backbone.'`` ('' for a plain
        torchvision checkpoint such as ``resnet101-5d3b4d8f.pth``; its ``fc.*`` keys and, for
        a 3-stage model, ``layer4.*`` keys come back as ``unused``).
      flax_prefix: Flax path of the ResNet module, e.g. ``'backbone/'``.
    """
    p, f = re.escape(torch_prefix), flax_prefix
    block = r"layer(\d+)\.(\d+)\."
    return (
        Rule(rf"{p}conv1", f"{f}conv1", "conv"),
        Rule(rf"{p}bn1", f"{f}bn1", "batch_norm"),
        Rule(rf"{p}{block}(conv\d)", rf"{f}layer\1_\2/\3", "conv"),
        Rule(rf"{p}{block}(bn\d)", rf"{f}layer\1_\2/\3", "batch_norm"),
        Rule(rf"{p}{block}downsample\.0", rf"{f}layer\1_\2/downsample_0", "conv"),
        Rule(rf"{p}{block}downsample\.1", rf"{f}layer\1_\2/downsample_1", "batch_norm"),
    )


# Reference GroundAwareHead (nn.Sequential indices) -> DetectionHead names.
HEAD_RULES: tuple[Rule, ...] = (
    Rule(r"bbox_head\.cls_feature_extraction\.0", "head/cls_conv1", "conv"),
    Rule(r"bbox_head\.cls_feature_extraction\.3", "head/cls_conv2", "conv"),
    Rule(r"bbox_head\.cls_feature_extraction\.6", "head/cls_out", "conv"),
    Rule(r"bbox_head\.reg_feature_extraction\.0", "head/gac", "gate"),
    Rule(r"bbox_head\.reg_feature_extraction\.0\.disp_create\.0", "head/gac/offset_conv", "conv"),
    Rule(r"bbox_head\.reg_feature_extraction\.0\.extract", "head/gac/extract", "conv"),
    Rule(r"bbox_head\.reg_feature_extraction\.1", "head/reg_conv1", "conv"),
    Rule(r"bbox_head\.reg_feature_extraction\.2", "head/reg_bn1", "batch_norm"),
    Rule(r"bbox_head\.reg_feature_extraction\.4", "head/reg_conv2", "conv"),
    Rule(r"bbox_head\.reg_feature_extraction\.5", "head/reg_bn2", "batch_norm"),
    Rule(r"bbox_head\.reg_feature_extraction\.7", "head/reg_out", "conv"),
)

# Reference buffers that are loss constants (focal balance weight, regression weights).
DETECTOR_IGNORED: tuple[str, ...] = (
    r"bbox_head\.balance_weights",
    r"bbox_head\.loss_cls\.balance_weights",
    r"bbox_head\.regression_weight",
)


def detector_rules() -> tuple[Rule, ...]:
    """Rules for the reference ``GroundAwareYolo3D`` state dict -> ``Detector`` variables."""
    return resnet_rules("core.backbone.", "backbone/") + HEAD_RULES


# Reference MonoDepth ``UNet_Core`` decoder and heads -> DepthUNet names (``up{i}`` stages).
DEPTH_UNET_RULES: tuple[Rule, ...] = (
    Rule(r"core\.up(\d)\.conv\.conv0", r"up\1/gac", "gate"),
    Rule(r"core\.up(\d)\.conv\.conv0\.disp_create\.0", r"up\1/gac/offset_conv", "conv"),
    Rule(r"core\.up(\d)\.conv\.conv0\.extract", r"up\1/gac/extract", "conv"),
    Rule(r"core\.up(\d)\.conv\.conv1\.0", r"up\1/conv1", "conv"),
    Rule(r"core\.up(\d)\.conv\.conv1\.1", r"up\1/bn1", "batch_norm"),
    Rule(r"core\.up(\d)\.conv\.conv2\.0", r"up\1/conv2", "conv"),  # DCNv2 weight, bias
    Rule(r"core\.up(\d)\.conv\.conv2\.0\.conv_offset", r"up\1/conv2/conv_offset", "conv"),
    Rule(r"core\.up(\d)\.conv\.conv2\.1", r"up\1/bn2", "batch_norm"),
    Rule(r"core\.out_scale_(\d)\.conv", r"out_scale_\1", "conv"),
    Rule(r"core\.outc\.conv", "out_scale_1", "conv"),
)

# ``prior_mean`` is the constant ``DepthUNet(prior_mean=float(state_dict['prior_mean']))``.
DEPTH_UNET_IGNORED: tuple[str, ...] = (r"prior_mean",)


def depth_unet_rules() -> tuple[Rule, ...]:
    """Rules for the reference ``MonoDepth`` state dict -> ``DepthUNet`` variables (use
    ``decoder_conv='deformable'`` for the reference layout; ``conv_offset`` keys come back
    ``unused`` for a plain-conv model)."""
    return resnet_rules("core.backbone.", "backbone/") + DEPTH_UNET_RULES


@dataclasses.dataclass
class Conversion:
    """Result of :func:`convert_state_dict`.

    Attributes:
      variables: nested ``{'params': ..., 'batch_stats': ...}`` dict of numpy arrays holding
        every converted leaf (only those).
      ignored: torch keys deliberately skipped (``ignored`` patterns, BN counters).
      unused: torch keys that map to no Flax leaf (no rule, unknown leaf, or a target the
        template lacks), each as ``'key (reason)'``.
      missing: '/'-joined Flax leaf paths of the template that no torch key filled.
    """

    variables: dict[str, Any]
    ignored: list[str]
    unused: list[str]
    missing: list[str]

    @property
    def complete(self) -> bool:
        """True when every torch key was used or ignored and every template leaf filled."""
        return not self.unused and not self.missing

    def merged_into(self, base: Mapping[str, Any]) -> dict[str, Any]:
        """``base`` (e.g. fresh ``model.init`` variables) with the converted leaves replaced."""
        flat = traverse_util.flatten_dict(dict(base))
        flat.update(traverse_util.flatten_dict(self.variables))
        return traverse_util.unflatten_dict(flat)


def _find_rule(module: str, rules: Sequence[Rule]) -> tuple[Rule, re.Match] | None:
    found = [(r, m) for r in rules if (m := re.fullmatch(r.torch, module))]
    if len(found) > 1:
        raise ValueError(
            f"torch module {module!r} matches several rules: {[r.torch for r, _ in found]}"
        )
    return found[0] if found else None


def convert_state_dict(
    state_dict: Mapping[str, Any],
    rules: Sequence[Rule],
    template: Mapping[str, Any] | None = None,
    ignored: Sequence[str] = (),
) -> Conversion:
    """Converts a flat torch-style state dict into Flax variables.

    Args:
      state_dict: ``{torch key: array}`` (numpy arrays or anything ``np.asarray`` accepts).
      rules: the mapping table, e.g. :func:`detector_rules`.
      template: the Flax variables (or ``jax.eval_shape`` of ``model.init``) to fill; when
        given, targets outside it are reported as unused, shapes are checked (mismatch ->
        ``ValueError`` naming the key) and values are cast to the template dtypes.
      ignored: regexes of torch keys (full match) to skip silently.
    Returns:
      A :class:`Conversion`.
    Raises:
      ValueError: two keys map to one Flax leaf, a key matches several rules, or a shape
        does not match the template.
    """
    flat_template = traverse_util.flatten_dict(dict(template)) if template is not None else None
    out: dict[tuple[str, ...], np.ndarray] = {}
    source: dict[tuple[str, ...], str] = {}
    ignored_keys: list[str] = []
    unused: list[str] = []
    for key, value in state_dict.items():
        if any(re.fullmatch(pattern, key) for pattern in ignored):
            ignored_keys.append(key)
            continue
        module, _, leaf = key.rpartition(".")
        found = _find_rule(module, rules)
        if found is None:
            unused.append(f"{key} (no rule)")
            continue
        rule, match = found
        leaf_maps = LEAF_MAPS[rule.kind]
        if leaf not in leaf_maps:
            unused.append(f"{key} (leaf {leaf!r} unknown to a {rule.kind} rule)")
            continue
        target = leaf_maps[leaf]
        if target is None:
            ignored_keys.append(key)
            continue
        collection, flax_leaf, transform = target
        path = (collection, *match.expand(rule.flax).split("/"), flax_leaf)
        if path in source:
            raise ValueError(f"{key} and {source[path]} both map to {'/'.join(path)}")
        array = transform(np.asarray(value))
        if flat_template is not None:
            if path not in flat_template:
                unused.append(f"{key} (no Flax leaf {'/'.join(path)})")
                continue
            expected = flat_template[path]
            if tuple(expected.shape) != array.shape:
                raise ValueError(
                    f"{key}: converted shape {array.shape} does not match Flax "
                    f"{'/'.join(path)} shape {tuple(expected.shape)}"
                )
            array = array.astype(expected.dtype, copy=False)
        source[path] = key
        out[path] = array
    missing = []
    if flat_template is not None:
        missing = ["/".join(path) for path in flat_template if path not in out]
    return Conversion(
        variables=traverse_util.unflatten_dict(out),
        ignored=ignored_keys,
        unused=unused,
        missing=missing,
    )
