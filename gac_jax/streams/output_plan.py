"""Where a stream writes, resolved and checked before any model is loaded.

:func:`plan_outputs` turns the output folder, the video file and the results' form into
absolute paths and refuses, with one line naming the path and what to do
(:class:`~gac_jax.data.files.KittiFormatError`), what would fail or destroy something only
after loading, warm-up and processing: a file where a folder is needed or a folder where a
file is, a symbolic link to nothing, the input itself as the output video, a video OpenCV
would have to write under a name that is not UTF-8, a folder that cannot be created or written
(permission denied, a read-only filesystem: tried with a probe file, so it holds for root too),
and (:func:`check_free_space`) too little free space for a few seconds of video (or, without
a video, for the results). It changes nothing on disk.

:func:`claim_outputs` then takes the outputs for this stream: it creates the folders, locks
them (:mod:`gac_jax.streams.output_lock`: a second stream into them is refused), gives back
what an ``--overwrite`` run that was killed had moved aside
(:mod:`gac_jax.streams.earlier_results`), and refuses a folder that holds an earlier run's
results unless ``overwrite`` (they are then moved aside just before the stream starts, and
restored if it ends before writing a whole frame).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import os
import tempfile
from pathlib import Path

from gac_jax.data.files import KittiFormatError
from gac_jax.data.io_errors import free_bytes, megabytes
from gac_jax.streams import earlier_results, output_lock
from gac_jax.streams.earlier_results import (
    JSONL_NAME,
    RESULTS_DIR,
    TRACKING_DIR,
    TRACKS_JSONL_NAME,
)
from gac_jax.streams.outputs import CONTAINERS, FRAGMENTED, check_video_path

VIDEO_NAME = "annotated.mp4"
OPENCV_WRITTEN = tuple(s for s in CONTAINERS if s not in FRAGMENTED)  # containers cv2 writes
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


def _utf8(path: Path) -> bool:
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def _dangling(path: Path, option: str, what: str) -> None:
    if path.is_symlink() and not path.exists():
        raise KittiFormatError(
            path,
            f"is a symbolic link to {os.readlink(path)}, which does not exist; create that "
            f"{what} or choose another {option}",
        )


def plan_outputs(
    folder: str | os.PathLike,
    video: str | os.PathLike | None,
    jsonl: bool,
    inputs: list[str | os.PathLike],
    track: bool = False,
) -> OutputPlan:
    """Resolves and checks the outputs (module doc); nothing is changed on disk.
    ``video``: the video file (None: none); ``inputs``: files the stream reads (none of them
    may be an output); ``track``: the results are tracks (``tracking/`` or ``tracks.jsonl``)."""
    folder = Path(folder).absolute()
    _dangling(folder, "--out", "folder")
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
        _dangling(plan.video.parent, "--out-video", "folder")
        for source in inputs:
            if _same_file(plan.video, Path(source).absolute()):
                raise KittiFormatError(
                    plan.video, "is the input; writing the video there would destroy it "
                    "(choose another --out-video)"
                )  # fmt: skip
        if plan.video.suffix.lower() in OPENCV_WRITTEN and not _utf8(plan.video):
            raise KittiFormatError(
                plan.video,
                f"OpenCV cannot write a {plan.video.suffix} video whose path is not UTF-8; "
                "choose a UTF-8 name (or an .mp4 video, written without OpenCV)",
            )
    if jsonl and plan.results.is_dir():
        raise KittiFormatError(plan.results, "is a folder; --jsonl writes a file of that name")
    if not jsonl and plan.results.exists() and not plan.results.is_dir():
        raise KittiFormatError(plan.results, "is a file; the per-frame results need a folder")
    _probe(folder, "output folder", create=False)
    if not jsonl and plan.results.is_dir():
        _probe(plan.results, "results folder", create=False)
    if plan.video is not None and plan.video.parent != folder:
        _probe(plan.video.parent, "folder of --out-video", create=False)
    return plan


def _device(path: Path) -> int | None:
    """The filesystem ``path`` is (or would be created) on."""
    while not path.exists() and path.parent != path:
        path = path.parent
    with contextlib.suppress(OSError):
        return os.stat(path).st_dev
    return None


def check_free_space(plan: OutputPlan, picture_pixels: int, fps: float | None) -> None:
    """Raises :class:`KittiFormatError` (one line, exit 2: checked before the stream starts)
    when a filesystem the stream writes to has less free space than the results need for a
    start (:data:`RESULTS_RESERVE`) plus, where the video goes, :data:`MIN_VIDEO_SECONDS` of
    video (``picture_pixels``: of one annotated picture; ``fps``: None for 10)."""
    needs: dict[int | None, list] = {}  # filesystem -> [path, bytes, what]
    needs[_device(plan.folder)] = [plan.folder, RESULTS_RESERVE, "the results need"]
    if plan.video is not None:
        frame = int(picture_pixels * JPEG_BYTES_PER_PIXEL)
        video = int(MIN_VIDEO_SECONDS * (fps or 10.0)) * frame
        what = f"{MIN_VIDEO_SECONDS:g} s of video need"
        where = needs.setdefault(_device(plan.video.parent), [plan.video.parent, 0, what])
        where[1] += video
        where[2] = what if where[1] == video else f"the results and {what}"
    for where, need, what in needs.values():
        free = free_bytes(where)
        if free is not None and free < need:
            option = "--out" if where == plan.folder else "--out-video"
            raise KittiFormatError(
                where,
                f"only {megabytes(free)} free; {what} about {megabytes(need)} (free some "
                f"space, or choose another {option})",
            )


def claim_outputs(plan: OutputPlan, overwrite: bool) -> list[str]:
    """Takes the outputs for this stream (module doc): creates and locks the folders, gives
    back what a killed ``--overwrite`` run had moved aside, and refuses an earlier run's results
    unless ``overwrite``. On a refusal the locks are released and the folders this call created
    removed again. Returns the lines to print (what was given back).

    Raises:
      KittiFormatError: earlier results without ``overwrite``.
      OutputBusyError: another stream holds an output.
      OSError: a folder or lock file cannot be made.
    """
    created = [p for p in (plan.folder, plan.video and plan.video.parent) if p and not p.exists()]
    created = _new_ancestors(created)
    locks = [output_lock.OutputLock(plan.folder, True, "--out")]
    if plan.video is not None and plan.video.parent != plan.folder:
        locks.append(output_lock.OutputLock(plan.video, False, "--out-video"))
    try:
        for folder in (plan.folder, plan.video and plan.video.parent):
            if folder:
                folder.mkdir(parents=True, exist_ok=True)
        output_lock.hold(locks)
        try:
            lines = earlier_results.recover(plan)
            _refuse_earlier(plan, overwrite)
        except BaseException:
            for lock in locks:
                lock.release()
            raise
    except BaseException:
        for folder in reversed(created):
            try:
                folder.rmdir()
            except OSError:
                break
        raise
    return lines


def _new_ancestors(paths: list[Path]) -> list[Path]:
    """Every folder that creating ``paths`` would create, parents first."""
    new: list[Path] = []
    for path in paths:
        chain = []
        while not path.exists() and path.parent != path:
            chain.append(path)
            path = path.parent
        new += [p for p in reversed(chain) if p not in new]
    return new


def _refuse_earlier(plan: OutputPlan, overwrite: bool) -> None:
    earlier = earlier_results.find(plan)
    if not earlier or overwrite:
        return
    outside = [p for p in earlier if not p.is_relative_to(plan.folder)]
    if outside:
        raise KittiFormatError(
            outside[0],
            "exists (an earlier run's video); pass --overwrite to replace it, or choose "
            "another --out-video",
        )
    results = [p for p in earlier if p.parent.name in (RESULTS_DIR, TRACKING_DIR)]
    others = sorted({p.name for p in earlier} - {p.name for p in results})
    held = ([f"{len(results)} result files"] if results else []) + others
    raise KittiFormatError(
        plan.folder,
        f"already holds the results of an earlier run ({', '.join(held)}); pass "
        "--overwrite to replace them, or choose another folder with --out",
    )
