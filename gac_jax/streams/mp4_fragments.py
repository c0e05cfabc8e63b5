"""A fragmented MP4 file of JPEG frames, written one whole frame at a time.

Why not ``cv2.VideoWriter`` for ``.mp4``: OpenCV's FFmpeg writer puts the index (``moov``)
at the end, written only by ``release()``, so a full disk, a kill or a crash leaves a file
that no player opens; it cannot be asked for a fragmented container (its
``OPENCV_FFMPEG_WRITER_OPTIONS`` reach the encoder, not the muxer), its buffered writes
report a failure one or more frames late, and ``release()`` reports none. PyAV is not a
dependency, and no ``ffmpeg`` binary is assumed.

So the frames are encoded with ``cv2.imencode`` (JPEG) and put in an ISO base media file
(ISO/IEC 14496-12) laid out as fragments: ``ftyp`` + ``moov`` (the track, no samples) first,
then one ``moof`` + ``mdat`` pair per frame. Every write is an ``os.write`` whose result is
checked; a frame is either wholly in the file or, after a failed write, cut off again
(``ftruncate`` to the end of the last whole frame, which needs no space). The file on disk
is therefore always a playable video of the frames appended so far, whether the program
ends normally, fails or is killed; :meth:`FragmentedJpegMp4.close` only adds the total
duration (``mehd``, patched in place: no new space) for players that show it. FFmpeg (so
OpenCV's ``VideoCapture``), VLC and GStreamer play it; browsers play neither this nor
OpenCV's MPEG-4 part 2.
"""

from __future__ import annotations

import errno
import os
import struct
from fractions import Fraction

TRACK_ID = 1
MOVIE_TIMESCALE = 1000
MATRIX = struct.pack(">9I", 0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)


def box(kind: bytes, *payload: bytes) -> bytes:
    body = b"".join(payload)
    return struct.pack(">I4s", 8 + len(body), kind) + body


def full_box(kind: bytes, version: int, flags: int, *payload: bytes) -> bytes:
    return box(kind, struct.pack(">I", (version << 24) | flags), *payload)


def frame_timing(fps: float) -> tuple[int, int]:
    """``(timescale, ticks per frame)`` representing ``fps`` exactly to 1/1000 frame/s
    (29.97 -> 30000 / 1001)."""
    rate = Fraction(fps).limit_denominator(1001)
    k = -(-MOVIE_TIMESCALE // rate.numerator)  # a timescale of at least 1000 ticks per second
    return rate.numerator * k, rate.denominator * k


def header(width: int, height: int, timescale: int, frame_ticks: int) -> tuple[bytes, int]:
    """``ftyp`` + ``moov`` of one JPEG video track; and the offset of the 64-bit
    ``mehd.fragment_duration`` in it (patched by :meth:`FragmentedJpegMp4.close`)."""
    ftyp = box(b"ftyp", b"isom", struct.pack(">I", 0x200), b"isomiso2iso6mp41")
    mvhd = full_box(
        b"mvhd", 0, 0,
        struct.pack(">IIII", 0, 0, MOVIE_TIMESCALE, 0),
        struct.pack(">IH", 0x10000, 0x100), bytes(10), MATRIX, bytes(24),
        struct.pack(">I", TRACK_ID + 1),
    )  # fmt: skip
    tkhd = full_box(
        b"tkhd", 0, 3,
        struct.pack(">IIIII", 0, 0, TRACK_ID, 0, 0), bytes(8),
        struct.pack(">HHHH", 0, 0, 0, 0), MATRIX,
        struct.pack(">II", width << 16, height << 16),
    )  # fmt: skip
    mdhd = full_box(b"mdhd", 0, 0, struct.pack(">IIIIHH", 0, 0, timescale, 0, 0x55C4, 0))
    hdlr = full_box(b"hdlr", 0, 0, struct.pack(">I4s12x", 0, b"vide"), b"gac_jax video\0")
    entry = box(
        b"jpeg",
        bytes(6), struct.pack(">H", 1),  # reserved, data_reference_index
        bytes(16), struct.pack(">HH", width, height),
        struct.pack(">IIIH", 0x480000, 0x480000, 0, 1),  # 72 dpi, reserved, frame_count
        bytes([4]) + b"JPEG" + bytes(27),  # compressorname (Pascal string, 32 bytes)
        struct.pack(">Hh", 0x18, -1),
    )  # fmt: skip
    stbl = box(
        b"stbl",
        full_box(b"stsd", 0, 0, struct.pack(">I", 1), entry),
        full_box(b"stts", 0, 0, struct.pack(">I", 0)),
        full_box(b"stsc", 0, 0, struct.pack(">I", 0)),
        full_box(b"stsz", 0, 0, struct.pack(">II", 0, 0)),
        full_box(b"stco", 0, 0, struct.pack(">I", 0)),
    )
    dinf = box(b"dinf", full_box(b"dref", 0, 0, struct.pack(">I", 1), full_box(b"url ", 0, 1)))
    minf = box(b"minf", full_box(b"vmhd", 0, 1, bytes(8)), dinf, stbl)
    trak = box(b"trak", tkhd, box(b"mdia", mdhd, hdlr, minf))
    mehd = full_box(b"mehd", 1, 0, struct.pack(">Q", 0))
    trex = full_box(b"trex", 0, 0, struct.pack(">IIIII", TRACK_ID, 1, frame_ticks, 0, 0))
    moov = box(b"moov", mvhd, trak, box(b"mvex", mehd, trex))
    mehd_at = len(ftyp) + len(moov) - len(trex) - 8  # mehd's 64-bit field (mvex is last)
    return ftyp + moov, mehd_at


def fragment(sequence: int, decode_time: int, sample: bytes) -> bytes:
    """``moof`` + ``mdat`` of one sample (a sync sample: every JPEG frame is a key frame)."""
    tfhd = full_box(b"tfhd", 0, 0x020000, struct.pack(">I", TRACK_ID))  # base: the moof
    tfdt = full_box(b"tfdt", 1, 0, struct.pack(">Q", decode_time))
    trun_size = 8 + 4 + 4 + 4 + 4  # header, version/flags, count, data offset, sample size
    traf_size = 8 + len(tfhd) + len(tfdt) + trun_size
    moof_size = 8 + 16 + traf_size  # + mfhd
    trun = full_box(b"trun", 0, 0x000201, struct.pack(">IiI", 1, moof_size + 8, len(sample)))
    moof = box(b"moof", full_box(b"mfhd", 0, 0, struct.pack(">I", sequence)),
               box(b"traf", tfhd, tfdt, trun))  # fmt: skip
    assert len(moof) == moof_size
    return moof + struct.pack(">I4s", 8 + len(sample), b"mdat") + sample


class FragmentedJpegMp4:
    """Appends JPEG frames to ``path`` (created or truncated), each as one fragment.

    Args:
      path: the file.
      fps: frames per second.
      size: ``(width, height)`` of the frames.

    Raises (every method): ``OSError`` naming ``path`` when a write fails; the file then holds
    the frames appended before, and stays usable for :meth:`close`.
    """

    def __init__(self, path: str | os.PathLike, fps: float, size: tuple[int, int]):
        self.path = os.fspath(path)
        self.timescale, self.frame_ticks = frame_timing(fps)
        self.frames = 0
        self._sizes: list[int] = []  # bytes of each frame's fragment
        self._starts: list[int] = []  # each frame's decode time (ticks)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        head, self._mehd_at = header(*size, self.timescale, self.frame_ticks)
        self._end = 0
        self._append(head)

    def _append(self, data: bytes) -> None:
        """Writes ``data`` after the last whole unit, or cuts the file back to it and raises."""
        view, done = memoryview(data), 0
        try:
            while done < len(data):
                n = os.pwrite(self._fd, view[done:], self._end + done)
                if n == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                done += n
        except OSError as e:
            os.ftruncate(self._fd, self._end)
            raise OSError(e.errno, e.strerror or os.strerror(e.errno), self.path) from None
        self._end += len(data)

    def append(self, jpeg: bytes, time_s: float | None = None) -> None:
        """Adds one JPEG frame (whole, or not at all) shown at ``time_s`` seconds (None, or
        not after the previous frame: one frame's ticks after it)."""
        after = self._starts[-1] + self.frame_ticks if self._starts else 0
        start = after if time_s is None else round(time_s * self.timescale)
        if self._starts and start <= self._starts[-1]:
            start = after
        unit = fragment(self.frames + 1, start, jpeg)
        self._append(unit)
        self._sizes.append(len(unit))
        self._starts.append(start)
        self.frames += 1

    def drop_last(self) -> None:
        """Cuts the last frame off again (its results could not be written)."""
        if self.frames:
            self._end -= self._sizes.pop()
            self._starts.pop()
            os.ftruncate(self._fd, self._end)
            self.frames -= 1

    def close(self) -> None:
        """Writes the duration in place, flushes to disk and closes (idempotent)."""
        if self._fd < 0:
            return
        try:
            end = self._starts[-1] + self.frame_ticks if self._starts else 0
            duration = struct.pack(">Q", end)
            if os.pwrite(self._fd, duration, self._mehd_at) != len(duration):
                raise OSError(errno.EIO, os.strerror(errno.EIO))
            os.fsync(self._fd)
        except OSError as e:
            raise OSError(e.errno, e.strerror or os.strerror(e.errno), self.path) from None
        finally:
            os.close(self._fd)
            self._fd = -1
