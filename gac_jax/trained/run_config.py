"""The config of a run folder: ``WORKDIR/config.json`` (written by the trainer) or ``--config``.

``evaluate.py --workdir W`` (model mode), ``python -m gac_jax.cli.predict`` and the export read
a training workdir: ``W/config.json`` (the resolved config the trainer wrote) and
``W/checkpoints/<step>``; ``--config`` replaces the stored config (needed for converted
weights, which come without one).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import ml_collections

from gac_jax.config import ConfigError, apply_overrides, load_config
from gac_jax.data.files import KittiFormatError


def load_run_config(
    workdir: str | os.PathLike,
    config_spec: str | None = None,
    overrides: list[str] | None = None,
    data_root: str | os.PathLike | None = None,
) -> ml_collections.ConfigDict:
    """The config of a run: ``--config`` if given, else ``WORKDIR/config.json``.

    ``data_root`` (``--data``) points ``data.root`` at a KITTI-format folder
    (``data.source = 'kitti'``); ``overrides`` are ``key.sub=value`` strings.

    Raises:
      KittiFormatError: no config.json (naming the file and how to get one), or
        an invalid config / override.
    """
    workdir = Path(workdir)
    try:
        if config_spec:
            config = load_config(config_spec)
        else:
            path = workdir / "config.json"
            if not path.is_file():
                raise KittiFormatError(
                    path,
                    "run config not found: the trainer writes it (python train.py --task ... "
                    f"--workdir {workdir}); for converted weights pass --config",
                )
            try:
                config = ml_collections.ConfigDict(json.loads(path.read_text()))
            except (json.JSONDecodeError, UnicodeDecodeError) as e:
                raise KittiFormatError(path, f"not a JSON config ({e})") from None
        apply_overrides(config, list(overrides or []))
    except ConfigError as e:
        raise KittiFormatError(config_spec or workdir / "config.json", str(e)) from None
    if data_root is not None:
        config.data.source = "kitti"
        config.data.root = str(data_root)
    return config


def load_workdir_config(workdir: str | Path) -> ml_collections.ConfigDict:
    """The resolved config a depth run saved in ``WORKDIR/config.json``."""
    path = Path(workdir) / "config.json"
    if not path.is_file():
        raise KittiFormatError(path, "no config.json: not a training workdir")
    return ml_collections.ConfigDict(json.loads(path.read_text()))
