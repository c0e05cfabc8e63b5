"""Damaged frames of a stream's input: skipped, counted, warned about, ended on only when many
come in a row.

A frame a video decoder rejects (or that its container flags as corrupt) or an image of a
sequence that cannot be read is skipped: it gets no result file and no video frame, the frames
after it keep their positions (frame ``000021`` follows a damaged ``000020``), one warning
line is printed, at most one every :data:`WARN_EVERY_S` seconds (the frames skipped in
between are counted in the next one), and the stream summary counts them all. Only
:data:`MAX_IN_A_ROW` damaged frames in a row end the stream (exit 2, with the count): a
recording that is damaged from there on. A video whose last frames are damaged, with nothing
decodable after them, was truncated (or damaged at its end): :meth:`DamagedFrames.check_end`.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable

from gac_jax.data.files import KittiFormatError

MAX_IN_A_ROW = 25  # damaged frames in a row that end a stream
WARN_EVERY_S = 5.0  # at most one warning line per this many seconds
LISTED = 5  # frame ids the summary names


def warn_on_stderr(line: str) -> None:
    print(line, file=sys.stderr, flush=True)


class DamagedFrames:
    """The damaged frames of one input (``name``, named in the lines).

    Args:
      name: the input (a video file, a sequence folder).
      what: a frame of it in the lines (``frame``, ``image``).
      warn: where the warning lines go (default: stderr).
    """

    def __init__(self, name: str, what: str = "frame", warn: Callable[[str], None] | None = None):
        self.name, self.what = name, what
        self.warn = warn or warn_on_stderr
        self.count = 0
        self.in_a_row = 0
        self.first_in_row: str | None = None
        self.listed: list[str] = []
        self._warned_at = -math.inf
        self._unwarned = 0

    def skip(self, frame_id: str, reason: str) -> None:
        """Frame ``frame_id`` is damaged (``reason``): counted and warned about; raises
        :class:`KittiFormatError` when it is the :data:`MAX_IN_A_ROW`-th in a row."""
        self.count += 1
        self.in_a_row += 1
        if self.in_a_row == 1:
            self.first_in_row = frame_id
        if len(self.listed) < LISTED:
            self.listed.append(frame_id)
        if self.in_a_row >= MAX_IN_A_ROW:
            raise KittiFormatError(
                self.name,
                f"{self.in_a_row} damaged {self.what}s in a row ({self.what}s "
                f"{self.first_in_row} to {frame_id}: {reason}); the stream stops there "
                f"({self.count} damaged in all; the results of the frames before are written)",
            )
        now = time.monotonic()
        if now - self._warned_at < WARN_EVERY_S:
            self._unwarned += 1
            return
        more = f"; {self._unwarned} more skipped since the last warning" if self._unwarned else ""
        self.warn(
            f"warning: {self.name}: {self.what} {frame_id} {reason}: skipped, no results for "
            f"it{more}"
        )
        self._warned_at, self._unwarned = now, 0

    def good(self) -> None:
        """A frame was read whole: the row of damaged ones is over."""
        self.in_a_row = 0

    def check_end(self, delivered: int) -> None:
        """At the end of a video (``delivered`` frames read whole): raises
        :class:`KittiFormatError` when the frames just before the end were damaged (the file
        is truncated, or damaged at its end)."""
        if self.in_a_row:
            last = (
                f"its last {self.what} ({self.first_in_row})"
                if self.in_a_row == 1
                else f"its last {self.in_a_row} {self.what}s (from {self.first_in_row})"
            )
            raise KittiFormatError(
                self.name,
                f"truncated or damaged at its end: {last} cannot be decoded; the results of "
                f"the {delivered} {self.what}s read are written",
            )

    def summary(self) -> str | None:
        """The summary's line (None: no damaged frame)."""
        if not self.count:
            return None
        ids = ", ".join(self.listed) + (" ..." if self.count > len(self.listed) else "")
        plural = "s" if self.count > 1 else ""
        return (
            f"{self.count} damaged {self.what}{plural} of {self.name} skipped (no results for "
            f"{ids})"
        )
