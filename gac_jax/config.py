"""Configs are Python files with ``get_config(arg=None) -> ml_collections.ConfigDict``.

``load_config("configs/detect3d_kitti.py:car")`` imports the file and calls
``get_config("car")``. Command-line overrides are ``dotted.key=value`` strings,
parsed as Python literals when possible (``train.batch_size=4``,
``model.backbone_depth=34``, ``data.classes="('Car',)"``), else kept as strings.
Unknown keys are rejected, so a typo never silently does nothing.
"""

from __future__ import annotations

import ast
import importlib.util
import json
import os
from pathlib import Path

import ml_collections

REPO_CONFIGS = Path(__file__).resolve().parents[1] / "configs"


class ConfigError(ValueError):
    """A config file or override is invalid; the message says which and why."""


def share_of_images(data, key: str) -> float:
    """``data[key]`` (0 when absent), a share of the training images an augmentation touches.

    Raises:
      ConfigError: it is not in [0, 1].
    """
    share = float(data.get(key, 0.0))
    if not 0.0 <= share <= 1.0:
        raise ConfigError(f"data.{key}={share}: the share of training images must be in [0, 1]")
    return share


def resolve_config_path(spec: str) -> tuple[Path, str | None]:
    """Splits ``path[:arg]`` and finds the file (as given, or under ``configs/``)."""
    path_str, arg = spec, None
    if ":" in spec and not Path(spec).exists():
        path_str, arg = spec.rsplit(":", 1)
    path = Path(path_str)
    if not path.exists():
        candidate = REPO_CONFIGS / path.name
        if not candidate.suffix:
            candidate = candidate.with_suffix(".py")
        if candidate.exists():
            path = candidate
        else:
            raise ConfigError(f"config file not found: {path_str}")
    return path, arg


def load_config(spec: str) -> ml_collections.ConfigDict:
    """Loads ``path[:arg]`` and returns its ``get_config(arg)``."""
    path, arg = resolve_config_path(spec)
    module_name = f"gac_jax_config_{path.stem}_{abs(hash(str(path.resolve())))}"
    module_spec = importlib.util.spec_from_file_location(module_name, path)
    if module_spec is None or module_spec.loader is None:
        raise ConfigError(f"{path}: cannot import config file")
    module = importlib.util.module_from_spec(module_spec)
    try:
        module_spec.loader.exec_module(module)
    except Exception as e:  # noqa: BLE001 - report any import problem as a config error
        raise ConfigError(f"{path}: error while importing config: {e}") from e
    if not hasattr(module, "get_config"):
        raise ConfigError(f"{path}: config files must define get_config(arg=None)")
    config = module.get_config(arg) if arg is not None else module.get_config()
    if not isinstance(config, ml_collections.ConfigDict):
        raise ConfigError(f"{path}: get_config() must return an ml_collections.ConfigDict")
    return config


def _parse_value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def apply_overrides(config: ml_collections.ConfigDict, overrides: list[str]) -> None:
    """Applies ``key.sub=value`` overrides in place; unknown keys raise ConfigError."""
    for item in overrides:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key.sub=value")
        key, raw = item.split("=", 1)
        parts = key.strip().split(".")
        node = config
        for part in parts[:-1]:
            if part not in node:
                raise ConfigError(f"override {item!r}: unknown config key {key!r}")
            node = node[part]
        leaf = parts[-1]
        if leaf not in node:
            raise ConfigError(f"override {item!r}: unknown config key {key!r}")
        value = _parse_value(raw)
        old = node[leaf]
        if isinstance(old, tuple) and isinstance(value, list):
            value = tuple(value)
        if isinstance(old, bool) and isinstance(value, str) and value.lower() in ("true", "false"):
            value = value.lower() == "true"  # shell spelling: log.tensorboard=false
        if isinstance(old, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        try:
            node[leaf] = value
        except (TypeError, ValueError) as e:
            raise ConfigError(f"override {item!r}: {e}") from e


def to_json(config: ml_collections.ConfigDict) -> str:
    return json.dumps(config.to_dict(), indent=2, sort_keys=True, default=str)


def save_config(config: ml_collections.ConfigDict, workdir: str | os.PathLike) -> Path:
    """Writes the resolved config to ``workdir/config.json`` (atomically)."""
    from gac_jax.data.files import atomic_write

    path = Path(workdir) / "config.json"
    with atomic_write(path) as f:
        f.write(to_json(config) + "\n")
    return path
