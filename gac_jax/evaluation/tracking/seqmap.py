"""Seqmaps: which sequences a KITTI tracking evaluation scores, and how many frames each has.

A seqmap (``evaluate_tracking.seqmap.<split>`` of the KITTI devkit and of TrackEval, beside
the ``label_02`` folder) has one line per sequence::

    0000 empty 000000 000154

the sequence, an unused word, the first frame (0) and the number of frames (154: frames 0 to
153). TrackEval reads the fourth column as that count, the older devkit as the last frame
(one more, empty, frame: it changes no figure). Only the listed sequences are scored, and a
label or result line of a frame outside ``0 .. count - 1`` is refused. TrackEval's ground
truth folders hold several (``.training``, ``.val``, ``.training_minus_val``); like
TrackEval, the ``training`` one is used unless another is asked for.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from gac_jax.data.files import KittiFormatError, read_bytes

SEQMAP_PREFIX = "evaluate_tracking.seqmap."
DEFAULT_SPLIT = "training"  # TrackEval's SPLIT_TO_EVAL default


def parse_seqmap(text: str, path: str | os.PathLike = "<seqmap>") -> dict[str, int]:
    """``{sequence: number of frames}`` in file order. Raises :class:`KittiFormatError`
    naming the line for a line of fewer than 4 fields, a count that is not a non-negative
    integer, or a sequence listed twice."""
    out: dict[str, int] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = [f for f in re.split(r"[\s,]+", raw.strip()) if f]
        if not fields:
            continue
        if len(fields) < 4:
            raise KittiFormatError(
                path, f"expected 'SEQUENCE empty FIRST COUNT', found {len(fields)} fields", lineno
            )
        name, count = fields[0], fields[3]
        if not count.isdigit():
            raise KittiFormatError(path, f"frame count {count!r} is not an integer", lineno)
        if name in out:
            raise KittiFormatError(path, f"sequence {name} listed twice", lineno)
        out[name] = int(count)
    if not out:
        raise KittiFormatError(path, "the seqmap lists no sequence")
    return out


def read_seqmap(path: str | os.PathLike) -> dict[str, int]:
    """Reads a seqmap file; see :func:`parse_seqmap`."""
    return parse_seqmap(read_bytes(path, "seqmap").decode("utf-8", "replace"), path)


def find_seqmap(label_dir: str | os.PathLike) -> Path | None:
    """The seqmap beside ``label_dir`` (``evaluate_tracking.seqmap.*`` in its parent): the
    only one, else the ``training`` one; None without any. Raises :class:`KittiFormatError`
    when there are several and none is ``training``."""
    parent = Path(label_dir).parent
    found = sorted(p for p in parent.glob(SEQMAP_PREFIX + "*") if p.is_file())
    if len(found) <= 1:
        return found[0] if found else None
    for p in found:
        if p.name == SEQMAP_PREFIX + DEFAULT_SPLIT:
            return p
    names = ", ".join(p.name for p in found)
    raise KittiFormatError(parent, f"several seqmaps ({names}): choose one with --seqmap")
