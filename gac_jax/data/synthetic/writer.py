"""Writes a generated dataset in the KITTI object and KITTI-depth layouts, resumably.

Layout under ``DIR`` (``NNNNNN`` = frame id, ``NNNNNNNNNN`` its 10-digit form)::

    training/{image_2,image_3}/NNNNNN.png, training/calib/NNNNNN.txt, training/label_2/NNNNNN.txt
    ImageSets/{train,val,trainval}.txt
    depth/data_depth_annotated/{train,val}/<drive>/proj_depth/groundtruth/image_0{2,3}/NNNNNNNNNN.png
    depth/data_depth_dense/{train,val}/<drive>/proj_depth/groundtruth/image_0{2,3}/NNNNNNNNNN.png
    depth/raw/<date>/<drive>/image_0{2,3}/data/NNNNNNNNNN.png      (hard links to the images)
    depth/raw/<date>/calib_cam_to_cam.txt, calib_velo_to_cam.txt
    synthetic.json                                                  (the arguments; written last)

and, for the ``"multi"`` rig set, each frame's ground plane (AVOD format,
:func:`gac_jax.data.kitti.write_plane`) in both layouts::

    training/planes/NNNNNN.txt
    depth/planes/<drive>/NNNNNNNNNN.txt                             (hard link to the above)

One plane file serves both cameras: it is in the rectified reference (camera 0)
frame, which ``P2``/``P3`` (object calib) and ``P_rect_02``/``P_rect_03``
(``calib_cam_to_cam.txt``) all project from (:mod:`gac_jax.data.kitti_depth`).

There is one drive per (split, recording day): ``<date>_drive_90RR_sync`` for
train and ``<date>_drive_91RR_sync`` for val (``RR`` = 01, 02, 03 for the
rigs). Every file is written atomically, so a frame is complete exactly when
all its files exist; an interrupted run is finished by calling again with the
same arguments. ``DIR/.synthetic_in_progress.json`` marks a directory being
written, so an unrelated non-empty directory is never touched.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data import files
from gac_jax.data.kitti import write_calib, write_label, write_plane, write_split
from gac_jax.data.synthetic import calibration, rigs
from gac_jax.data.synthetic.frame import frame_rig, make_frame
from gac_jax.data.synthetic.generated_dir import (
    check_target,
    finish_writing,
    png_bytes,
    run_jobs,
    start_writing,
)
from gac_jax.data.synthetic.scene import CLASS_SIZES, DEFAULT_COUNTS
from gac_jax.progress import about

FORMAT_VERSION = 3  # bump whenever the generated content changes (it keys idempotence)
MARKER = ".synthetic_in_progress.json"
DONE = "synthetic.json"
OWNED = ("training", "ImageSets", "depth")  # what a fresh start may delete (only in our own dirs)


class SceneArguments:
    """What frames and clips share: seed, image size (``height``, ``width``), rig set and the
    road users' ``classes`` (name, min, max); checked by :meth:`validate_scene`."""

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def counts(self) -> dict[str, tuple[int, int]]:
        return {name: (lo, hi) for name, lo, hi in self.classes}

    def validate_scene(self) -> None:
        """Raises ValueError with a clear message for unusable shared arguments."""
        rigs.check_rig_set(self.rigs)
        if not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed!r}")
        if not (32 <= self.height <= 4096 and 64 <= self.width <= 8192):
            raise ValueError(
                f"image size must be 32..4096 x 64..8192 pixels, got {self.height}x{self.width}"
            )
        for name, lo, hi in self.classes:
            if name not in CLASS_SIZES:
                raise ValueError(f"unknown class {name!r} (known: {', '.join(CLASS_SIZES)})")
            if not 0 <= lo <= hi <= 50:
                raise ValueError(f"class {name}: need 0 <= min <= max <= 50, got {lo}..{hi}")
        if len({c[0] for c in self.classes}) != len(self.classes):
            raise ValueError("a class is listed twice")


@dataclasses.dataclass(frozen=True)
class DatasetSpec(SceneArguments):
    """The arguments that determine a generated dataset's content."""

    num_frames: int
    seed: int
    height: int = calibration.KITTI_SIZE[0]
    width: int = calibration.KITTI_SIZE[1]
    val_fraction: float = 0.5
    classes: tuple[tuple[str, int, int], ...] = tuple((k, *v) for k, v in DEFAULT_COUNTS.items())
    rigs: str = "kitti"  # the camera rig set (gac_jax.data.synthetic.rigs)
    randomize: float = 0.0  # share of frames with a randomized background (domain_randomization)
    photo: float = 0.0  # share of frames with photo textures (photo_textures)
    randomize_cars: float = 0.0  # share of frames with randomized cars (domain_randomization)
    large_vehicles: float = 0.0  # share of frames with vans and trucks (vehicles)
    gardens: float = 0.0  # probability of front gardens on an urban roadside (gardens)

    def validate(self) -> None:
        """Raises ValueError with a clear message for unusable arguments."""
        if not isinstance(self.num_frames, int | np.integer) or self.num_frames < 1:
            raise ValueError(
                f"number of frames must be a positive integer, got {self.num_frames!r}"
            )
        if self.num_frames > 1_000_000:
            raise ValueError(f"at most 1,000,000 frames (6-digit ids), got {self.num_frames}")
        self.validate_scene()
        if not 0.0 <= self.val_fraction <= 1.0:
            raise ValueError(f"val fraction must be in [0, 1], got {self.val_fraction}")
        if not 0.0 <= self.randomize <= 1.0:
            raise ValueError(f"randomize must be a share in [0, 1], got {self.randomize}")
        if not 0.0 <= self.photo <= 1.0:
            raise ValueError(f"photo must be a share in [0, 1], got {self.photo}")
        if not 0.0 <= self.randomize_cars <= 1.0:
            raise ValueError(f"randomize_cars must be a share in [0, 1], got {self.randomize_cars}")
        if not 0.0 <= self.large_vehicles <= 1.0:
            raise ValueError(f"large_vehicles must be a share in [0, 1], got {self.large_vehicles}")
        if not 0.0 <= self.gardens <= 1.0:
            raise ValueError(f"gardens must be a share in [0, 1], got {self.gardens}")

    def to_json(self) -> dict:
        return {
            "generator": "gac_jax.data.synthetic",
            "format_version": FORMAT_VERSION,
            "num_frames": int(self.num_frames),
            "seed": int(self.seed),
            "height": int(self.height),
            "width": int(self.width),
            "val_fraction": float(self.val_fraction),
            "classes": {name: [int(lo), int(hi)] for name, lo, hi in self.classes},
            # (absent for KITTI's rigs: the default dataset's description is what it was)
            **({"rigs": self.rigs} if self.rigs != "kitti" else {}),
            **({"randomize": float(self.randomize)} if self.randomize > 0 else {}),
            **({"photo": float(self.photo)} if self.photo > 0 else {}),
            **({"randomize_cars": float(self.randomize_cars)} if self.randomize_cars > 0 else {}),
            **({"large_vehicles": float(self.large_vehicles)} if self.large_vehicles > 0 else {}),
            **({"gardens": float(self.gardens)} if self.gardens > 0 else {}),
        }

    def splits(self) -> dict[str, list[int]]:
        """Frame indices of ``train`` and ``val``: the first frames train, the last ``val``.

        With the ``"multi"`` rig set, frames of held-out rigs form ``val_heldout`` instead
        (never trained on), and the others are divided as above.
        """
        ids = list(range(self.num_frames))
        heldout = []
        if self.rigs != "kitti":
            held = {i for i in ids if rigs.heldout(self.rigs, frame_rig(self.seed, i, self.rigs))}
            heldout = [i for i in ids if i in held]
            ids = [i for i in ids if i not in held]
        n = len(ids)
        n_val = int(round(n * self.val_fraction))
        if 0.0 < self.val_fraction < 1.0 and n >= 2:
            n_val = min(max(n_val, 1), n - 1)
        out = {"train": ids[: n - n_val], "val": ids[n - n_val :]}
        return {**out, "val_heldout": heldout} if self.rigs != "kitti" else out

    def subsets(self) -> dict[str, list[int]]:
        """Extra split files (subsets of :meth:`splits`): ``train_kitti_rig`` / ``val_kitti_rig``,
        the frames of the KITTI-like rig of the ``"multi"`` set (the cross-rig experiment
        trains there and tests on ``val_heldout``)."""
        if self.rigs == "kitti":
            return {}
        parts = self.splits()
        on_kitti = {
            i
            for i in range(self.num_frames)
            if rigs.MULTI_RIGS[frame_rig(self.seed, i, self.rigs)].name == "kitti"
        }
        return {f"{k}_kitti_rig": [i for i in parts[k] if i in on_kitti] for k in ("train", "val")}


SPLIT_DRIVE_OFFSET = {"train": 0, "val": 100, "val_heldout": 200}


def drive_name(rig: int, split: str, rig_set: str = "kitti") -> str:
    """KITTI-raw-style drive of a (rig, split): e.g. ``2011_09_26_drive_9001_sync``."""
    number = 9001 + rig + SPLIT_DRIVE_OFFSET[split]
    return f"{rigs.cameras(rig_set)[rig].date}_drive_{number:04d}_sync"


def frame_paths(
    root: Path, index: int, rig: int, split: str, rig_set: str = "kitti"
) -> dict[str, Path]:
    """Every file of frame ``index`` (keys: image_2, image_3, calib, label, sparse_2, ...;
    ``plane`` and ``depth_plane`` for the ``"multi"`` rig set)."""
    fid, long_id = f"{index:06d}", f"{index:010d}"
    drive = drive_name(rig, split, rig_set)
    date = rigs.cameras(rig_set)[rig].date
    paths = {
        "image_2": root / "training" / "image_2" / f"{fid}.png",
        "image_3": root / "training" / "image_3" / f"{fid}.png",
        "calib": root / "training" / "calib" / f"{fid}.txt",
        "label": root / "training" / "label_2" / f"{fid}.txt",
    }
    if rig_set != "kitti":
        paths["plane"] = root / "training" / "planes" / f"{fid}.txt"
        paths["depth_plane"] = root / "depth" / "planes" / drive / f"{long_id}.txt"
    for cam in (2, 3):
        for key, kind in (("sparse", "data_depth_annotated"), ("dense", "data_depth_dense")):
            paths[f"{key}_{cam}"] = (
                root
                / "depth"
                / kind
                / split
                / drive
                / "proj_depth"
                / "groundtruth"
                / f"image_0{cam}"
                / f"{long_id}.png"
            )
        paths[f"raw_{cam}"] = (
            root / "depth" / "raw" / date / drive / f"image_0{cam}" / "data" / f"{long_id}.png"
        )
    return paths


# Files of a frame that are hard links of another of its files (key -> the linked file's key).
LINKED = {"raw_2": "image_2", "raw_3": "image_3", "depth_plane": "plane"}


def _complete_by_linking(paths: dict[str, Path]) -> bool:
    """Links a frame's missing files when only links are missing and their originals exist
    (a ``"multi"`` dataset written before ``depth/planes/``, a deleted ``raw/`` folder), so
    the frame needs no re-rendering; False (nothing done) when anything else is missing."""
    missing = [key for key, path in paths.items() if not path.exists()]
    if not all(key in LINKED and paths[LINKED[key]].exists() for key in missing):
        return False
    for key in missing:
        _link(paths[LINKED[key]], paths[key])
    return True


def _link(src: Path, dst: Path) -> None:
    """Atomically makes ``dst`` a hard link to ``src`` (a copy where links are not possible)."""
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.parent / f".{dst.name}.{os.getpid()}.tmp"
    try:
        os.link(src, tmp)
    except OSError:
        shutil.copyfile(src, tmp)
    os.replace(tmp, dst)


@dataclasses.dataclass(frozen=True)
class _Job:
    root: str
    spec: DatasetSpec
    split_of: dict[int, str]


def _write_frame(job: _Job, index: int) -> float:
    """Renders and writes frame ``index``; returns the seconds it took."""
    start = time.perf_counter()
    spec = job.spec
    frame = make_frame(
        spec.seed,
        index,
        spec.image_size,
        spec.counts,
        rig_set=spec.rigs,
        randomize=spec.randomize,
        photo=spec.photo,
        randomize_cars=spec.randomize_cars,
        large_vehicles=spec.large_vehicles,
        gardens=spec.gardens,
    )
    paths = frame_paths(Path(job.root), index, frame.rig, job.split_of[index], spec.rigs)
    write_calib(paths["calib"], frame.calib)
    write_label(paths["label"], frame.objects)
    if "plane" in paths:
        write_plane(paths["plane"], frame.plane)
        _link(paths["plane"], paths["depth_plane"])
    for cam in (2, 3):
        view = frame.views[cam]
        dense = files.depth_to_uint16(view.depth)
        sparse = np.where(frame.sparse[cam], dense, np.uint16(0))
        files.write_bytes_atomic(paths[f"dense_{cam}"], png_bytes(dense, cv2.IMWRITE_PNG_FILTER_UP))
        files.write_bytes_atomic(
            paths[f"sparse_{cam}"], png_bytes(sparse, cv2.IMWRITE_PNG_FILTER_NONE)
        )
        image = cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR)
        files.write_bytes_atomic(
            paths[f"image_{cam}"], png_bytes(image, cv2.IMWRITE_PNG_FILTER_SUB, True)
        )
        _link(paths[f"image_{cam}"], paths[f"raw_{cam}"])
    return time.perf_counter() - start


@dataclasses.dataclass
class GenerationResult:
    """What :func:`generate_dataset` did: ``generated`` frames newly rendered and written, their
    seconds each (frames completed by linking alone are not counted)."""

    root: Path
    num_frames: int
    generated: int
    frame_seconds: list[float]
    complete: bool = True  # every frame is there (False: a shard's part only, so far)


def _check_target(root: Path, spec: DatasetSpec, overwrite: bool) -> str:
    """Decides what to do with ``root``: 'done', 'resume' or 'fresh' (after cleaning our files)."""
    return check_target(root, spec.to_json(), overwrite, DONE, MARKER, OWNED)


def generate_dataset(
    out_dir: str | os.PathLike,
    num_frames: int,
    seed: int = 0,
    *,
    height: int = calibration.KITTI_SIZE[0],
    width: int = calibration.KITTI_SIZE[1],
    val_fraction: float = 0.5,
    classes: dict[str, tuple[int, int]] | None = None,
    rig_set: str = "kitti",
    randomize: float = 0.0,
    photo: float = 0.0,
    randomize_cars: float = 0.0,
    large_vehicles: float = 0.0,
    gardens: float = 0.0,
    workers: int | None = None,
    overwrite: bool = False,
    progress: bool = False,
    shard: tuple[int, int] | None = None,
    should_stop=None,
) -> GenerationResult:
    """Generates (or completes) a synthetic KITTI-format dataset in ``out_dir``.

    Idempotent: if ``out_dir`` already holds the complete dataset for these
    arguments, returns at once; missing frames (an interrupted run, deleted
    files) are regenerated byte-identically (a frame that lacks only hard links of
    its own files, e.g. a ``"multi"`` dataset written before ``depth/planes/``
    existed, is completed by linking, not rendered again). The output does not
    depend on ``workers``.

    Args:
      num_frames: frames ``000000 .. num_frames-1``.
      seed: dataset seed; frame ``i`` depends only on ``(seed, i)`` and the size/classes.
      height, width: image size; intrinsics are KITTI's scaled from 375x1242.
      val_fraction: share of frames (the last ones) in ``ImageSets/val.txt``.
      classes: class -> (min, max) road users per frame; default
        ``{"Car": (3, 8), "Pedestrian": (0, 4), "Cyclist": (0, 2)}``.
      rig_set: ``"kitti"`` (KITTI's rigs) or ``"multi"`` (eight vehicles, two held out into
        ``val_heldout``, ground planes in ``training/planes/`` and ``depth/planes/``;
        :mod:`gac_jax.data.synthetic.rigs`).
      randomize: share of frames whose background gets random colours and patterns
        (:mod:`gac_jax.data.synthetic.domain_randomization`; 0 = none, the default).
      photo: share of frames whose foliage, rough solids and verges take their detail from
        photographs (:mod:`gac_jax.data.synthetic.photo_textures`; 0 = none, the default).
      randomize_cars: share of frames whose cars get random paint, glass and tyres
        (:func:`gac_jax.data.synthetic.domain_randomization.randomize_cars`; 0 = none).
      large_vehicles: share of frames with vans and trucks among the road users, labelled
        ``Van`` / ``Truck`` (:mod:`gac_jax.data.synthetic.vehicles`; 0 = none).
      gardens: probability that an urban roadside has front gardens, its buildings set back
        behind lawns, hedges and trees (:mod:`gac_jax.data.synthetic.gardens`; 0 = none).
      workers: processes (default ``os.cpu_count()``; 1 = in this process).
      overwrite: replace a dataset made with other arguments instead of failing.
      progress: show a progress bar.
      shard: ``(k, n)``: write only frames ``k * num_frames // n .. (k + 1) * num_frames // n
        - 1`` (and the shared index files). Shards may run in any order and at once, in other
        processes or on other machines sharing ``out_dir``; their frames are the bytes one
        run writes, and whichever finds every frame present marks the dataset complete
        (``GenerationResult.complete``).
      should_stop: polled after every frame; True stops with
        :class:`~gac_jax.data.synthetic.generated_dir.GenerationStoppedError` (the frames written
        are kept: the same call later finishes the dataset).

    Raises:
      ValueError: bad arguments, or ``out_dir`` holds something else.
      OSError: ``out_dir`` cannot be written.
    """
    counts = DEFAULT_COUNTS if classes is None else classes
    spec = DatasetSpec(
        num_frames=num_frames,
        seed=seed,
        height=height,
        width=width,
        val_fraction=float(val_fraction),
        classes=tuple((str(k), int(lo), int(hi)) for k, (lo, hi) in counts.items()),
        rigs=rig_set,
        randomize=float(randomize),
        photo=float(photo),
        randomize_cars=float(randomize_cars),
        large_vehicles=float(large_vehicles),
        gardens=float(gardens),
    )
    spec.validate()
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise ValueError(f"{root} exists and is not a directory")
    state = _check_target(root, spec, overwrite)
    splits = spec.splits()
    split_of = {i: name for name, ids in splits.items() for i in ids}
    subsets = spec.subsets()
    frame_rigs = [frame_rig(seed, i, rig_set) for i in range(num_frames)]
    if shard is not None:
        k, n = shard
        if not (n >= 1 and 0 <= k < n):
            raise ValueError(f"shard {k}/{n}: expected 0 <= k < n")
        mine = range(k * num_frames // n, (k + 1) * num_frames // n)
    else:
        mine = range(num_frames)
    todo = [
        i
        for i in mine
        if state == "fresh"
        or not all(
            p.exists() for p in frame_paths(root, i, frame_rigs[i], split_of[i], rig_set).values()
        )
    ]
    lists = (*splits, *subsets, "trainval")
    dataset_files = [root / "ImageSets" / f"{name}.txt" for name in lists]
    dataset_files += [
        root / "depth" / "raw" / rig.date / name
        for rig in rigs.cameras(rig_set)
        for name in ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt")
    ]
    if state == "done" and not todo and all(p.exists() for p in dataset_files):
        return GenerationResult(root, num_frames, 0, [])
    # (shards may be writing beside this one: their temporary files are not stale)
    start_writing(root, spec.to_json(), DONE, MARKER, OWNED, clean=shard is None)
    if state != "fresh":
        todo = [
            i
            for i in todo
            if not _complete_by_linking(frame_paths(root, i, frame_rigs[i], split_of[i], rig_set))
        ]
    seconds = _run(_Job(str(root), spec, split_of), todo, workers, progress, should_stop)

    for name, ids in {**splits, **subsets}.items():
        write_split(root / "ImageSets" / f"{name}.txt", [f"{i:06d}" for i in ids])
    write_split(root / "ImageSets" / "trainval.txt", [f"{i:06d}" for i in range(num_frames)])
    for rig in rigs.cameras(rig_set):
        raw = root / "depth" / "raw" / rig.date
        with files.atomic_write(raw / "calib_cam_to_cam.txt") as f:
            f.write(calibration.cam_to_cam_text(rig, rigs.image_size(rig, spec.image_size)))
        with files.atomic_write(raw / "calib_velo_to_cam.txt") as f:
            f.write(calibration.velo_to_cam_text(rig))
    complete = shard is None or all(
        p.exists()
        for i in range(num_frames)
        for p in frame_paths(root, i, frame_rigs[i], split_of[i], rig_set).values()
    )
    if complete:
        finish_writing(root, spec.to_json(), DONE, MARKER)
    return GenerationResult(root, num_frames, len(todo), seconds, complete)


def _run(job: _Job, todo: list[int], workers: int | None, progress: bool, should_stop=None):
    spec, total = job.spec, job.spec.num_frames
    what = f"{total} frames" if len(todo) == total else f"{len(todo)} missing of {total} frames"

    def announce(first_s: float, parallel: int) -> str:
        return (
            f"generating the embedded dataset ({what}, {spec.height}x{spec.width}, "
            f"rigs {spec.rigs}) into {job.root}: {about(first_s * len(todo) / parallel)} "
            f"({first_s:.2f} s per frame measured, {parallel} at a time); later runs reuse it"
        )

    return run_jobs(
        _write_frame, job, todo, workers, progress, "synthetic KITTI", announce, should_stop
    )
