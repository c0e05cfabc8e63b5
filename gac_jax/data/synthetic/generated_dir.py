"""A generated directory: what it holds, the marker of a run in progress, parallel jobs.

A generator (the frames' :mod:`writer`, the :mod:`clips`) describes its arguments as JSON:
``start_writing`` puts that description in a marker file first, ``finish_writing`` writes
it as the directory's description last, so a directory with the description is complete
and one with the marker is ours to finish. ``check_target`` decides between done, resume
and a fresh start (never touching a foreign non-empty directory); ``run_jobs`` renders
items in worker processes that never outlive the generator; ``png_bytes`` is how the
generators encode their images (fast, fixed settings).
"""

from __future__ import annotations

import concurrent.futures
import json
import multiprocessing
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data import files
from gac_jax.data.worker_lifetime import Owner, exit_with_owner
from gac_jax.progress import Progress, say


def png_bytes(array: np.ndarray, png_filter: int, huffman_only: bool = False) -> bytes:
    """PNG bytes at compression level 1 with a fixed row filter (BGR for colour).

    Measured here: for the noisy colour renders a SUB filter with Huffman-only
    coding is twice as fast as OpenCV's default and smaller; depth maps
    compress best with UP (dense) or no filter (sparse).
    """
    params = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, png_filter]
    if huffman_only:
        params += [cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    ok, buf = cv2.imencode(".png", array, params)
    if not ok:
        raise ValueError(f"cannot encode an array of shape {array.shape} as PNG")
    return buf.tobytes()


def init_worker(owner: str) -> None:
    cv2.setNumThreads(1)
    # The pool never outlives a killed generator. The owner is named: under forkserver a
    # worker's parent is the fork server, not the generating process.
    exit_with_owner(Owner.parse(owner))


def check_target(
    root: Path, want: dict, overwrite: bool, done_name: str, marker_name: str, owned
) -> str:
    """'done', 'resume' or 'fresh' for a generated directory described by ``want``.

    ``done_name`` (the description, written last) and ``marker_name`` (written first)
    say what ``root`` holds; 'fresh' deletes the stale ``owned`` folders of our own
    directory. Raises ValueError for a directory of other arguments (unless
    ``overwrite``) or a non-empty directory that is not ours.
    """
    done, marker = root / done_name, root / marker_name
    if done.exists():
        have = _read_json(done)
        if have == want:
            return "done"
        if not overwrite:
            raise ValueError(
                f"{root} holds a synthetic dataset made with other arguments "
                f"({_diff(have, want)}); use another directory or overwrite it (--overwrite)"
            )
    elif marker.exists():
        if _read_json(marker) == want:
            return "resume"
    elif root.exists() and any(root.iterdir()):
        raise ValueError(
            f"{root} is not empty and holds no synthetic dataset ({done_name} missing); "
            "refusing to write into it: choose an empty or new directory"
        )
    for name in (*owned, done_name):  # our own, stale content
        p = root / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    return "fresh"


def _read_json(path: Path):
    try:
        return json.loads(files.read_bytes(path, "dataset description"))
    except json.JSONDecodeError as e:
        raise files.KittiFormatError(path, f"not valid JSON ({e.msg})", e.lineno) from None


def _diff(have, want) -> str:
    if not isinstance(have, dict):
        return "unreadable description"
    keys = sorted(k for k in set(have) | set(want) if have.get(k) != want.get(k))
    return ", ".join(f"{k}: {have.get(k)!r} there, {want.get(k)!r} asked" for k in keys)


def start_writing(
    root: Path, want: dict, done_name: str, marker_name: str, owned, clean: bool = True
) -> None:
    """Marks ``root`` as being written (``marker_name`` holds ``want``; ``done_name`` goes
    until everything is back) and deletes an interrupted run's temporary files (unless
    ``clean`` is False: other writers may be at work in ``root``)."""
    root.mkdir(parents=True, exist_ok=True)
    if not os.access(root, os.W_OK):
        raise PermissionError(f"{root}: directory is not writable")
    with files.atomic_write(root / marker_name) as f:
        json.dump(want, f, indent=1)
    (root / done_name).unlink(missing_ok=True)  # incomplete until everything is back
    if clean:
        remove_temporaries(root, owned)


def finish_writing(root: Path, want: dict, done_name: str, marker_name: str) -> None:
    """Writes the description ``want`` as ``done_name`` (last) and drops the marker."""
    with files.atomic_write(root / done_name) as f:
        json.dump(want, f, indent=1)
    (root / marker_name).unlink(missing_ok=True)


def remove_temporaries(root: Path, owned) -> None:
    """Deletes half-written temporary files an interrupted run left behind."""
    for sub in owned:
        if (root / sub).is_dir():
            for p in (root / sub).rglob(".*.tmp"):
                p.unlink(missing_ok=True)


class GenerationStoppedError(Exception):
    """Generation stopped on request (``should_stop``); what was written is kept, and the
    same call finishes it."""

    def __init__(self, done: int, total: int):
        super().__init__(f"stopped after {done} of {total} items")
        self.done, self.total = done, total


def run_jobs(
    fn,
    job,
    todo: list,
    workers: int | None,
    progress: bool,
    desc: str,
    announce=None,
    should_stop=None,
) -> list[float]:
    """Calls ``fn(job, item)`` for every item of ``todo`` in ``workers`` processes (default: one
    per core; 1 = in this process), in order; returns what the calls returned (seconds).

    ``progress``: the first item runs here, timed, and ``announce(seconds, parallel)`` (if
    given) returns the line printed before the rest (what is made, where, about how long);
    then a bar on a terminal or a line every ~10 % (:mod:`gac_jax.progress`). The pool uses
    forkserver (spawn where there is none) and never outlives this process.

    ``should_stop``: a callable polled after every item; when it returns True the items not
    started are cancelled, those running finish, and :class:`GenerationStoppedError` is raised.
    """
    if workers is None:
        workers = os.cpu_count() or 1
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    seconds, start = [], time.perf_counter()
    if progress and todo:
        seconds.append(fn(job, todo[0]))
        if announce is not None:
            say(announce(seconds[0], max(1, min(workers, len(todo) - 1, os.cpu_count() or 1))))
    with Progress(len(todo), desc, "frame", enabled=progress, start=start) as bar:
        bar.update(len(seconds))
        rest = todo[len(seconds) :]
        if workers == 1 or len(rest) <= 1:
            for item in rest:
                if should_stop is not None and should_stop():
                    raise GenerationStoppedError(len(seconds), len(todo))
                seconds.append(fn(job, item))
                bar.update(1)
            return seconds
        methods = multiprocessing.get_all_start_methods()
        context = multiprocessing.get_context("forkserver" if "forkserver" in methods else "spawn")
        # (a few items per task: a stop waits for the tasks running, at most a few items long)
        chunk = max(1, min(4, len(rest) // (workers * 8)))
        with concurrent.futures.ProcessPoolExecutor(
            max_workers=min(workers, len(rest)),
            mp_context=context,
            initializer=init_worker,
            initargs=(Owner.current().token(),),
        ) as pool:
            for dt in pool.map(fn, [job] * len(rest), rest, chunksize=chunk):
                seconds.append(dt)
                bar.update(1)
                if should_stop is not None and should_stop():
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise GenerationStoppedError(len(seconds), len(todo))
        return seconds
