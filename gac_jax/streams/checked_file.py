"""A checked, append-only file object for libraries that write by themselves (FFmpeg's muxer
through PyAV, the ``mcap`` writer): every write is checked, a failed one leaves the file at
the end of its last whole unit and names the file the user asked for (not its hidden
partial). Used by :mod:`gac_jax.streams.video_encoder` and
:mod:`gac_jax.streams.mcap_recording`.
"""

from __future__ import annotations

import errno
import os


class CheckedFile:
    """A file object for a library that writes by itself (PyAV's muxer, the ``mcap``
    writer): appends with checked ``os.write``; :meth:`mark` records the end of a whole unit
    (a video fragment; with ``mark_writes`` every write, each a run of whole records); after a
    failed write the file ends at the last mark (``ftruncate``, which needs no space) and
    every later write fails with the same error, an ``OSError`` naming ``name``.

    Args:
      path: the file (created or truncated); name: the path errors name.
    """

    def __init__(self, path: str | os.PathLike, name: str | os.PathLike, mark_writes=False):
        self.name = os.fspath(name)
        self.mark_writes = mark_writes
        self.fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        self.offset = 0
        self.marks: list[int] = []  # file ends after the header and after each fragment
        self.error: OSError | None = None

    def writable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.offset

    def flush(self) -> None:
        pass  # every write went to the file already

    def write(self, data) -> int:
        if self.error is not None:
            raise self.error
        view, done = memoryview(data).cast("B"), 0
        try:
            while done < len(view):
                n = os.write(self.fd, view[done:])
                if n == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                done += n
        except OSError as e:
            self.fail(e)
            raise self.error from None
        self.offset += len(view)
        if self.mark_writes:
            self.mark()
        return len(view)

    def fail(self, e: OSError) -> None:
        """Cuts the file back to the last mark and keeps ``e`` (naming the file)."""
        code = e.errno or errno.EIO
        self.error = OSError(code, e.strerror or os.strerror(code), self.name)
        self.truncate(self.marks[-1] if self.marks else 0)

    def mark(self) -> None:
        self.marks.append(self.offset)

    def truncate(self, end: int) -> None:
        os.ftruncate(self.fd, end)
        self.offset = end

    def close(self) -> None:
        """Flushes to disk and closes (idempotent); a failed flush is kept as the error."""
        if self.fd < 0:
            return
        try:
            os.fsync(self.fd)
        except OSError as e:
            if self.error is None:
                code = e.errno or errno.EIO
                self.error = OSError(code, e.strerror or os.strerror(code), self.name)
        finally:
            os.close(self.fd)
            self.fd = -1
