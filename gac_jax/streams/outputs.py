"""What a stream writes: the annotated video and the per-frame results, as frames finish.

* :class:`AnnotatedVideo`: ``cv2.VideoWriter`` at the input's fps, codec by the container
  suffix (:data:`CODECS`: ``.mp4``/``.m4v``/``.mov`` MPEG-4 part 2 ``mp4v``, ``.avi``/``.mkv``
  Motion JPEG). It is written to a hidden ``.<name>.partial<suffix>`` beside the target and
  renamed when released, so an earlier video of the same name stays whole until the new one is.
  Frames of an odd size get a black row / column at the bottom / right (FFmpeg's MPEG-4 and
  Motion JPEG encoders would cut them).
* :class:`KittiResults`: ``DIR/<frame id>.txt`` per frame (KITTI result lines with scores,
  written atomically), the files ``python -m gac_jax.cli.predict IMAGE_DIR`` writes.
* :class:`JsonlResults`: one JSON object per frame and line, flushed per frame (``.partial``
  until closed, like the video).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti import KittiObjects, write_label

CODECS = {".mp4": "mp4v", ".m4v": "mp4v", ".mov": "mp4v", ".avi": "MJPG", ".mkv": "MJPG"}
DEFAULT_FPS = 10.0  # when the input does not say (a camera without the property)


def partial_path(path: Path) -> Path:
    """``dir/.name.partial.suffix``: where ``path`` is written until it is complete."""
    return path.with_name(f".{path.stem}.partial{path.suffix}")


def check_video_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.suffix.lower() not in CODECS:
        raise KittiFormatError(
            path, f"unknown video container {path.suffix!r} (use one of {', '.join(CODECS)})"
        )
    return path


class AnnotatedVideo:
    """Writes RGB pictures as video frames (the writer opens at the first picture's size).

    Args:
      path: the video (container by suffix, :data:`CODECS`).
      fps: frames per second of the video (None: :data:`DEFAULT_FPS`).
    """

    def __init__(self, path: str | os.PathLike, fps: float | None):
        self.path = check_video_path(path)
        self.fps = fps or DEFAULT_FPS
        self.partial = partial_path(self.path)
        self.frames = 0
        self.size: tuple[int, int] | None = None
        self._writer: cv2.VideoWriter | None = None
        self._pad = (0, 0)  # rows, columns added at the bottom / right

    def write(self, rgb: np.ndarray) -> None:
        h, w = rgb.shape[:2]
        if self._writer is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            codec = CODECS[self.path.suffix.lower()]
            # the codecs want even sizes (FFmpeg would cut the last row / column): pad instead
            self._pad = (h % 2, w % 2)
            size = (w + self._pad[1], h + self._pad[0])
            fourcc = cv2.VideoWriter_fourcc(*codec)
            self._writer = cv2.VideoWriter(os.fspath(self.partial), fourcc, self.fps, size)
            if not self._writer.isOpened():
                raise KittiFormatError(self.path, f"OpenCV cannot write this video ({w}x{h})")
            self.size = (h, w)
        if (h, w) != self.size:
            raise ValueError(f"picture of {w}x{h} in a video of {self.size[1]}x{self.size[0]}")
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self._pad != (0, 0):
            bgr = cv2.copyMakeBorder(bgr, 0, self._pad[0], 0, self._pad[1], cv2.BORDER_CONSTANT)
        self._writer.write(bgr)
        self.frames += 1

    def close(self) -> None:
        """Releases the writer (the video is then playable) and renames it into place."""
        if self._writer is None:
            return
        self._writer.release()
        self._writer = None
        os.replace(self.partial, self.path)


class KittiResults:
    """``folder/<frame id>.txt``: KITTI result lines (with scores) per frame, atomically."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self.frames = 0

    def write(self, frame_id: str, index: int, objects: KittiObjects, record: dict) -> None:
        write_label(self.folder / f"{frame_id}.txt", objects, with_score=True)
        self.frames += 1

    def close(self) -> None:
        pass


class JsonlResults:
    """One line per frame: ``{"frame": id, "index": i, **record}`` (``record``: the detections'
    ``to_dict()``), flushed as each frame finishes."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.partial, "w", encoding="utf-8")  # noqa: SIM115 (closed in close)
        self.frames = 0

    def write(self, frame_id: str, index: int, objects: KittiObjects, record: dict) -> None:
        line = json.dumps({"frame": frame_id, "index": index, **record}, default=_plain)
        self._file.write(line + "\n")
        self._file.flush()
        self.frames += 1

    def close(self) -> None:
        if self._file.closed:
            return
        self._file.close()
        os.replace(self.partial, self.path)


def _plain(value):
    """JSON for numpy values of a record."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
