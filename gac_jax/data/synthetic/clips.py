"""Generated driving clips in the KITTI tracking layout, resumably; the clip cache.

Layout under ``DIR`` (:mod:`gac_jax.data.kitti_tracking` reads it)::

    training/image_02/SSSS/NNNNNN.png    left images, 10 Hz
    training/calib/SSSS.txt              the sequence's calibration (as the frames' calib)
    training/label_02/SSSS.txt           KITTI tracking labels (track ids; DontCare -1)
    training/planes/SSSS/NNNNNN.txt      each frame's ground plane (AVOD format)
    training/poses/SSSS.txt              a (3, 4) camera-to-world pose per frame
    clips.json                           the arguments (seed, rigs, counts, version): last

Every file is written atomically. A frame's label lines wait in
``.clips_partial/SSSS/NNNNNN.txt`` until its sequence is complete, then form
``label_02/SSSS.txt``. ``.clips_in_progress.json`` marks a directory being written; the
same call finishes an interrupted run and is a no-op on a complete one. The content
depends on the arguments only, not on the number of worker processes.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data import files, kitti
from gac_jax.data import kitti_tracking as tracking
from gac_jax.data.cache import default_cache_dir
from gac_jax.data.synthetic import calibration, drive
from gac_jax.data.synthetic.generated_dir import (
    check_target,
    finish_writing,
    png_bytes,
    run_jobs,
    start_writing,
)
from gac_jax.data.synthetic.scene import DEFAULT_COUNTS
from gac_jax.data.synthetic.traffic import SCENARIOS
from gac_jax.data.synthetic.writer import SceneArguments

FORMAT_VERSION = 4  # bump whenever the generated content changes (it keys idempotence)
DONE = "clips.json"
MARKER = ".clips_in_progress.json"
PARTIAL = ".clips_partial"
OWNED = ("training", PARTIAL)
# Seconds to render and write one 375x1242 clip frame of the default scenario mix: 0.15 s
# CPU, 0.30 s wall in one process, 0.50 s in each of 2 processes, on a shared 2-core EPYC
# at load 7.5 (benchmarks/bench_clips.py); only for the time estimate ensure_clips prints.
SECONDS_PER_FRAME = 0.5


@dataclasses.dataclass(frozen=True)
class ClipSpec(SceneArguments):
    """The arguments that determine a clip set's content."""

    num_sequences: int
    frames_per_sequence: int
    seed: int = 0
    rigs: str = "kitti"
    height: int = calibration.KITTI_SIZE[0]
    width: int = calibration.KITTI_SIZE[1]
    classes: tuple[tuple[str, int, int], ...] = tuple((k, *v) for k, v in DEFAULT_COUNTS.items())
    scenarios: tuple[tuple[str, float], ...] = drive.DEFAULT_MIX

    def validate(self) -> None:
        """Raises ValueError with a clear message for unusable arguments."""
        for name, value, most in (
            ("number of sequences", self.num_sequences, 10_000),
            ("frames per sequence", self.frames_per_sequence, 1_000_000),
        ):
            if not isinstance(value, int | np.integer) or not 1 <= value <= most:
                raise ValueError(f"{name} must be an integer in 1..{most:,}, got {value!r}")
        self.validate_scene()
        for name, share in self.scenarios:
            if name not in SCENARIOS:
                raise ValueError(f"unknown scenario {name!r} (known: {', '.join(SCENARIOS)})")
            if not 0.0 <= share <= 1.0:
                raise ValueError(
                    f"scenario {name}: share of sequences must be in [0, 1], got {share}"
                )

    def to_json(self) -> dict:
        return {
            "generator": "gac_jax.data.synthetic.clips",
            "format_version": FORMAT_VERSION,
            "num_sequences": int(self.num_sequences),
            "frames_per_sequence": int(self.frames_per_sequence),
            "frame_rate": drive.FRAME_RATE,
            "seed": int(self.seed),
            "rigs": self.rigs,
            "height": int(self.height),
            "width": int(self.width),
            "classes": {name: [int(lo), int(hi)] for name, lo, hi in self.classes},
            "scenarios": {name: float(share) for name, share in self.scenarios},
        }

    def drive(self, sequence: int) -> drive.Drive:
        counts = tuple(sorted(self.counts.items()))
        return drive.cached_drive(
            self.seed,
            sequence,
            self.frames_per_sequence,
            self.image_size,
            counts,
            self.rigs,
            self.scenarios,
        )


def sequence_name(sequence: int) -> str:
    return f"{sequence:04d}"


def _frame_files(root: Path, sequence: int, k: int) -> dict[str, Path]:
    layout = tracking.KittiTrackingLayout(root)
    seq = sequence_name(sequence)
    return {
        "image": layout.image(seq, k),
        "plane": layout.plane(seq, k),
        "partial": root / PARTIAL / seq / f"{k:06d}.txt",
    }


@dataclasses.dataclass(frozen=True)
class _Job:
    root: str
    spec: ClipSpec


def _write_clip_frame(job: _Job, item: tuple[int, int]) -> float:
    """Renders frame ``k`` of sequence ``sequence`` and writes its image, plane and labels."""
    start = time.perf_counter()
    sequence, k = item
    spec = job.spec
    frame = drive.render_clip_frame(spec.drive(sequence), spec.seed, sequence, k)
    paths = _frame_files(Path(job.root), sequence, k)
    tracking.write_text(
        paths["partial"], tracking.format_tracking_labels(k, frame.objects, frame.track_ids)
    )
    kitti.write_plane(paths["plane"], frame.plane)
    image = cv2.cvtColor(frame.view.image, cv2.COLOR_RGB2BGR)
    files.write_bytes_atomic(paths["image"], png_bytes(image, cv2.IMWRITE_PNG_FILTER_SUB, True))
    return time.perf_counter() - start


@dataclasses.dataclass
class ClipsResult:
    """What :func:`generate_clips` did: ``generated`` frames rendered now, seconds each."""

    root: Path
    num_sequences: int
    frames_per_sequence: int
    generated: int
    frame_seconds: list[float]


def _sequence_complete(root: Path, sequence: int) -> bool:
    layout = tracking.KittiTrackingLayout(root)
    seq = sequence_name(sequence)
    return all(p.exists() for p in (layout.calib(seq), layout.label(seq), layout.poses(seq)))


def _todo(root: Path, spec: ClipSpec, fresh: bool) -> list[tuple[int, int]]:
    """The frames to render: images or planes missing, or labels in neither place."""
    todo = []
    for sequence in range(spec.num_sequences):
        seq = sequence_name(sequence)
        labelled = not fresh and tracking.KittiTrackingLayout(root).label(seq).exists()
        for k in range(spec.frames_per_sequence):
            paths = _frame_files(root, sequence, k)
            if (
                fresh
                or not paths["image"].exists()
                or not paths["plane"].exists()
                or not (labelled or paths["partial"].exists())
            ):
                todo.append((sequence, k))
    return todo


def _finish_sequence(root: Path, spec: ClipSpec, sequence: int) -> None:
    """Writes the sequence's calib and poses and gathers its labels (all frames are there)."""
    layout = tracking.KittiTrackingLayout(root)
    seq = sequence_name(sequence)
    ego = drive.ego_motion(spec.seed, sequence, spec.rigs, spec.scenarios)
    calib, _ = drive.clip_calibration(ego, spec.image_size, spec.rigs)
    if not layout.calib(seq).exists():
        kitti.write_calib(layout.calib(seq), calib)
    if not layout.poses(seq).exists():
        world = spec.drive(sequence)
        poses = np.stack([world.pose(k) for k in range(spec.frames_per_sequence)])
        tracking.write_text(layout.poses(seq), tracking.format_poses(poses))
    partial = root / PARTIAL / seq
    if not layout.label(seq).exists():
        text = "".join(
            files.read_bytes(_frame_files(root, sequence, k)["partial"], "label part").decode()
            for k in range(spec.frames_per_sequence)
        )
        tracking.write_text(layout.label(seq), text)
    if partial.is_dir():
        shutil.rmtree(partial)


def generate_clips(
    out_dir: str | os.PathLike,
    num_sequences: int,
    frames_per_sequence: int,
    seed: int = 0,
    *,
    rigs: str = "kitti",
    height: int = calibration.KITTI_SIZE[0],
    width: int = calibration.KITTI_SIZE[1],
    classes: dict[str, tuple[int, int]] | None = None,
    scenarios: dict[str, float] | None = None,
    workers: int | None = None,
    overwrite: bool = False,
    progress: bool = False,
    announce=None,
) -> ClipsResult:
    """Generates (or completes) ``num_sequences`` driving clips in ``out_dir``.

    Idempotent: returns at once when ``out_dir`` holds the complete clips of these
    arguments; missing frames are rendered again byte-identically.

    Args:
      rigs: ``"kitti"`` (KITTI's rigs) or ``"multi"`` (one of eight vehicles per sequence).
      height, width: image size at KITTI's rig (other rigs scale alike).
      classes: class -> (min, max) road users per 66 m of road (default as the frames').
      scenarios: scenario -> share of the sequences that have it (default
        :data:`traffic.DEFAULT_MIX`; scenarios not listed never happen; ``{}``: straight
        roads, constant speeds).
      workers: processes (default one per core; 1 = in this process).
      overwrite: replace clips made with other arguments instead of failing.
      progress: show a progress bar.
      announce: called with one line (what, where, about how long) before rendering.

    Raises:
      ValueError: bad arguments, or ``out_dir`` holds something else.
      OSError: ``out_dir`` cannot be written.
    """
    counts = DEFAULT_COUNTS if classes is None else classes
    spec = ClipSpec(
        num_sequences=num_sequences,
        frames_per_sequence=frames_per_sequence,
        seed=seed,
        rigs=rigs,
        height=height,
        width=width,
        classes=tuple((str(k), int(lo), int(hi)) for k, (lo, hi) in counts.items()),
        scenarios=drive.DEFAULT_MIX
        if scenarios is None
        else tuple((str(k), float(v)) for k, v in scenarios.items()),
    )
    spec.validate()
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise ValueError(f"{root} exists and is not a directory")
    state = check_target(root, spec.to_json(), overwrite, DONE, MARKER, OWNED)
    todo = _todo(root, spec, state == "fresh")
    complete = all(_sequence_complete(root, s) for s in range(num_sequences))
    if state == "done" and not todo and complete:
        return ClipsResult(root, num_sequences, frames_per_sequence, 0, [])
    start_writing(root, spec.to_json(), DONE, MARKER, OWNED)
    if todo and announce is not None:
        procs = min(workers or os.cpu_count() or 1, len(todo))
        pixels = spec.height * spec.width / (calibration.KITTI_SIZE[0] * calibration.KITTI_SIZE[1])
        minutes = len(todo) * SECONDS_PER_FRAME * pixels / procs / 60
        announce(
            f"generating {len(todo)} frames of {num_sequences} driving clip(s) "
            f"({frames_per_sequence} frames at 10 Hz, {spec.width}x{spec.height}, rigs "
            f"{spec.rigs}, seed {seed}) into {root}: about {max(minutes, 0.1):.1f} min "
            f"on {procs} process(es)"
        )
    seconds = run_jobs(_write_clip_frame, _Job(str(root), spec), todo, workers, progress, "clips")
    for sequence in range(num_sequences):
        _finish_sequence(root, spec, sequence)
    if (root / PARTIAL).is_dir() and not any((root / PARTIAL).iterdir()):
        (root / PARTIAL).rmdir()
    finish_writing(root, spec.to_json(), DONE, MARKER)
    return ClipsResult(root, num_sequences, frames_per_sequence, len(todo), seconds)


def default_clip_dir(
    num_sequences: int = 1, frames_per_sequence: int = 100, seed: int = 0, rigs: str = "kitti"
) -> Path:
    """Cache folder of a clip set (under ``$GAC_JAX_CACHE``, default ``~/.cache/gac_jax``)."""
    name = f"clips_{num_sequences}x{frames_per_sequence}_s{seed}"
    return default_cache_dir() / (name if rigs == "kitti" else f"{name}_{rigs}rig")


def ensure_clips(
    out_dir: str | os.PathLike | None,
    num_sequences: int = 1,
    frames_per_sequence: int = 100,
    seed: int = 0,
    rigs: str = "kitti",
    workers: int | None = None,
) -> Path:
    """Returns ``out_dir`` (or :func:`default_clip_dir` when None) holding the clips,
    generating what is missing first (one line on stderr says what, where and about how
    long; then a progress bar). KITTI-sized images (375x1242 at KITTI's rig), the default
    scenario mix. A cache folder made by an older generator is generated again.

    Raises:
      ValueError: bad arguments, or ``out_dir`` holds something else.
    """
    root = (
        Path(out_dir)
        if out_dir is not None
        else default_clip_dir(num_sequences, frames_per_sequence, seed, rigs)
    )
    generate_clips(
        root,
        num_sequences,
        frames_per_sequence,
        seed,
        rigs=rigs,
        workers=workers,
        overwrite=out_dir is None,  # the cache: clips of an older generator are replaced
        progress=True,
        announce=lambda line: print(line, file=sys.stderr, flush=True),
    )
    return root
