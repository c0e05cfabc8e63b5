"""Where a stream writes, resolved and checked before any model is loaded.

:func:`plan_outputs` turns the output folder, the video file and the results' form into
absolute paths and refuses, with one line naming the path and what to do
(:class:`~gac_jax.data.files.KittiFormatError`), what would fail or destroy something only
after loading, warm-up and processing: a file where a folder is needed or a folder where a
file is, the input itself as the output video, a folder that cannot be created or written
(permission denied, a read-only filesystem: tried with a probe file, so it holds for root
too), and a folder that already holds results of an earlier run (unless ``overwrite``: the
old result files are then deleted first; an earlier video is kept until the new one is
complete, :mod:`gac_jax.streams.outputs`). Too little free space for a few seconds of video
is a :class:`~gac_jax.data.io_errors.DiskWriteError` (exit 1, as a disk that fills later).
"""

from __future__ import annotations

import dataclasses
import errno
import os
import tempfile
from pathlib import Path

from gac_jax.data.files import KittiFormatError
from gac_jax.data.io_errors import DiskWriteError, free_bytes, megabytes
from gac_jax.streams.outputs import check_video_path, incomplete_path, partial_path

VIDEO_NAME = "annotated.mp4"
JSONL_NAME = "detections.jsonl"
RESULTS_DIR = "data"
TRACKS_JSONL_NAME = "tracks.jsonl"  # --track: the tracks of every frame as JSON lines
TRACKING_DIR = "tracking"  # --track: KITTI tracking result files SSSS.txt
MIN_VIDEO_SECONDS = 3.0  # free space needed before starting: this much video
# bytes of a JPEG frame (quality 90) per pixel of the annotated picture (camera view + bird's-eye
# view, about twice the frame): measured 0.2 to 0.3 on KITTI frames; with room to spare
JPEG_BYTES_PER_PIXEL = 0.5
RESULTS_RESERVE = 1 << 20  # bytes kept free for a few seconds of result files


@dataclasses.dataclass(frozen=True)
class OutputPlan:
    """Absolute output paths: ``folder``; ``video`` (None: no video); ``results`` (the
    ``data`` folder or the JSON lines file; with tracking the ``tracking`` folder or
    ``tracks.jsonl``) and ``jsonl``."""

    folder: Path
    video: Path | None
    results: Path
    jsonl: bool


def _probe(folder: Path, what: str, create: bool) -> None:
    """Creates ``folder`` (``create``; else takes its nearest existing ancestor, where it would
    be created) and a file in it (deleted again), or raises naming the cause."""
    where = folder
    if not create:
        while not where.exists() and where.parent != where:
            where = where.parent
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        elif not where.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(where))
        fd, probe = tempfile.mkstemp(prefix=".gac_jax_probe.", dir=where)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        reason = os.strerror(e.errno).lower() if e.errno else str(e)
        raise KittiFormatError(
            folder, f"{what} cannot be written ({reason}); choose another one"
        ) from None


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a == b or (a.exists() and b.exists() and os.path.samefile(a, b))
    except OSError:
        return False


def earlier_results(plan: OutputPlan) -> list[Path]:
    """The files of an earlier run where ``plan`` would write: result files, the JSON lines,
    the video, and what a failed or killed run left (``*.incomplete*``, hidden partials)."""
    found: list[Path] = []
    for name in (RESULTS_DIR, TRACKING_DIR):
        if (plan.folder / name).is_dir():
            found += sorted((plan.folder / name).glob("*.txt"))
    for path in (plan.folder / JSONL_NAME, plan.folder / TRACKS_JSONL_NAME, plan.video):
        if path is None:
            continue
        found += [p for p in (path, incomplete_path(path), partial_path(path)) if p.is_file()]
    return found


def plan_outputs(
    folder: str | os.PathLike,
    video: str | os.PathLike | None,
    jsonl: bool,
    inputs: list[str | os.PathLike],
    overwrite: bool,
    clear: bool = True,
    track: bool = False,
) -> OutputPlan:
    """Resolves and checks the outputs (module doc). ``clear``: creates the folders and, with
    ``overwrite``, deletes the earlier result files (without ``clear`` nothing is changed).
    ``video``: the video file (None: none); ``inputs``: files the stream reads (none of them
    may be an output); ``track``: the results are tracks (``tracking/`` or ``tracks.jsonl``)."""
    folder = Path(folder).absolute()
    if folder.exists() and not folder.is_dir():
        raise KittiFormatError(folder, "is a file; --out needs a folder (or a new name)")
    if video is not None and Path(video).is_dir():
        raise KittiFormatError(video, "is a folder; --out-video needs a video file name")
    plan = OutputPlan(
        folder=folder,
        video=None if video is None else Path(check_video_path(video)).absolute(),
        results=folder
        / (
            (TRACKS_JSONL_NAME if jsonl else TRACKING_DIR)
            if track
            else (JSONL_NAME if jsonl else RESULTS_DIR)
        ),
        jsonl=jsonl,
    )
    if plan.video is not None:
        for source in inputs:
            if _same_file(plan.video, Path(source).absolute()):
                raise KittiFormatError(
                    plan.video, "is the input; writing the video there would destroy it "
                    "(choose another --out-video)"
                )  # fmt: skip
    if jsonl and plan.results.is_dir():
        raise KittiFormatError(plan.results, "is a folder; --jsonl writes a file of that name")
    if not jsonl and plan.results.exists() and not plan.results.is_dir():
        raise KittiFormatError(plan.results, "is a file; the per-frame results need a folder")
    _probe(folder, "output folder", create=clear)
    if plan.video is not None and plan.video.parent != folder:
        _probe(plan.video.parent, "folder of --out-video", create=clear)
    earlier = earlier_results(plan)
    if earlier and not overwrite:
        results = [p for p in earlier if p.parent.name in (RESULTS_DIR, TRACKING_DIR)]
        others = sorted({p.name for p in earlier} - {p.name for p in results})
        held = ([f"{len(results)} result files"] if results else []) + others
        raise KittiFormatError(
            folder,
            f"already holds the results of an earlier run ({', '.join(held)}); pass "
            "--overwrite to replace them, or choose another folder with --out",
        )
    for path in earlier if clear else []:
        if path != plan.video:  # an earlier video stays until the new one is complete
            path.unlink(missing_ok=True)
    return plan


def check_free_space(plan: OutputPlan, picture_pixels: int, fps: float | None) -> None:
    """Raises :class:`DiskWriteError` when the video's (or results') filesystem has less free
    space than :data:`MIN_VIDEO_SECONDS` of video need (``picture_pixels``: of one annotated
    picture; ``fps``: None for 10)."""
    need = RESULTS_RESERVE
    where = plan.results if plan.video is None else plan.video.parent
    if plan.video is not None:
        frame = int(picture_pixels * JPEG_BYTES_PER_PIXEL)
        need += int(MIN_VIDEO_SECONDS * (fps or 10.0)) * frame
    free = free_bytes(where)
    if free is not None and free < need:
        raise DiskWriteError(
            errno.ENOSPC,
            where,
            f"{where}: only {megabytes(free)} free; {MIN_VIDEO_SECONDS:g} s of video need "
            f"about {megabytes(need)} (free some space, or choose another --out / --out-video)",
        )
