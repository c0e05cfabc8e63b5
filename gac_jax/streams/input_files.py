"""What a stream reads must be a file: one line naming it and what it is instead."""

from __future__ import annotations

import os
import stat

from gac_jax.data.files import KittiFormatError


def check_input_file(path, what: str) -> None:
    """Raises :class:`KittiFormatError` naming ``path`` unless it is a regular file (or a link
    to one): not found, a folder, a named pipe or a device get their own words."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        problem = f"{what} not found"
        if os.path.islink(path):
            problem += f" (a symbolic link to {os.readlink(path)}, which does not exist)"
        raise KittiFormatError(path, problem) from None
    except OSError as e:
        raise KittiFormatError(path, f"cannot be read ({(e.strerror or str(e)).lower()})") from None
    if stat.S_ISREG(mode):
        return
    if stat.S_ISDIR(mode):
        kind = "a folder"
    elif stat.S_ISFIFO(mode):
        kind = "a named pipe (FIFO)"
    elif stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        kind = "a device"
    else:
        kind = "a special file"
    raise KittiFormatError(
        path, f"is {kind}, not a {what} file: a stream reads a saved {what} file"
    )
