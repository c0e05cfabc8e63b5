"""Training telemetry: a JSON-lines metrics file (and the same numbers as TensorBoard event
files) and a progress line with loss, images/s and ETA.

Only process 0 writes (``enabled=False`` elsewhere). Device values are
fetched by the caller at log steps only.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

from tqdm import tqdm

from gac_jax.data.files import atomic_write
from gac_jax.data.io_errors import naming


class MetricsWriter:
    """Appends one JSON object per line to ``WORKDIR/metrics.jsonl``.

    On resume from ``resume_step`` the lines of later steps (written by the
    interrupted run after its last checkpoint) are dropped, so the file
    describes exactly one history.

    With ``tensorboard=True`` every number written also goes to TensorBoard event
    files in ``WORKDIR/tensorboard`` (tag ``<kind>/<key>``, nested keys joined by
    ``/``), and :meth:`pictures` adds evaluation pictures there.
    """

    def __init__(
        self,
        workdir: str | os.PathLike,
        enabled: bool = True,
        resume_step: int | None = None,
        tensorboard: bool = False,
    ):
        self.path = Path(workdir) / "metrics.jsonl"
        self.enabled = enabled
        self.tensorboard = None
        if not enabled:
            return
        if tensorboard:
            from gac_jax.training.tensorboard_writer import TensorBoardWriter

            self.tensorboard = TensorBoardWriter(Path(workdir) / "tensorboard", resume_step)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():
            keep = []
            for line in self.path.read_text().splitlines():
                try:
                    record = json.loads(line)
                except json.JSONDecodeError:
                    continue  # a torn last line from a killed run
                if resume_step is not None and record.get("step", 0) <= resume_step:
                    keep.append(line)
            with atomic_write(self.path) as f:
                f.write("".join(line + "\n" for line in keep))

    def write(self, step: int, kind: str = "train", **values) -> None:
        if not self.enabled:
            return
        record = {"step": int(step), "kind": kind, "time": round(time.time(), 3)}
        record.update({k: _jsonable(v) for k, v in values.items()})
        with naming(self.path), open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
        if self.tensorboard is not None:
            from gac_jax.training.tensorboard_writer import flatten_scalars

            self.tensorboard.scalars(step, flatten_scalars(values, kind))
            if kind != "train":  # evaluations are rare: visible at once
                self.tensorboard.flush()

    def pictures(self, step: int, paths, tag: str = "eval/pictures") -> None:
        """Image files (evaluation pictures) as TensorBoard images ``<tag>/<file stem>``."""
        if self.tensorboard is None:
            return
        for path in sorted(Path(p) for p in paths):
            self.tensorboard.image_file(step, f"{tag}/{path.stem}", path)
        self.tensorboard.flush()

    def flush(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.flush()

    def close(self) -> None:
        if self.tensorboard is not None:
            self.tensorboard.close()
            self.tensorboard = None


def _jsonable(v):
    if hasattr(v, "item") and getattr(v, "size", 2) == 1:
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


# Share of a logging window the device waited for data above which the run says so (again
# after DATA_WAIT_REPEAT windows if it stays above: the progress line shows it every window).
DATA_WAIT_WARNING = 0.2
DATA_WAIT_REPEAT = 10


class Progress:
    """A progress bar (interactive terminals) or periodic log lines (files, CI).

    Shows step/total, loss, images/s, the share of the time the device waited for data
    (``data 3%``) and ETA. A window in which that share exceeds :data:`DATA_WAIT_WARNING`
    prints one warning line naming ``data.num_workers`` (``num_workers``), repeated at most
    every :data:`DATA_WAIT_REPEAT` windows.
    """

    def __init__(
        self,
        total_steps: int,
        start_step: int,
        batch_size: int,
        enabled: bool = True,
        num_workers: int | None = None,
    ):
        self.total, self.batch_size, self.enabled = total_steps, batch_size, enabled
        self.start_step = start_step
        self.num_workers = num_workers
        self._t_last, self._s_last = time.perf_counter(), start_step
        self._windows, self._warned_window = 0, None
        self._interactive = enabled and sys.stderr.isatty()
        self._bar = None
        if self._interactive:
            self._bar = tqdm(total=total_steps, initial=start_step, unit="step", dynamic_ncols=True)

    def restart(self, step: int) -> None:
        """The next window starts now, at ``step`` (after compiling: it is not throughput)."""
        self._t_last, self._s_last = time.perf_counter(), step

    def update(
        self, step: int, loss: float, extra: dict | None = None, data_wait_s: float | None = None
    ) -> dict:
        """Called at log steps; returns the throughput figures it computed.

        ``data_wait_s``: seconds the device waited for batches since the previous call
        (:class:`~gac_jax.training.data_wait.DataWaitClock`); reported as the share
        ``data_wait`` of the window's wall time.
        """
        now = time.perf_counter()
        first = self._s_last
        steps = max(step - self._s_last, 1)
        dt = max(now - self._t_last, 1e-9)
        ips = steps * self.batch_size / dt
        eta = (self.total - step) * dt / steps
        self._t_last, self._s_last = now, step
        stats = {"images_per_s": ips, "eta_s": eta}
        if data_wait_s is not None:
            stats["data_wait"] = min(max(data_wait_s / dt, 0.0), 1.0)
        if not self.enabled:
            return stats
        text = f"loss {loss:.4f} | {ips:.1f} img/s"
        if "data_wait" in stats:
            text += f" | data {100 * stats['data_wait']:.0f}%"
        if extra:
            text += " | " + " ".join(f"{k} {v:.3g}" for k, v in extra.items())
        if self._bar is not None:
            self._bar.n = step
            self._bar.set_postfix_str(text, refresh=True)
        else:
            print(f"step {step}/{self.total} | {text} | ETA {_fmt(eta)}", flush=True)
        self._windows += 1
        recent = self._warned_window is not None and (
            self._windows - self._warned_window < DATA_WAIT_REPEAT
        )
        if stats.get("data_wait", 0.0) > DATA_WAIT_WARNING and not recent:
            self._warned_window = self._windows
            self._warn(
                f"warning: steps {first + 1}-{step} waited for data "
                f"{100 * stats['data_wait']:.0f}% of the time: the input pipeline is the "
                f"bottleneck; raise data.num_workers (now {self.num_workers})"
                " (benchmarks/bench_loader.py: images/s of one worker)"
            )
        return stats

    def _warn(self, line: str) -> None:
        if self._bar is not None:
            self._bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _fmt(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{s:02d}" if h else f"{m:d}:{s:02d}"
