"""The export folder: ``model.onnx`` + ``export.json``, written atomically and checked on use.

``export.json`` records where the weights came from (workdir and step, or converted weights),
the task, the input size, the opset, the network-relevant config (compared on use), the full
config, library versions, the sha256 of ``model.onnx`` and what decoding needs that the ONNX
file does not hold (classes, anchor layout and priors file for the detector; the input view
and folded prior mean for the depth net). :func:`read_export` refuses a folder whose
``model.onnx`` does not match its sha256 (truncated or replaced file), and
:func:`check_export` one made from other weights, config or input size, naming what differs.
"""

from __future__ import annotations

import datetime
import hashlib
import importlib.metadata
import json
import os
from pathlib import Path

from gac_jax.data.files import KittiFormatError, atomic_write, write_bytes_atomic

MODEL_FILE = "model.onnx"
EXPORT_FILE = "export.json"
FORMAT_VERSION = 1
DEFAULT_OPSET = 17
LIBRARIES = ("gac-jax", "jax", "flax", "numpy", "onnx")
# what an export must agree on with the run that uses it
COMPARED = ("task", "weights", "input_size", "network_config")


def library_versions(names=LIBRARIES) -> dict[str, str]:
    out = {}
    for name in names:
        try:
            out[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def write_export(out_dir: str | os.PathLike, model_bytes: bytes, meta: dict) -> dict:
    """Writes ``model.onnx`` then ``export.json`` (both atomically); returns the metadata."""
    out = Path(out_dir)
    meta = {
        "format": FORMAT_VERSION,
        "model_file": MODEL_FILE,
        "sha256": sha256_bytes(model_bytes),
        "size_bytes": len(model_bytes),
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "libraries": library_versions(),
        **meta,
    }
    meta = json.loads(json.dumps(meta, default=str))
    write_bytes_atomic(out / MODEL_FILE, model_bytes)
    with atomic_write(out / EXPORT_FILE) as f:
        json.dump(meta, f, indent=2)
        f.write("\n")
    return meta


def read_export(out_dir: str | os.PathLike) -> dict:
    """``export.json`` of a folder, after checking that ``model.onnx`` is the file it describes.

    Raises:
      KittiFormatError: missing or unreadable ``export.json``, missing ``model.onnx`` or a
        ``model.onnx`` whose sha256 differs (naming the file).
    """
    out = Path(out_dir)
    path = out / EXPORT_FILE
    if not path.is_file():
        raise KittiFormatError(
            path, "no export description (python -m gac_jax.deploy.export writes it)"
        )
    try:
        meta = json.loads(path.read_text())
        expected = meta["sha256"]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as e:
        raise KittiFormatError(path, f"not an export description ({e})") from None
    model = out / MODEL_FILE
    if not model.is_file():
        raise KittiFormatError(model, f"model file missing (described by {path})")
    actual = sha256_bytes(model.read_bytes())
    if actual != expected:
        raise KittiFormatError(
            model,
            f"corrupted or replaced: sha256 {actual[:12]}... differs from {expected[:12]}... "
            f"recorded in {EXPORT_FILE}; export again (python -m gac_jax.deploy.export)",
        )
    return meta


def _differences(stored, wanted, prefix: str = "") -> list[str]:
    if isinstance(stored, dict) and isinstance(wanted, dict):
        out = []
        for key in sorted(set(stored) | set(wanted)):
            out += _differences(stored.get(key), wanted.get(key), f"{prefix}{key}.")
        return out
    if stored != wanted:
        return [f"{prefix.rstrip('.')} (export: {stored!r}, run: {wanted!r})"]
    return []


def check_export(out_dir: str | os.PathLike, meta: dict, expected: dict) -> None:
    """Refuses an export made for other weights / config / input size than ``expected``.

    Args:
      meta: :func:`read_export` of the folder; expected: the run's values of ``COMPARED``.

    Raises:
      KittiFormatError: naming ``model.onnx`` and every differing entry.
    """
    wanted = json.loads(json.dumps({k: expected[k] for k in COMPARED}, default=str))
    diffs = _differences({k: meta.get(k) for k in COMPARED}, wanted)
    if diffs:
        shown = "; ".join(diffs[:4]) + (f"; ... {len(diffs) - 4} more" if len(diffs) > 4 else "")
        raise KittiFormatError(
            Path(out_dir) / MODEL_FILE,
            f"stale export, made for another run: {shown}. Delete {out_dir} (it is exported "
            "again) or export these weights elsewhere",
        )
