"""A long wait that talks: a progress bar on a terminal, a plain line every ~10 % elsewhere.

For the waits outside the train step (generating the embedded dataset, computing anchor
priors): on an interactive terminal (``stream.isatty()``) a tqdm bar; in a log file, CI or a
subprocess pipe, where a bar would be one ever-growing line, one line per tenth of the work::

    anchor priors: 250/500 frames (50%), 0:41 elapsed, about 0:41 left

Lines go to ``stdout`` (flushed, in order with the run's other lines); the bar to ``stderr``
(tqdm's default).
"""

from __future__ import annotations

import sys
import time
from typing import IO


def say(line: str, stream: IO[str] | None = None) -> None:
    """Prints one line now (flushed), e.g. what a wait is about to do and how long it takes."""
    print(line, file=stream or sys.stdout, flush=True)


def duration(seconds: float) -> str:
    """``h:mm:ss`` or ``m:ss`` (non-negative, whole seconds)."""
    seconds = int(round(max(seconds, 0.0)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


def about(seconds: float) -> str:
    """A rough length for an estimate: ``about 40 s``, ``about 4.5 min``, ``about 1.2 h``."""
    if seconds < 90:
        return f"about {max(round(seconds), 1)} s"
    if seconds < 5400:
        return f"about {seconds / 60:.1f} min"
    return f"about {seconds / 3600:.1f} h"


class Progress:
    """Counts ``total`` units of work under the name ``desc`` (``update(n)`` as they finish).

    Args:
      total: units expected (>= 0).
      desc: what is being done, starts each line (``"synthetic KITTI"``).
      unit: the unit's name (``"frame"``), plural with an ``s`` in the lines.
      stream: where the plain lines go (default ``sys.stdout``); a bar is used instead when
        ``bar_stream`` (default ``sys.stderr``) is an interactive terminal.
      steps: lines at each ``1/steps`` of ``total`` (and at the end).
      enabled: ``False``: silent.
      start: ``time.perf_counter()`` when the work began (default: now).
    """

    def __init__(
        self,
        total: int,
        desc: str,
        unit: str = "item",
        *,
        stream: IO[str] | None = None,
        bar_stream: IO[str] | None = None,
        steps: int = 10,
        enabled: bool = True,
        start: float | None = None,
    ):
        self.total, self.desc, self.unit = max(int(total), 0), desc, unit
        self.done = 0
        self._stream = stream
        self._steps = max(int(steps), 1)
        self._next_step = 1
        self._start = time.perf_counter() if start is None else start
        self._enabled = enabled and self.total > 0
        self._bar = None
        bar_stream = bar_stream or sys.stderr
        if self._enabled and _is_terminal(bar_stream):
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, file=bar_stream)

    def update(self, n: int = 1) -> None:
        """``n`` more units are done."""
        self.done += n
        if not self._enabled:
            return
        if self._bar is not None:
            self._bar.update(n)
            return
        reached = self.done * self._steps // self.total
        if reached >= self._next_step:
            self._next_step = reached + 1
            say(self.line(), self._stream)

    def line(self) -> str:
        """The plain progress line for the current count."""
        elapsed = time.perf_counter() - self._start
        pct = 100 * self.done // self.total if self.total else 100
        text = f"{self.desc}: {self.done}/{self.total} {self.unit}s ({pct}%), "
        text += f"{duration(elapsed)} elapsed"
        if 0 < self.done < self.total:
            text += f", about {duration(elapsed * (self.total - self.done) / self.done)} left"
        return text

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty / closed
        return False
