"""Reading PyTorch ``.pth`` state dicts and telling what they hold (:mod:`gac_jax.weights.convert`).

:func:`read_torch_state_dict` loads a checkpoint as numpy arrays (``torch`` is an optional
extra: ``pip install 'gac-jax[torch]'``); :func:`resnet_layout` and :func:`gac_head_layout`
read the architecture settings (block counts, width, anchors, classes, branch widths) off the
key names and tensor shapes, torchvision's ResNet naming and the reference GroundAwareYolo3D's.
"""

from __future__ import annotations

import hashlib
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from gac_jax.models.detection_head import NUM_REGRESSION
from gac_jax.models.resnet import RESNET_SPECS
from gac_jax.weights.pretrained import WeightsError

GAC_PREFIX = "core.backbone."
_WRAPPER_KEYS = ("state_dict", "model", "model_state_dict")


# ---------------------------------------------------------------------------------------------
# reading .pth files


def read_torch_state_dict(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Loads a PyTorch checkpoint as ``{key: numpy array}`` (``torch.load(weights_only=True)``).

    Accepts a raw ``state_dict`` or a dict holding one under ``'state_dict'``, ``'model'`` or
    ``'model_state_dict'``; a ``'module.'`` prefix on every key (DataParallel) is removed.
    Half-precision tensors are widened to float32.

    Raises:
      WeightsError: torch missing, file missing/unreadable/truncated, or no tensor dict inside.
    """
    try:
        import torch
    except ImportError as e:
        raise WeightsError(
            "reading PyTorch .pth files needs torch: pip install 'gac-jax[torch]'"
        ) from e
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"{path}: file not found")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for bad files
        reason = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise WeightsError(
            f"{path}: cannot read as a PyTorch checkpoint (truncated or not a .pth file?): "
            f"{type(e).__name__}: {reason}"
        ) from e
    while isinstance(obj, Mapping) and not _all_tensors(obj, torch):
        inner = next((obj[k] for k in _WRAPPER_KEYS if isinstance(obj.get(k), Mapping)), None)
        if inner is None:
            break
        obj = inner
    if not isinstance(obj, Mapping) or not obj:
        raise WeightsError(f"{path}: holds no state dict (got {type(obj).__name__})")
    bad = [k for k, v in obj.items() if not isinstance(v, torch.Tensor)]
    if bad:
        raise WeightsError(
            f"{path}: not a state dict: {len(bad)} entries are not tensors "
            f"(looked inside {'/'.join(_WRAPPER_KEYS)})",
            [f"{k} ({type(obj[k]).__name__})" for k in bad],
        )
    keys = list(obj)
    strip = all(k.startswith("module.") for k in keys)
    out = {}
    for key, tensor in obj.items():
        tensor = tensor.detach().cpu()
        if tensor.is_floating_point() and tensor.dtype != torch.float64:
            tensor = tensor.float()
        out[key.removeprefix("module.") if strip else key] = tensor.numpy()
    return out


def _all_tensors(obj: Mapping, torch) -> bool:
    return all(isinstance(v, torch.Tensor) for v in obj.values())


def sha256_file(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------
# what a state dict holds


def resnet_layout(state_dict: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Block kind, blocks per stage, depth (None if unknown) and width of the ResNet keys
    under ``prefix`` (torchvision naming)."""
    blocks: dict[int, set[int]] = {}
    bottleneck = False
    pattern = re.compile(rf"{re.escape(prefix)}layer(\d+)\.(\d+)\.(\w+)")
    for key in state_dict:
        if m := pattern.match(key):
            blocks.setdefault(int(m.group(1)), set()).add(int(m.group(2)))
            bottleneck |= m.group(3) == "conv3"
    counts = tuple(len(blocks.get(s, ())) for s in range(1, 5))
    counts = counts[: next((i for i, n in enumerate(counts) if n == 0), 4)]
    kind = "bottleneck" if bottleneck else "basic"
    depth = next(
        (
            d
            for d, (k, b) in RESNET_SPECS.items()
            if k == kind and counts and b[: len(counts)] == counts
        ),
        None,
    )
    conv1 = state_dict.get(f"{prefix}conv1.weight")
    width = int(np.shape(conv1)[0]) if conv1 is not None else None
    return {"kind": kind, "blocks": counts, "depth": depth, "width": width}


def describe_resnet(layout: Mapping[str, Any]) -> str:
    """'a ResNet-50 (blocks 3-4-6-3, width 64)' for a :func:`resnet_layout` (error texts)."""
    blocks = "-".join(map(str, layout["blocks"])) or "none"
    name = f"ResNet-{layout['depth']}" if layout["depth"] else f"{layout['kind']}-block ResNet"
    return f"a {name} (blocks {blocks}, width {layout['width']})"


def gac_head_layout(state_dict: Mapping[str, Any]) -> dict[str, int]:
    """num_anchors, num_classes, cls_features, reg_features implied by the reference head."""
    out: dict[str, int] = {}
    cls_out = state_dict.get("bbox_head.cls_feature_extraction.6.weight")
    reg_out = state_dict.get("bbox_head.reg_feature_extraction.7.weight")
    if reg_out is not None and np.shape(reg_out)[0] % NUM_REGRESSION == 0:
        out["num_anchors"] = np.shape(reg_out)[0] // NUM_REGRESSION
        if cls_out is not None and np.shape(cls_out)[0] % out["num_anchors"] == 0:
            out["num_classes"] = np.shape(cls_out)[0] // out["num_anchors"] - 1
    for name, key in (
        ("cls_features", "bbox_head.cls_feature_extraction.0.weight"),
        ("reg_features", "bbox_head.reg_feature_extraction.1.weight"),
    ):
        if key in state_dict:
            out[name] = int(np.shape(state_dict[key])[0])
    return out
