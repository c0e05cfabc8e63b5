"""Where a config's data lives: the embedded dataset cache and ``prepare_dataset``."""

from __future__ import annotations

from pathlib import Path

import jax
import ml_collections

from gac_jax.data import transforms
from gac_jax.data.cache import default_cache_dir
from gac_jax.data.files import KittiFormatError


def synthetic_config() -> ml_collections.ConfigDict:
    """The configs' ``data.synthetic`` block: what the embedded dataset is made of.

    ``rigs``: ``'kitti'`` (KITTI's rigs) or ``'multi'`` (eight vehicles, ground planes,
    :mod:`gac_jax.data.synthetic.rigs`); ``workers``: generator processes (0: one per
    core; the content does not depend on them). Both configs share it, so the detector
    and the depth network train on one generated dataset.
    """
    return ml_collections.ConfigDict(
        dict(
            num_frames=1000, seed=0, height=375, width=1242, val_fraction=0.5, rigs="kitti",
            workers=0,
        )
    )  # fmt: skip


def synthetic_dataset_dir(cfg: ml_collections.ConfigDict) -> Path:
    """Folder of the embedded dataset described by ``cfg`` (``data.synthetic``)."""
    if cfg.get("root"):
        return Path(cfg.root)
    s = cfg.synthetic
    name = f"synthetic_n{s.num_frames}_s{s.seed}_{s.height}x{s.width}_val{s.val_fraction:g}"
    rig_set = s.get("rigs", "kitti")
    return default_cache_dir() / (name if rig_set == "kitti" else f"{name}_{rig_set}rig")


def prepare_dataset(cfg: ml_collections.ConfigDict) -> Path:
    """Returns the dataset root, generating the embedded dataset on first use.

    ``cfg`` is the config's ``data`` block: ``source`` is ``'synthetic'`` (the
    embedded generator; ``root`` optional) or ``'kitti'`` (``root`` = a KITTI
    object folder or a prepared TFDS dataset). In a multi-process run, process
    0 generates and the others wait for it.
    """
    if cfg.source == "kitti":
        if not cfg.get("root"):
            raise KittiFormatError("<config>", "data.root must point at a KITTI folder")
        root = Path(cfg.root)
        if not root.exists():
            raise KittiFormatError(root, "dataset folder not found (data.root)")
        return root
    if cfg.source != "synthetic":
        raise ValueError(f"data.source must be 'synthetic' or 'kitti', got {cfg.source!r}")
    root = synthetic_dataset_dir(cfg)
    if jax.process_index() == 0:
        from gac_jax.data.synthetic import generate_dataset

        s = cfg.synthetic
        generate_dataset(
            root,
            num_frames=s.num_frames,
            seed=s.seed,
            height=s.height,
            width=s.width,
            val_fraction=s.val_fraction,
            rig_set=s.get("rigs", "kitti"),
            workers=s.get("workers") or None,  # 0 / absent: one per core
        )
    from gac_jax.training import multiprocess

    multiprocess.barrier("dataset_ready")  # the others wait (with a timeout) for process 0
    return root


def plane_ops(data: ml_collections.ConfigDict) -> list:
    """``[DropGroundPlane()]`` when the config ignores the frames' plane files
    (``data.use_planes = False``, variant ``fixedplane``; absent in older workdirs: used),
    else ``[]``: the first transforms of both tasks' train and eval chains."""
    return [] if data.get("use_planes", True) else [transforms.DropGroundPlane()]
