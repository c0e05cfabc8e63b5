"""What a stream writes: the annotated video and the per-frame results, as frames finish.

Every write is checked; a failed one raises an ``OSError`` naming the file and the cause
(no space left, permission denied), and what was written before stays valid:

* :class:`AnnotatedVideo`: ``.mp4``/``.m4v``/``.mov`` are fragmented MP4 files encoded by
  FFmpeg through PyAV on a thread of their own (:mod:`gac_jax.streams.video_encoder`): H.264
  (browsers play it) or Motion JPEG (``codec="mjpeg"``); the file is a playable video of
  whole frames at every moment, after a full disk or a kill too. ``.avi``/``.mkv`` are
  Motion JPEG through ``cv2.VideoWriter`` (a failed frame is detected, but only a clean close
  leaves a playable file). The video is written to a hidden ``.<name>.partial<suffix>``
  beside the target and renamed into place when the stream ends (at its end or when stopped
  by Ctrl-C, SIGTERM, SIGHUP), so an earlier video of the same name is only replaced by a
  complete one; after a failed write the frames written so far are kept as
  ``<name>.incomplete<suffix>`` and an earlier video stays as it was.
* :class:`KittiResults`: ``DIR/<frame id>.txt`` per frame (KITTI result lines with scores,
  written atomically), the files ``python -m gac_jax.cli.predict IMAGE_DIR`` writes.
* :class:`JsonlResults`: one JSON object per frame and line, each line written whole or cut
  off again (the file always ends on a whole line); ``.partial`` until closed, like the video.

Frames of the video and result files are written in the same order, the video first. The
MP4 encoder runs behind the writer by a frame or two, so :func:`close_outputs` closes the
video first and cuts the results to the frames the video holds (and the video to the frames
with results): after a failed write the video and the results hold the same frames.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.files import KittiFormatError
from gac_jax.data.io_errors import free_bytes
from gac_jax.data.kitti import KittiObjects, write_label
from gac_jax.streams import video_encoder

CONTAINERS = {".mp4": "PyAV", ".m4v": "PyAV", ".mov": "PyAV", ".avi": "MJPG", ".mkv": "MJPG"}
FRAGMENTED = (".mp4", ".m4v", ".mov")  # written by video_encoder, the others by OpenCV
DEFAULT_FPS = 10.0  # when the input does not say (a camera without the property)


def partial_path(path: Path) -> Path:
    """``dir/.name.partial.suffix``: where ``path`` is written until it is complete."""
    return path.with_name(f".{path.stem}.partial{path.suffix}")


def incomplete_path(path: Path) -> Path:
    """``dir/name.incomplete.suffix``: what a failed write keeps of ``path``."""
    return path.with_name(f"{path.stem}.incomplete{path.suffix}")


def check_video_path(path: str | os.PathLike, codec: str | None = None) -> Path:
    """``path`` if its container is known and can hold ``codec`` (None: the default)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CONTAINERS:
        raise KittiFormatError(
            path, f"unknown video container {path.suffix!r} (use one of {', '.join(CONTAINERS)})"
        )
    if codec is not None and codec not in video_encoder.CODECS:
        raise KittiFormatError(
            "--codec", f"unknown codec {codec!r} (use one of {', '.join(video_encoder.CODECS)})"
        )
    if suffix not in FRAGMENTED and codec not in (None, "mjpeg"):
        raise KittiFormatError(
            path, f"{suffix} is written as Motion JPEG; {codec} needs .mp4, .m4v or .mov"
        )
    return path


def _keep(partial: Path, path: Path, complete: bool, frames: int) -> Path | None:
    """Renames ``partial`` to ``path`` (complete) or to its incomplete name; deletes it when it
    holds no frame. Returns where the frames are (None: nowhere)."""
    if frames == 0:
        partial.unlink(missing_ok=True)
        return None
    target = path if complete else incomplete_path(path)
    os.replace(partial, target)
    return target


class AnnotatedVideo:
    """Writes RGB pictures as video frames (the file opens at the first picture's size).

    Args:
      path: the video (container by suffix, :data:`CONTAINERS`).
      fps: frames per second of the video (None: :data:`DEFAULT_FPS`).
      codec: ``h264`` or ``mjpeg`` for an MP4 (:mod:`gac_jax.streams.video_encoder`; None:
        ``h264``); ``.avi``/``.mkv`` are Motion JPEG.
    """

    def __init__(self, path: str | os.PathLike, fps: float | None, codec: str | None = None):
        self.path = check_video_path(path, codec)
        self.fps = fps or DEFAULT_FPS
        mp4 = self.path.suffix.lower() in FRAGMENTED
        self.codec = (codec or video_encoder.DEFAULT_CODEC) if mp4 else "mjpeg"
        self.partial = partial_path(self.path)
        self.kept: Path | None = None  # where close() left the frames
        self.size: tuple[int, int] | None = None
        self._mp4: video_encoder.Mp4Video | None = None
        self._writer: cv2.VideoWriter | None = None
        self._frames = 0
        self._keep: int | None = None  # drop_last: frames to keep at most
        self._encoder_cpu_s = 0.0
        self._closed = False
        self._pad = (0, 0)  # rows, columns added at the bottom / right (OpenCV's codecs)

    @property
    def frames(self) -> int:
        """Frames whole in the file (an MP4's encoder may still hold the newest ones)."""
        return self._mp4.frames if self._mp4 is not None else self._frames

    @property
    def encoder_cpu_s(self) -> float:
        """CPU seconds of the MP4 encoder's thread (0 for OpenCV's writer)."""
        return self._mp4.cpu_s if self._mp4 is not None else self._encoder_cpu_s

    def _open(self, h: int, w: int) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.size = (h, w)
        if self.path.suffix.lower() in FRAGMENTED:
            try:
                self._mp4 = video_encoder.Mp4Video(
                    self.partial, self.path, self.fps, (h, w), self.codec
                )
            except OSError as e:
                self.partial.unlink(missing_ok=True)
                raise OSError(e.errno, e.strerror, os.fspath(self.path)) from None
            return
        # the codecs want even sizes (FFmpeg would cut the last row / column): pad instead
        self._pad = (h % 2, w % 2)
        size = (w + self._pad[1], h + self._pad[0])
        fourcc = cv2.VideoWriter_fourcc(*CONTAINERS[self.path.suffix.lower()])
        self._writer = cv2.VideoWriter(os.fspath(self.partial), fourcc, self.fps, size)
        if not self._writer.isOpened():
            raise KittiFormatError(self.path, f"OpenCV cannot write this video ({w}x{h})")

    def write(self, rgb: np.ndarray, time_s: float | None = None) -> None:
        """Appends one picture (H, W, 3) uint8 RGB shown at ``time_s`` seconds (the frame's
        own time; None: ``1 / fps`` after the previous; MP4 only, OpenCV's containers play at
        ``fps``); raises ``OSError`` naming the file when it cannot be written (the frames
        before it stay). An MP4's frames are encoded on the encoder's thread: its failure is
        raised by the next ``write`` or ``close``."""
        h, w = rgb.shape[:2]
        if self.size is None:
            self._open(h, w)
        if (h, w) != self.size:
            raise ValueError(f"picture of {w}x{h} in a video of {self.size[1]}x{self.size[0]}")
        if self._mp4 is not None:
            self._mp4.write(rgb, time_s)
            return
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self._pad != (0, 0):
            bgr = cv2.copyMakeBorder(bgr, 0, self._pad[0], 0, self._pad[1], cv2.BORDER_CONSTANT)
        if not self._writer.write(bgr):
            raise _write_failed(self.path)
        self._frames += 1

    def drop_last(self) -> bool:
        """Cuts the last frame off again (MP4 only, when the video closes); False when the
        container cannot."""
        if self._mp4 is None:
            return False
        self._keep = self._mp4.submitted - 1 if self._keep is None else self._keep - 1
        return True

    def close(self, complete: bool = True, frames: int | None = None) -> Path | None:
        """Finishes the file and renames it: into place when ``complete`` (the stream ended or
        was stopped), else to ``<name>.incomplete<suffix>``. ``frames``: keep at most this
        many (MP4). Returns where the frames are (None: no frame was written); raises the
        encoder's error after keeping the frames before it. Idempotent."""
        if self._closed:
            return self.kept
        self._closed = True
        if self._mp4 is not None:
            limits = [n for n in (frames, self._keep) if n is not None]
            mp4, self._mp4 = self._mp4, None
            try:
                self._frames = mp4.close(min(limits) if limits else None)
            except Exception:
                self._frames = mp4.kept_frames
                self.kept = _keep(self.partial, self.path, False, self._frames)
                raise
            finally:
                self._encoder_cpu_s = mp4.cpu_s
        elif self._writer is not None:
            self._writer.release()
            self._writer = None
        elif self.frames == 0:
            return None
        self.kept = _keep(self.partial, self.path, complete, self.frames)
        return self.kept


def _write_failed(path: Path) -> OSError:
    """OpenCV says only that a frame was not written: a full disk is the likely cause."""
    free = free_bytes(path)
    code = errno.ENOSPC if free is not None and free < (1 << 20) else errno.EIO
    return OSError(code, os.strerror(code), os.fspath(path))


class KittiResults:
    """``folder/<frame id>.txt``: KITTI result lines (with scores) per frame, atomically."""

    needs_record = False  # the objects are all it writes: the pipeline skips ``to_dict()``

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        self.frames = 0
        self._written: list[Path] = []

    @property
    def location(self) -> Path:
        return self.folder

    def write(self, frame_id: str, index: int, objects: KittiObjects, record: dict) -> None:
        path = self.folder / f"{frame_id}.txt"
        write_label(path, objects, with_score=True)
        self._written.append(path)
        self.frames += 1

    def truncate(self, frames: int) -> None:
        """Deletes the files of the frames after the first ``frames`` again."""
        while self.frames > frames:
            self._written.pop().unlink(missing_ok=True)
            self.frames -= 1

    def close(self, complete: bool = True) -> Path:
        return self.folder


class JsonlResults:
    """One line per frame: ``{"frame": id, "index": i, **record}`` (``record``: the detections'
    ``to_dict()``), written as each frame finishes; a line is written whole or not at all."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.partial = partial_path(self.path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        self._end = 0
        self._ends: list[int] = []  # the file's end before each frame
        self.frames = 0
        self.kept: Path | None = None

    @property
    def location(self) -> Path:
        return self.path

    def write(self, frame_id: str, index: int, objects: KittiObjects, record: dict) -> None:
        line = json.dumps({"frame": frame_id, "index": index, **record}, default=_plain)
        self.append_frame(line + "\n")

    def append_frame(self, text: str) -> None:
        """Appends one frame's ``text`` (whole lines) whole, or not at all (the file is cut
        back to the previous frame's end and the error names the file)."""
        data = memoryview(text.encode())
        done = 0
        try:
            while done < len(data):
                done += os.pwrite(self._fd, data[done:], self._end + done)
        except OSError as e:
            os.ftruncate(self._fd, self._end)  # the file ends on the last whole line
            raise OSError(e.errno, e.strerror, os.fspath(self.path)) from None
        self._ends.append(self._end)
        self._end += len(data)
        self.frames += 1

    def truncate(self, frames: int) -> None:
        """Cuts the lines of the frames after the first ``frames`` off again."""
        if frames < self.frames and self._fd >= 0:
            self._end = self._ends[frames]
            del self._ends[frames:]
            os.ftruncate(self._fd, self._end)
            self.frames = frames

    def close(self, complete: bool = True) -> Path | None:
        """Closes and renames (as :meth:`AnnotatedVideo.close`)."""
        if self._fd < 0:
            return self.kept
        try:
            os.fsync(self._fd)
        finally:
            os.close(self._fd)
            self._fd = -1
        self.kept = _keep(self.partial, self.path, complete, self.frames)
        return self.kept


def close_outputs(video, others, complete: bool) -> tuple[list[Path], BaseException | None]:
    """Closes a stream's outputs: the video first (its encoder finishes the queued frames),
    then ``others`` (results writers, recordings), each cut to the frames the video holds;
    the video is cut to the frames the first of ``others`` (the results) holds. ``complete``:
    rename into place (else ``.incomplete``). Returns where the outputs are and the first
    error of a close (the others are closed all the same)."""
    kept: list[Path] = []
    error: BaseException | None = None
    results = next((o for o in others if o is not None), None)
    frames = getattr(results, "frames", None)
    if video is not None:
        try:
            where = video.close(complete, frames)
        except OSError as e:
            error, where, complete = e, video.kept, False
        if where is not None:
            kept.append(where)
        frames = video.frames
    for output in others:
        if output is None:
            continue
        if video is not None and hasattr(output, "truncate"):
            output.truncate(frames)
        try:
            where = output.close(complete)
        except OSError as e:
            error = error or e
            where = getattr(output, "kept", None)
        if where is not None:
            kept.append(where)
    return kept, error


def _plain(value):
    """JSON for numpy values of a record."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
