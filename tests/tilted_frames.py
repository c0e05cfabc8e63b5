"""A small KITTI-format object folder of generated frames whose camera is pitched down (the
authors' issue #69), each with its ``planes/NNNNNN.txt`` (written here from the generator's
frame, not by the generator's writer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gac_jax.data.files import write_png
from gac_jax.data.kitti import KittiObjectLayout, write_calib, write_label, write_plane, write_split
from gac_jax.data.synthetic.frame import make_frame


def write_tilted_root(
    root: Path,
    num_frames: int,
    image_size: tuple[int, int] = (188, 621),
    pitch_degrees: float = 20.0,
    seed: int = 3,
) -> Path:
    """Writes frames ``0..num_frames-1`` (split ``all``) to ``root``; returns ``root``."""
    layout = KittiObjectLayout(root)
    ids = []
    for i in range(num_frames):
        frame = make_frame(seed, i, image_size, pitch=np.radians(pitch_degrees))
        fid = f"{i:06d}"
        write_png(layout.image(fid, 2), frame.views[2].image)
        write_calib(layout.calib(fid), frame.calib)
        write_label(layout.label(fid), frame.objects)
        write_plane(layout.plane(fid), frame.plane)
        ids.append(fid)
    write_split(layout.split_file("all"), ids)
    return root
