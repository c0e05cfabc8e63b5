"""An MP4 video encoded and muxed by FFmpeg through PyAV, on a thread of its own, whose file
holds whole frames at every moment.

* **Codec** (:data:`CODECS`): ``h264`` (libx264, bundled in PyAV's wheels: GPL-2.0-or-later;
  CRF 23, ``zerolatency``: no B-frames and no look-ahead, so a frame in gives a packet out;
  High profile, yuv420p, which browsers play) or ``mjpeg`` (Motion JPEG, every frame a JPEG
  of about OpenCV's quality 90; players play it, browsers do not). Odd picture sizes are
  padded to even ones (the last row / column repeated), as yuv420p needs.
* **Container**: fragmented MP4, a fragment per frame (``movflags``
  ``frag_every_frame+empty_moov+default_base_moof``): ``ftyp`` + ``moov`` without samples
  first, then ``moof`` + ``mdat`` per frame, so the file plays at every moment. FFmpeg's mov
  muxer writes a frame's fragment when the next frame arrives (or at the close), and
  ``flush_packets`` hands each fragment to the file at once.
* **Writes**: PyAV's muxer writes into :class:`CheckedFile`, a file object of ours: every
  ``os.write`` is checked, the output is not seekable (the muxer only appends), and the file
  offset after each fragment is recorded. A failed write (a full disk) cuts the file back to
  its last whole fragment (``ftruncate``, which needs no space) and raises an ``OSError``
  naming the video; the frames before it stay playable. :meth:`Mp4Video.close` can cut the
  file to fewer frames (those whose results were written).
* **Thread**: :meth:`Mp4Video.write` hands the picture to the encoder's thread (a queue of
  :data:`QUEUE_FRAMES`): colour conversion, encoding and muxing run there, with one libx264
  thread, beside the stream's other stages; :attr:`Mp4Video.cpu_s` is that thread's CPU time.
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
import time
from fractions import Fraction

import cv2
import numpy as np

from gac_jax.streams.checked_file import CheckedFile

CODECS = ("h264", "mjpeg")
DEFAULT_CODEC = "h264"
H264_CRF = 23
H264_PRESET = "veryfast"
KEYFRAME_SECONDS = 2.0  # a keyframe every this many seconds (seeking; a cut file plays anyway)
MJPEG_QSCALE = 3  # FFmpeg's quantizer scale: about OpenCV's JPEG quality 90
QUEUE_FRAMES = 2  # pictures waiting for the encoder before write() blocks
MOVFLAGS = "frag_every_frame+empty_moov+default_base_moof"
_END = object()


def frame_rate(fps: float) -> Fraction:
    """``fps`` as an exact rate to 1/1000 frame/s (29.97 -> 30000/1001)."""
    return Fraction(fps).limit_denominator(1001)


def even_size(h: int, w: int) -> tuple[int, int]:
    """The encoded size of an (h, w) picture: rounded up to even numbers."""
    return h + h % 2, w + w % 2


def _open_stream(file: CheckedFile, codec: str, fps: float, size: tuple[int, int]):
    """The PyAV output container and its video stream (nothing written yet)."""
    import av

    container = av.open(
        file,
        "w",
        format="mp4",
        options={"movflags": MOVFLAGS, "flush_packets": "1"},
    )
    rate = frame_rate(fps)
    h, w = size
    if codec == "h264":
        stream = container.add_stream("libx264", rate=rate)
        stream.pix_fmt = "yuv420p"
        stream.codec_context.options = {
            "crf": str(H264_CRF),
            "preset": H264_PRESET,
            "tune": "zerolatency",
            "profile": "high",
        }
        stream.codec_context.gop_size = max(1, round(KEYFRAME_SECONDS * float(rate)))
    else:
        stream = container.add_stream("mjpeg", rate=rate)
        stream.pix_fmt = "yuvj420p"
        stream.codec_context.qscale = True
        stream.codec_context.qmin = stream.codec_context.qmax = MJPEG_QSCALE
    stream.width, stream.height = w, h
    stream.codec_context.thread_count = 1  # the stream's thread budget: one encoder thread
    stream.codec_context.thread_type = "NONE"
    return container, stream


class Mp4Video:
    """Encodes RGB pictures of one size into a fragmented MP4 file on its own thread
    (module doc).

    Args:
      path: the file written (created or truncated); name: the path errors name.
      fps: frames per second; size: ``(h, w)`` of the pictures; codec: one of :data:`CODECS`.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        name: str | os.PathLike,
        fps: float,
        size: tuple[int, int],
        codec: str = DEFAULT_CODEC,
    ):
        if codec not in CODECS:
            raise ValueError(f"unknown codec {codec!r} (use one of {', '.join(CODECS)})")
        self.size = size
        self.file = CheckedFile(path, name)
        self.codec = codec
        self._container, self._stream = _open_stream(self.file, codec, fps, even_size(*size))
        self._rate = frame_rate(fps)
        self._queue: queue.Queue = queue.Queue(QUEUE_FRAMES)
        self.submitted = 0  # pictures handed to write()
        self.packets = 0  # packets muxed (one per frame)
        self._pts = 0
        self.cpu_s = 0.0  # CPU seconds of the encoder thread
        self.kept_frames = 0  # frames the file holds after close()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="gac-video-encoder", daemon=True)
        self._thread.start()

    @property
    def frames(self) -> int:
        """Frames whole in the file now (the muxer holds the newest one until the next)."""
        return max(len(self.file.marks) - 1, 0)

    def write(self, rgb: np.ndarray, time_s: float | None = None) -> None:
        """Queues one (h, w, 3) uint8 RGB picture shown at ``time_s`` seconds from the first
        (None: one frame after the previous; times are kept to the stream's 1 / fps grid, a
        frame at least one step after the previous); raises the encoder's error once it
        failed."""
        if self.error is not None:
            raise self.error
        self._queue.put((rgb, time_s))
        self.submitted += 1

    def _frame(self, rgb: np.ndarray):
        import av

        h, w = self.size
        H, W = even_size(h, w)
        if (h, w) != (H, W):
            rgb = cv2.copyMakeBorder(rgb, 0, H - h, 0, W - w, cv2.BORDER_REPLICATE)
        yuv = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2YUV_I420)
        frame = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        if self.codec == "mjpeg":  # full-range JPEG: the same samples, relabelled
            frame = frame.reformat(format="yuvj420p")
        return frame

    def _mux(self, packets) -> None:
        for packet in packets:
            self._container.mux_one(packet)
            if self.file.error is not None:
                raise self.file.error
            self.file.mark()
            self.packets += 1

    def _run(self) -> None:
        t0 = time.thread_time()
        try:
            while (item := self._queue.get()) is not _END:
                if self.error is not None:
                    continue  # failed: the pictures are dropped
                try:
                    rgb, time_s = item
                    frame = self._frame(rgb)
                    pts = self._pts
                    if time_s is not None:  # the frame's own time, on the stream's grid
                        pts = max(pts, round(time_s * float(self._rate)))
                    frame.pts, self._pts = pts, pts + 1
                    self._mux(self._stream.encode(frame))
                except Exception as e:
                    self.error = self.file.error or e
            if self.error is None:
                try:
                    self._mux(self._stream.encode(None))
                    self._container.close()  # the last fragment, and mfra (an index)
                    if self.file.error is not None:
                        raise self.file.error
                    self.file.mark()
                except Exception as e:
                    self.error = self.file.error or e
        finally:
            self.cpu_s += time.thread_time() - t0

    def close(self, frames: int | None = None) -> int:
        """Encodes what is queued, finishes the file (cut to ``frames`` frames when fewer are
        whole) and closes it; returns the frames it holds. Raises the encoder's error (the
        file then holds the frames before it)."""
        if self._thread.is_alive():
            self._queue.put(_END)
            self._thread.join()
            if self.error is not None:
                with contextlib.suppress(Exception):  # raises again: the error is kept
                    self._container.close()
        whole = self.frames if self.error is not None else self.packets
        keep = whole if frames is None else min(frames, whole)
        if keep < whole and self.file.fd >= 0:
            self.file.truncate(self.file.marks[keep])
        self.file.close()
        if self.error is None and self.file.error is not None:
            self.error = self.file.error
        self.kept_frames = keep
        if self.error is not None:
            raise self.error
        return keep
