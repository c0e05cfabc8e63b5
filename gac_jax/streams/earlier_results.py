"""An earlier run's results where a stream writes: found, moved aside by ``--overwrite``, and
given back unless replaced.

``--overwrite`` must not lose the earlier results to a run that then fails (a bad pose file,
a missing checkpoint, a full disk, Ctrl-C during start-up). So nothing is deleted before the
new run has written a whole frame: just before the stream starts, :func:`set_aside` renames
the earlier result files (``data/``, ``tracking/``, the JSON lines files, what a failed or
killed run left: ``*.incomplete*`` and hidden partials) into a hidden ``.gac_jax_earlier``
folder beside them (the same filesystem: a rename, no copy, no space needed). When the first
frame is written they are deleted (:meth:`SetAside.discard`); when the run ends before that,
however it ends, they are moved back (:meth:`SetAside.restore`). A run killed in between
(SIGKILL, power loss) leaves the hidden folder: the next stream into the folder gives its
contents back, or deletes them where the killed run's own results replaced them
(:func:`recover`, under the output lock). An earlier video is not moved: the new one replaces
it only once complete (:mod:`gac_jax.streams.outputs`).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from gac_jax.streams.outputs import incomplete_path, partial_path

JSONL_NAME = "detections.jsonl"
RESULTS_DIR = "data"
TRACKS_JSONL_NAME = "tracks.jsonl"  # --track: the tracks of every frame as JSON lines
TRACKING_DIR = "tracking"  # --track: KITTI tracking result files SSSS.txt
ASIDE = ".gac_jax_earlier"  # the moved-aside results, beside where they were
DISCARDED = ".gac_jax_earlier.discarded"  # being deleted


def find(plan) -> list[Path]:
    """The files of an earlier run where ``plan`` (an
    :class:`~gac_jax.streams.output_plan.OutputPlan`) would write: result files, the JSON
    lines, the video, and what a failed or killed run left (``*.incomplete*``, hidden
    partials)."""
    found: list[Path] = []
    for name in (RESULTS_DIR, TRACKING_DIR):
        if (plan.folder / name).is_dir():
            found += sorted((plan.folder / name).glob("*.txt"))
    for path in _files(plan):
        found += [p for p in (path, incomplete_path(path), partial_path(path)) if p.is_file()]
    return found


def _files(plan) -> list[Path]:
    return [p for p in (plan.folder / JSONL_NAME, plan.folder / TRACKS_JSONL_NAME, plan.video) if p]


def _movable(plan) -> list[tuple[Path, Path]]:
    """What :func:`set_aside` moves, as ``(file, the folder it is relative to)``: the result
    files and every earlier file but the video itself."""
    items = [
        (p, plan.folder)
        for name in (RESULTS_DIR, TRACKING_DIR)
        if (plan.folder / name).is_dir()
        for p in sorted((plan.folder / name).glob("*.txt"))
    ]
    for path in _files(plan):
        names = (incomplete_path(path), partial_path(path))
        names = (path, *names) if path != plan.video else names
        items += [
            (p, p.parent if path == plan.video else plan.folder) for p in names if p.is_file()
        ]
    return items


class SetAside:
    """Earlier results moved aside: ``moves`` of ``(where it was, where it is)``; ``folders``
    the hidden folders that hold them."""

    def __init__(self, moves: list[tuple[Path, Path]], folders: list[Path]):
        self.moves, self.folders = moves, folders

    def restore(self) -> None:
        """Moves back everything whose place is free; deletes the rest (the new run replaced
        it). Idempotent."""
        for original, aside in reversed(self.moves):
            if not original.exists() and aside.exists():
                os.rename(aside, original)
        self.discard()

    def discard(self) -> None:
        """Deletes what was moved aside (the new run replaced it); idempotent."""
        self.moves = []
        for folder in self.folders:
            _delete(folder)


def set_aside(plan) -> SetAside:
    """Moves the earlier results of ``plan``'s outputs aside (module doc); all or nothing
    (a failed rename moves back what was moved and raises the ``OSError``)."""
    moved = SetAside([], [])
    try:
        for item, root in _movable(plan):
            aside = root / ASIDE / item.relative_to(root)
            if root / ASIDE not in moved.folders:
                moved.folders.append(root / ASIDE)
            aside.parent.mkdir(parents=True, exist_ok=True)
            os.rename(item, aside)
            moved.moves.append((item, aside))
    except BaseException:
        moved.restore()
        raise
    return moved


def _delete(folder: Path) -> None:
    if not folder.exists():
        return
    doomed = folder.with_name(DISCARDED)
    if doomed.exists():
        shutil.rmtree(doomed, ignore_errors=True)
    os.rename(folder, doomed)  # never half deleted under the name that would be restored
    shutil.rmtree(doomed, ignore_errors=True)


def recover(plan) -> list[str]:
    """Gives back what a killed ``--overwrite`` run moved aside in ``plan``'s folders (where
    nothing replaced it; else deletes it). Returns one line per folder that got files back."""
    lines = []
    for root in sorted({plan.folder, *([plan.video.parent] if plan.video else [])}):
        shutil.rmtree(root / DISCARDED, ignore_errors=True)
        folder = root / ASIDE
        if not folder.is_dir():
            continue
        files = sorted(p for p in folder.rglob("*") if p.is_file())
        moves = [(root / p.relative_to(folder), p) for p in files]
        for original, _ in moves:
            if not original.exists():
                original.parent.mkdir(parents=True, exist_ok=True)
        back = SetAside(moves, [folder])
        free = [original for original, _ in moves if not original.exists()]
        back.restore()
        if free:
            lines.append(
                f"{root}: gave back {len(free)} files of an earlier run that an --overwrite run "
                "had moved aside before it was killed"
            )
    return lines
