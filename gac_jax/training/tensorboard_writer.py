"""TensorBoard event files (``WORKDIR/tensorboard/events.out.tfevents.*``) without TensorFlow.

Written with the ``tensorboard`` package's own event-file writer and protocol buffers
(the writer PyTorch's ``SummaryWriter`` uses too); nothing imports TensorFlow or PyTorch.
View with ``tensorboard --logdir workdirs``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.io_errors import naming

DIFFICULTIES = ("easy", "moderate", "hard")


def flatten_scalars(values: Mapping, prefix: str = "") -> dict[str, float]:
    """Numbers of a nested dict as ``{'a/b/c': value}``; strings and None are left out.

    Lists get their index as the last name, except 3-long lists of KITTI AP
    (``.../ap11/...`` or ``.../ap40/...``), which are named easy / moderate / hard.
    """
    out: dict[str, float] = {}
    for key, value in values.items():
        name = f"{prefix}/{key}" if prefix else str(key)
        if isinstance(value, Mapping):
            out.update(flatten_scalars(value, name))
        elif isinstance(value, list | tuple):
            is_ap = len(value) == 3 and any(p in ("ap11", "ap40") for p in name.split("/"))
            names = DIFFICULTIES if is_ap else [str(i) for i in range(len(value))]
            out.update(flatten_scalars(dict(zip(names, value, strict=True)), name))
        elif isinstance(value, int | float | np.number):  # (bool is an int)
            out[name] = float(value)
    return out


class TensorBoardWriter:
    """Scalars and images of a run, as TensorBoard event files in ``logdir``.

    ``resume_step``: the run continues from that step (a checkpoint); TensorBoard
    then discards the events of later steps written before the interruption
    (a ``SessionLog.START`` at the next step), so the curves show one history.
    """

    def __init__(self, logdir: str | os.PathLike, resume_step: int | None = None):
        try:
            from tensorboard.compat.proto import event_pb2, summary_pb2
            from tensorboard.summary.writer.event_file_writer import EventFileWriter
        except ImportError as e:
            raise ImportError(
                "TensorBoard event files need the 'tensorboard' package (pip install "
                "tensorboard); or turn them off with log.tensorboard=false"
            ) from e
        self._event_pb2, self._summary_pb2 = event_pb2, summary_pb2
        self.logdir = Path(logdir)
        self.logdir.mkdir(parents=True, exist_ok=True)
        with naming(self.logdir):
            self._writer = EventFileWriter(str(self.logdir), flush_secs=30)
        # Failed writes (a full disk) name the event file (the writer's thread does not).
        self.path = Path(getattr(self._writer, "_file_name", self.logdir))
        if resume_step:
            start = event_pb2.SessionLog(status=event_pb2.SessionLog.START)
            # TensorBoard drops the earlier events of steps >= this one.
            self._add(event_pb2.Event(step=int(resume_step) + 1, session_log=start))

    def _add(self, event) -> None:
        event.wall_time = time.time()
        with naming(self.path):
            self._writer.add_event(event)

    def scalars(self, step: int, values: Mapping[str, float]) -> None:
        """One scalar per tag (``{'train/loss': 0.3}``); non-finite values are kept as such."""
        s = self._summary_pb2
        items = [s.Summary.Value(tag=t, simple_value=float(v)) for t, v in values.items()]
        if items:
            self._add(self._event_pb2.Event(step=int(step), summary=s.Summary(value=items)))

    def image(self, step: int, tag: str, image: np.ndarray) -> None:
        """An (H, W, 3) uint8 RGB image (or (H, W) gray), stored PNG-encoded."""
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim not in (2, 3):
            raise ValueError(f"{tag}: expected an (H, W[, 3]) uint8 image, got {image.shape}")
        bgr = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        ok, png = cv2.imencode(".png", bgr)
        if not ok:
            raise ValueError(f"{tag}: PNG encoding failed")
        s = self._summary_pb2
        picture = s.Summary.Image(
            height=image.shape[0],
            width=image.shape[1],
            colorspace=1 if image.ndim == 2 else 3,
            encoded_image_string=png.tobytes(),
        )
        summary = s.Summary(value=[s.Summary.Value(tag=tag, image=picture)])
        self._add(self._event_pb2.Event(step=int(step), summary=summary))

    def image_file(self, step: int, tag: str, path: str | os.PathLike) -> None:
        """A PNG/JPEG file from disk (e.g. an evaluation picture) as image ``tag``."""
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"{path}: not a readable image")
        self.image(step, tag, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))

    def flush(self) -> None:
        with naming(self.path):
            self._writer.flush()

    def close(self) -> None:
        with naming(self.path):
            self._writer.close()
