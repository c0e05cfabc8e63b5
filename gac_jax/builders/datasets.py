"""Where a config's data lives: the embedded dataset cache and ``prepare_dataset``."""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path

import jax
import ml_collections

from gac_jax.data import camera_effects, cast_shadows, random_convolution, transforms
from gac_jax.data.cache import default_cache_dir
from gac_jax.data.files import KittiFormatError, atomic_write
from gac_jax.progress import say


def synthetic_config() -> ml_collections.ConfigDict:
    """The configs' ``data.synthetic`` block: what the embedded dataset is made of.

    ``rigs``: ``'kitti'`` (KITTI's rigs) or ``'multi'`` (eight vehicles, ground planes,
    :mod:`gac_jax.data.synthetic.rigs`); ``randomize``: share of frames with a randomized
    background (:mod:`gac_jax.data.synthetic.domain_randomization`; 0: none, a cache folder of
    its own otherwise); ``photo``: share of frames with photo textures on foliage, rough
    solids and verges (:mod:`gac_jax.data.synthetic.photo_textures`; the same);
    ``randomize_cars``: share of frames whose cars get random paint, glass and tyres
    (:func:`gac_jax.data.synthetic.domain_randomization.randomize_cars`; the same);
    ``large_vehicles``: share of frames with vans and trucks, labelled ``Van`` / ``Truck``
    (:mod:`gac_jax.data.synthetic.vehicles`; the same); ``gardens``: probability that an
    urban roadside has front gardens (:mod:`gac_jax.data.synthetic.gardens`; the same);
    ``workers``: generator processes (0: one per core; the content does not depend on them).
    Both configs share it, so the detector and the depth network train on one generated
    dataset.
    """
    return ml_collections.ConfigDict(
        dict(
            num_frames=1000, seed=0, height=375, width=1242, val_fraction=0.5, rigs="kitti",
            randomize=0.0, photo=0.0, randomize_cars=0.0, large_vehicles=0.0, gardens=0.0,
            workers=0,
        )
    )  # fmt: skip


# the generator's share options and their cache folder suffixes (``..._dc0.5``), in the
# folder name's order; a dataset without one (share 0) is named as before it existed
SHARE_SUFFIXES = {
    "randomize": "dr",
    "photo": "ph",
    "randomize_cars": "dc",
    "large_vehicles": "lv",
    "gardens": "g",
}


def _shares(s: ml_collections.ConfigDict) -> dict[str, float]:
    return {key: float(s.get(key, 0.0)) for key in SHARE_SUFFIXES}


def synthetic_dataset_dir(cfg: ml_collections.ConfigDict) -> Path:
    """Folder of the embedded dataset described by ``cfg`` (``data.synthetic``)."""
    if cfg.get("root"):
        return Path(cfg.root)
    s = cfg.synthetic
    from gac_jax.data.synthetic.writer import FORMAT_VERSION

    name = f"synthetic_n{s.num_frames}_s{s.seed}_{s.height}x{s.width}_val{s.val_fraction:g}"
    # (a new version of the frames gets a folder of its own: an older cache stays readable to
    # the run folders that recorded it, and is never taken for the new one)
    name += f"_v{FORMAT_VERSION}" if FORMAT_VERSION > 1 else ""
    for key, share in _shares(s).items():
        name += f"_{SHARE_SUFFIXES[key]}{share:g}" if share > 0 else ""
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
    from gac_jax.training import multiprocess, stopping

    root = synthetic_dataset_dir(cfg)
    if jax.process_index() == 0:
        from gac_jax.data.synthetic import generate_dataset
        from gac_jax.data.synthetic.generated_dir import GenerationStoppedError

        s = cfg.synthetic
        try:
            result = generate_dataset(
                root,
                num_frames=s.num_frames,
                seed=s.seed,
                height=s.height,
                width=s.width,
                val_fraction=s.val_fraction,
                rig_set=s.get("rigs", "kitti"),
                **_shares(s),
                workers=s.get("workers") or None,  # 0 / absent: one per core
                progress=True,  # what, where and about how long; then a bar or a line per ~10 %
                should_stop=stopping.stop_requested,  # a stop signal stops it at once
            )
        except GenerationStoppedError as e:
            raise multiprocess.PreemptedError(
                0,
                f"stopped while generating the embedded dataset ({e.done} of {e.total} frames "
                f"written, kept in {root}); run the same command to finish it and train",
            ) from None
        if result.generated == 0:
            say(f"reusing the embedded dataset ({result.num_frames} frames) in {root}")
    multiprocess.barrier("dataset_ready")  # the others wait (with a timeout) for process 0
    return root


def plane_ops(data: ml_collections.ConfigDict) -> list:
    """``[DropGroundPlane()]`` when the config ignores the frames' plane files
    (``data.use_planes = False``, variant ``fixedplane``; absent in older workdirs: used),
    else ``[]``: the first transforms of both tasks' train and eval chains."""
    return [] if data.get("use_planes", True) else [transforms.DropGroundPlane()]


def appearance_ops(data: ml_collections.ConfigDict) -> list:
    """The pixel-only augmentations of both tasks' training chains, in order: cast shadows
    (``data.cast_shadows`` > 0), camera effects (``data.camera_effects``), random convolutions
    (``data.random_convolution`` > 0), the reference's photometric distortion
    (``data.photometric``). Keys absent from older run folders: off."""
    ops: list = []
    shadows = cast_shadows.from_config(data)
    if shadows is not None:
        ops.append(shadows)
    if data.get("camera_effects", False):
        ops.append(camera_effects.from_config(data))
    randconv = random_convolution.from_config(data)
    if randconv is not None:
        ops.append(randconv)
    if data.photometric:
        ops.append(transforms.PhotometricDistort())
    return ops


CACHE_RECORD = "data_cache.json"  # in a run folder: the cache its embedded dataset is in


def record_cache(workdir: str | os.PathLike) -> None:
    """Writes ``WORKDIR/data_cache.json``: the cache root (``$GAC_JAX_CACHE`` or the
    default) of the run, so that later work on the run's data (int8 calibration) finds
    the dataset the run trained on whatever ``$GAC_JAX_CACHE`` says then."""
    with atomic_write(Path(workdir) / CACHE_RECORD) as f:
        json.dump({"cache": str(default_cache_dir().absolute())}, f)
        f.write("\n")


def run_cache(workdir: str | os.PathLike | None) -> Path | None:
    """The cache root :func:`record_cache` wrote for the run (None: none recorded, an older
    run folder, or no workdir)."""
    if workdir is None:
        return None
    path = Path(workdir) / CACHE_RECORD
    try:
        return Path(json.loads(path.read_text())["cache"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


@contextlib.contextmanager
def cache_of_run(workdir: str | os.PathLike | None) -> Iterator[Path]:
    """Inside, :func:`~gac_jax.data.cache.default_cache_dir` is the run's recorded cache
    (:func:`run_cache`; unchanged when none is recorded). Yields the cache in effect."""
    recorded = run_cache(workdir)
    if recorded is None:
        yield default_cache_dir()
        return
    before = os.environ.get("GAC_JAX_CACHE")
    os.environ["GAC_JAX_CACHE"] = str(recorded)
    try:
        yield recorded
    finally:
        if before is None:
            os.environ.pop("GAC_JAX_CACHE", None)
        else:
            os.environ["GAC_JAX_CACHE"] = before
