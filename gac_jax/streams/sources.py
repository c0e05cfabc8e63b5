"""Frame sources of a stream: a video file, a camera, an image sequence (KITTI tracking layout).

Every source gives :class:`Frame` objects in order from :meth:`read` (``None`` at the end),
each with its calibration ``P2`` and ground plane, and checks the calibration against the
first frame's size before anything else runs, so a wrong input fails in a second with one
line (:class:`~gac_jax.data.files.KittiFormatError`, ``<input>: <problem>``).

* :class:`VideoSource`: any container FFmpeg reads (PyAV); the frames' own timestamps; a
  damaged frame is skipped, a file whose last frames cannot be decoded is reported by
  :meth:`VideoSource.check_complete` (:mod:`gac_jax.streams.damaged_frames`).
* :class:`CameraSource`: a ``cv2.VideoCapture`` device (``live``: frames come at the camera's
  pace whether or not they are taken; a frame's time is when it was read).
* :class:`SequenceSource`: a folder of images, sorted by name; in the KITTI tracking layout
  (``ROOT/training/image_02/SSSS/NNNNNN.png``) the calibration ``ROOT/training/calib/SSSS.txt``
  and the per-frame planes ``ROOT/training/planes/SSSS/NNNNNN.txt`` are found by themselves;
  in the KITTI raw layout (``DATE/DATE_drive_NNNN_sync/image_02/data``, its ``image_02`` or
  the drive folder) the day's ``DATE/calib_cam_to_cam.txt`` (with the day's other two files)
  and the frames' times ``image_02/timestamps.txt`` (:mod:`gac_jax.data.kitti_raw`); an image
  that cannot be read is skipped.
* :class:`PacedSource`: another source delivered at a fixed rate, as a camera would (a
  recording replayed live: ``--realtime`` on a file).

Images are RGB uint8 ``(H, W, 3)``; ``P2`` (3, 4) projects camera coordinates (x right,
y down, z forward) to pixels (u right, v down); a plane is ``(a, b, c, d)`` in the camera
frame, ``None`` for the detector's level camera.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np

from gac_jax.api.inputs import InputError, check_fits, check_projection
from gac_jax.data.files import KittiFormatError, decode_image, read_bytes
from gac_jax.data.kitti import read_plane
from gac_jax.data.kitti_calib import read_calib
from gac_jax.streams.damaged_frames import DamagedFrames
from gac_jax.streams.input_files import check_input_file
from gac_jax.streams.sequence_layout import (
    IMAGE_SUFFIXES,
    SequenceFiles,
    sequence_files,
    sequence_images,
)

__all__ = ["IMAGE_SUFFIXES", "SequenceFiles", "sequence_files", "sequence_images"]

MAX_CAMERA = 99  # OpenCV reads a camera index of 100 or more as backend * 100 + device


def quiet_video_backend() -> None:
    """Keeps OpenCV's and FFmpeg's own messages (``moov atom not found``, ``can't open camera
    by index``) off stderr: the caller reports a failure as one line. FFmpeg reads its setting
    when it first opens a file, so call this before any video is opened."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


@dataclasses.dataclass
class Frame:
    """One frame of a stream.

    Attributes:
      index: position in the stream (0, 1, ...; frames a live source dropped count too).
      frame_id: name of the frame's results (``NNNNNN`` or the image's stem).
      image: (H, W, 3) uint8 RGB.
      P2: (3, 4) float64 projection of the frame.
      plane: (4,) ground plane in the camera frame; None: the detector's level camera.
      t_read: ``time.perf_counter()`` when reading the frame began (latency starts here).
      time: the frame's time in seconds from the stream's first frame (a video's timestamps,
        a KITTI raw drive's ``timestamps.txt``, else a sequence's frame rate, a camera's read
        times): the tracker's and the annotated video's timing. None: unknown (``index / fps``
        is assumed).
      jpeg: the bytes of the JPEG file the image was read from (an MCAP recording stores
        them as they are), or None.
    """

    index: int
    frame_id: str
    image: np.ndarray
    P2: np.ndarray
    plane: np.ndarray | None
    t_read: float
    time: float | None = None
    jpeg: bytes | None = None


def load_projection(path: str | os.PathLike, camera: int = 2) -> np.ndarray:
    """(3, 4) ``P2`` (``camera`` 3: ``P3``) of a KITTI calibration file of any format
    (:func:`gac_jax.data.kitti_calib.read_calib`)."""
    return np.asarray(read_calib(path, camera).projection(camera), np.float64)


def check_calibration(P2: np.ndarray, size: tuple[int, int], calib: str, frames: str) -> None:
    """Raises :class:`KittiFormatError` naming ``calib`` if ``P2`` cannot be the calibration of
    ``frames`` of ``size = (H, W)``: the API's checks (:func:`gac_jax.api.inputs.check_projection`,
    :func:`~gac_jax.api.inputs.check_fits`), with the principal point in the middle of the
    frame.
    """
    try:
        check_fits(check_projection(P2), size, what=f"frames of {frames}", centre_band=True)
    except InputError as e:
        raise KittiFormatError(calib, e.problem) from None


def _check_size(image: np.ndarray, size: tuple[int, int], where: str, what: str) -> None:
    if image.shape[:2] != size:
        h, w = image.shape[:2]
        raise KittiFormatError(
            where,
            f"frame is {w}x{h} but {what} {size[1]}x{size[0]} (one calibration per stream)",
        )


class VideoSource:
    """Frames of a video file, decoded in order (PyAV: FFmpeg's demuxers and decoders).

    Args:
      path: the video (any container and codec FFmpeg reads; a name that is not UTF-8 too).
      P2: (3, 4) its calibration, read from ``calib`` (named in errors).
      plane: (4,) ground plane of every frame, or None.
      decode_threads: the decoder's threads (a stream's thread budget: 1, the read stage is
        a thread of its own); None: FFmpeg's own choice (every core).
      warn: where the warning line of a damaged frame goes (default stderr).

    A frame's time is its timestamp in the container (PTS, seconds from the first frame), so
    a variable-frame-rate recording keeps its timing; a frame without one (or one not after
    the previous) is placed ``1 / fps`` after the previous. A frame the decoder rejects, or a
    packet the container flags as corrupt, is skipped (:mod:`gac_jax.streams.damaged_frames`);
    the header's frame count is only reported (:attr:`expected_frames`), never relied on.
    """

    live = False

    def __init__(
        self,
        path,
        P2: np.ndarray,
        calib: str,
        plane: np.ndarray | None = None,
        decode_threads: int | None = None,
        warn=None,
    ):
        import av

        self.name = os.fspath(path)
        check_input_file(path, "video")
        try:
            self._container = av.open(self.name, metadata_errors="ignore")
        except PermissionError:
            raise KittiFormatError(path, "cannot be read (permission denied)") from None
        except (av.error.FFmpegError, OSError, ValueError):
            raise KittiFormatError(
                path, "cannot be opened as a video (damaged, truncated or not a video file)"
            ) from None
        if not self._container.streams.video:
            self.close()
            raise KittiFormatError(path, "holds no video stream")
        self._stream = self._container.streams.video[0]
        codec = self._stream.codec_context
        codec.thread_type = "AUTO"
        codec.thread_count = 0 if decode_threads is None else int(decode_threads)
        rate = self._stream.guessed_rate or self._stream.average_rate
        fps = float(rate) if rate else math.nan
        self.fps = fps if math.isfinite(fps) and fps > 0 else None
        self.expected_frames = self._stream.frames or None  # the header's: reported only
        self.P2, self.plane = np.asarray(P2, np.float64), plane
        self.damaged = DamagedFrames(self.name, "frame", warn)
        self.decoded = 0
        self.position = 0  # frames decoded or found damaged
        self._packets = None
        self._ready: list = []  # (position, av.VideoFrame) decoded, not yet delivered
        self._ended = False
        self._t0: float | None = None
        self._last_time: float | None = None
        t0 = time.perf_counter()
        first = self._next_image()
        if first is None:
            self.close()
            raise KittiFormatError(path, "no frame could be decoded (damaged or truncated video)")
        self.size = first[1].shape[:2]
        check_calibration(self.P2, self.size, calib, self.name)
        self._pending = (first, t0)

    @property
    def decode_threads(self) -> int | None:
        """The decoder's threads (None: FFmpeg's own choice)."""
        n = int(self._stream.codec_context.thread_count)
        return n if n > 0 else None

    def _decode_packet(self, packet) -> None:
        """Decodes ``packet`` into :attr:`_ready`; a rejected or corrupt one is a damaged
        frame."""
        import av

        if packet.size and packet.is_corrupt:  # cut short (a truncated file) or flagged
            self._damaged("is cut short or corrupt in the container")
            return
        try:
            frames = packet.decode()
        except av.error.EOFError:
            frames = []
        except (av.error.FFmpegError, ValueError) as e:
            self._damaged(f"cannot be decoded ({_reason(e)})")
            return
        for frame in frames:
            if frame.is_corrupt:
                self._damaged("is decoded with errors (corrupt)")
                continue
            self._ready.append((self.position, frame))
            self.position += 1

    def _damaged(self, reason: str) -> None:
        i, self.position = self.position, self.position + 1
        self.damaged.skip(f"{i:06d}", reason)

    def _next_image(self) -> tuple[int, np.ndarray, float] | None:
        """``(position, RGB image, time)`` of the next whole frame, None at the end."""
        import av

        while not self._ready:
            if self._ended:
                return None
            if self._packets is None:
                self._packets = self._container.demux(self._stream)
            try:
                packet = next(self._packets)
            except StopIteration:
                self._ended = True
                continue
            except (av.error.FFmpegError, ValueError) as e:  # the container itself is damaged
                self._packets = None  # a new demuxing pass resumes after the damage
                self._damaged(f"cannot be read from the container ({_reason(e)})")
                continue
            self._decode_packet(packet)
        position, frame = self._ready.pop(0)
        image = frame.to_ndarray(format="rgb24")
        self.decoded += 1
        self.damaged.good()
        return position, image, self._frame_time(frame.time)

    def _frame_time(self, t: float | None) -> float:
        """Seconds from the first frame (see the class doc)."""
        known = t is not None and math.isfinite(t)
        if self._t0 is None:
            self._t0, self._last_time = (t if known else 0.0), 0.0
            return 0.0
        step = 1.0 / (self.fps or 10.0)
        relative = t - self._t0 if known else self._last_time + step
        if not relative > self._last_time:
            relative = self._last_time + step
        self._last_time = relative
        return relative

    def read(self) -> Frame | None:
        if self._pending is not None:
            (item, t0), self._pending = self._pending, None
        else:
            t0 = time.perf_counter()
            item = self._next_image()
            if item is None:
                return None
        i, image, t = item
        _check_size(image, self.size, f"{self.name} frame {i}", "the first frame is")
        return Frame(i, f"{i:06d}", image, self.P2, self.plane, t0, t)

    def check_complete(self) -> None:
        """After the last frame: raises if the frames just before the end were damaged (a
        truncated file); the header's frame count is not consulted."""
        self.damaged.check_end(self.decoded)

    def close(self) -> None:
        self._container.close()


def _reason(error: BaseException) -> str:
    """FFmpeg's reason for ``error`` without PyAV's errno and function name."""
    text = getattr(error, "strerror", None) or str(error)
    return str(text).rstrip(".").lower()


class CameraSource:
    """Frames of a live camera (``cv2.VideoCapture(index)``).

    Args:
      index: the device index (``/dev/video<index>`` on Linux).
      P2, calib, plane: as :class:`VideoSource`.
    """

    live = True
    expected_frames = None

    def __init__(self, index: int, P2: np.ndarray, calib: str, plane: np.ndarray | None = None):
        self.name = f"camera {index}"
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index <= MAX_CAMERA:
            # OpenCV takes -1 as "any camera" (some backends crash on it) and an index of 100
            # or more as a backend's number plus a device
            raise KittiFormatError(self.name, f"a camera index is an integer 0 to {MAX_CAMERA}")
        self._capture = cv2.VideoCapture(index)
        if not self._capture.isOpened():
            raise KittiFormatError(
                self.name, "could not be opened (no such device, no permission, or in use)"
            )
        fps = self._capture.get(cv2.CAP_PROP_FPS)
        self.fps = fps if math.isfinite(fps) and fps > 0 else None
        self.P2, self.plane = np.asarray(P2, np.float64), plane
        self.index = 0
        self._t_first: float | None = None
        self._last_time = -math.inf
        ok, bgr = self._capture.read()
        if not ok or bgr is None:
            self.close()
            raise KittiFormatError(self.name, "opened but delivered no frame")
        self.size = bgr.shape[:2]
        check_calibration(self.P2, self.size, calib, self.name)

    def read(self) -> Frame | None:
        t0 = time.perf_counter()
        ok, bgr = self._capture.read()
        if not ok or bgr is None:
            return None
        now = time.perf_counter()
        if self._t_first is None:
            self._t_first = now
        t = max(now - self._t_first, self._last_time + 1e-6)  # strictly increasing
        self._last_time = t
        image = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        i, self.index = self.index, self.index + 1
        _check_size(image, self.size, f"{self.name} frame {i}", "the first frame is")
        return Frame(i, f"{i:06d}", image, self.P2, self.plane, t0, t)

    def check_complete(self) -> None:
        pass

    def close(self) -> None:
        self._capture.release()


class SequenceSource:
    """An image folder read as an ordered sequence (frame ids: the images' stems).

    Args:
      folder: the images (sorted by name), or a KITTI raw drive folder or its ``image_0N``
        (:func:`sequence_files`).
      calib: its calibration file (any KITTI format, or a raw day's folder); None: the one
        :func:`sequence_files` finds.
      plane: one ground plane for every frame; None: the tracking layout's per-frame
        ``ROOT/training/planes/SSSS/<stem>.txt`` where present, else the level camera.
      camera: 2 (``P2``) or 3 (``P3``) of the calibration.
      fps: the frame rate (KITTI records at 10 Hz): image ``i`` is at ``i / fps`` seconds
        unless the folder has its own times.
      warn: where the warning line of an image that cannot be read goes (default stderr);
        such an image is skipped (:mod:`gac_jax.streams.damaged_frames`).

    Attributes:
      calibration: the :class:`~gac_jax.data.kitti_calib.Calibration` read.
      files: the :class:`SequenceFiles` of the folder.
      times: (N,) seconds of the frames since the first (a KITTI raw drive's
        ``timestamps.txt``), or None.
      found: one line per file found by the layout rather than given (to print).
    """

    live = False

    def __init__(
        self, folder, calib=None, plane=None, camera: int = 2, fps: float = 10.0, warn=None
    ):
        folder = Path(folder)
        self.name = os.fspath(folder)
        self.files = sequence_files(folder, camera)
        raw = self.files.raw
        if raw is not None and raw.camera != camera:
            raise KittiFormatError(
                folder,
                f"frames of camera {raw.camera} (image_0{raw.camera}) but P{camera} chosen: "
                f"pass --calib-camera {raw.camera}",
            )
        self.images = sequence_images(self.files.images)
        self.damaged = DamagedFrames(self.name, "image", warn)
        self.expected_frames = len(self.images)
        self.planes_dir = self.files.planes
        self.found: list[str] = []
        if calib is None:
            calib = self.files.calib
            if calib is None or not calib.is_file():
                looked = (
                    f"no {calib} (the KITTI raw layout)"
                    if calib is not None
                    else "not in the KITTI tracking layout ROOT/training/image_02/SSSS, "
                    f"no {folder / 'calib.txt'}"
                )
                raise KittiFormatError(
                    folder, f"no calibration found ({looked}); pass --calib FILE"
                )
            layout = self.files.layout
            self.found.append(
                f"calibration: {calib}" + (f" ({layout} layout)" if layout != "folder" else "")
            )
        self.calibration = read_calib(calib, camera)
        self.P2 = np.asarray(self.calibration.projection(camera), np.float64)
        self.times = None
        if raw is not None and raw.timestamps.is_file():
            stems = [p.stem for p in self.images]
            if not all(s.isdigit() for s in stems):
                raise KittiFormatError(
                    raw.timestamps, "frame names are not frame numbers: no line is theirs"
                )
            self.times = raw.frame_times([int(s) for s in stems])
            self.found.append(f"frame times: {raw.timestamps}")
        self.plane = plane
        self.fps = fps
        self.index = 0
        self._pending = self._next_image()  # the first image that can be read
        if self._pending is None:
            raise KittiFormatError(folder, "none of its images can be read")
        self.size = self._pending[1].shape[:2]
        check_calibration(self.P2, self.size, os.fspath(calib), self.name)

    def frame_plane(self, image: Path) -> np.ndarray | None:
        if self.plane is not None or self.planes_dir is None:
            return self.plane
        path = self.planes_dir / f"{image.stem}.txt"
        return read_plane(path) if path.is_file() else None

    def _next_image(self) -> tuple[int, np.ndarray, bytes | None] | None:
        """``(index, image, the file's bytes if a JPEG)`` of the next image that can be read
        (the others are skipped); None at the end."""
        while self.index < len(self.images):
            i, self.index = self.index, self.index + 1
            try:
                data = read_bytes(self.images[i], "image")
                image = decode_image(data, self.images[i])
            except KittiFormatError as e:
                self.damaged.skip(self.images[i].name, f"cannot be read ({e.problem})")
                continue
            self.damaged.good()
            return i, image, data if data[:3] == b"\xff\xd8\xff" else None
        return None

    def read(self) -> Frame | None:
        t0 = time.perf_counter()
        item, self._pending = self._pending or self._next_image(), None
        if item is None:
            return None
        i, image, jpeg = item
        path = self.images[i]
        _check_size(image, self.size, os.fspath(path), "the first image of the sequence is")
        when = i / self.fps if self.times is None else float(self.times[i])
        plane = self.frame_plane(path)
        return Frame(i, path.stem, image, self.P2, plane, t0, when, jpeg)

    def check_complete(self) -> None:
        pass

    def close(self) -> None:
        pass


class PacedSource:
    """``source`` delivered at ``fps`` frames/s, as a live camera would: frame ``i`` is not
    read before ``start + i / fps`` (and is late when the reader is)."""

    live = True

    def __init__(self, source, fps: float):
        if not fps > 0:
            raise ValueError(f"fps must be > 0, got {fps}")
        self.source, self.fps = source, fps
        self.name, self.size = source.name, source.size
        self.expected_frames = source.expected_frames
        self.damaged = getattr(source, "damaged", None)
        self._start: float | None = None
        self._next = 0

    def read(self) -> Frame | None:
        if self._start is None:
            self._start = time.perf_counter()
        delay = self._start + self._next / self.fps - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        self._next += 1
        return self.source.read()

    def check_complete(self) -> None:
        self.source.check_complete()

    def close(self) -> None:
        self.source.close()
