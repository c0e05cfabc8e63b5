"""Inputs the stream tests make for themselves: half-size KITTI frames and their calibration,
an MJPG AVI with chosen frames damaged, a variable-frame-rate video (PyAV), a small tmpfs, and
the subprocess helpers (a fake ``jax`` package that fails on import proves a check ran before
JAX loads)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import pytest

from gac_jax.data.files import read_image
from gac_jax.data.kitti import read_calib, write_calib

REPO = Path(__file__).resolve().parents[1]
HALF = (184, 612)  # half of the smallest vendored frame (even sizes: every codec takes them)


def half_frames(kitti_object_root: Path) -> list[np.ndarray]:
    """The vendored KITTI frames, cut to 368 x 1224 and halved (RGB uint8)."""
    images = sorted((kitti_object_root / "training" / "image_2").glob("*.png"))
    full = [read_image(p)[: 2 * HALF[0], : 2 * HALF[1]] for p in images]
    return [cv2.resize(f, HALF[::-1], interpolation=cv2.INTER_AREA) for f in full]


def write_half_calib(kitti_object_root: Path, path: Path, scale: float = 0.5) -> Path:
    """The vendored calibration with P2 scaled by ``scale`` (0.5: the half-size frames')."""
    calib = read_calib(kitti_object_root / "training" / "calib" / "000001.txt")
    P2 = np.array(calib.P2, np.float64)
    P2[:2] *= scale
    write_calib(path, dataclasses.replace(calib, P2=P2))
    return path


def run(argv, capsys) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``python -m gac_jax.cli.predict ARGV`` in this
    process."""
    from gac_jax.cli import predict

    code = predict.main([os.fspath(a) if isinstance(a, os.PathLike) else str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def numbered(frames: list[np.ndarray], n: int) -> list[np.ndarray]:
    """``n`` frames cycling through ``frames``, each with its number drawn (all distinct)."""
    out = []
    for i in range(n):
        f = frames[i % len(frames)].copy()
        cv2.putText(f, str(i), (20, 60), cv2.FONT_HERSHEY_SIMPLEX, 2, (255, 255, 255), 4)
        out.append(f)
    return out


def write_avi(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def avi_frame_chunks(data: bytes) -> list[tuple[int, int]]:
    """``(offset, size)`` of the data of every video frame chunk (``00dc``) of an AVI."""
    pos = data.index(b"movi") + 4
    chunks = []
    while pos + 8 <= len(data):
        kind, size = data[pos : pos + 4], int.from_bytes(data[pos + 4 : pos + 8], "little")
        if kind == b"idx1":
            break
        if kind == b"LIST":  # a rec list: its chunks follow
            pos += 12
            continue
        if kind[2:] in (b"dc", b"db"):
            chunks.append((pos + 8, size))
        pos += 8 + size + (size & 1)
    return chunks


def damage_avi(path: Path, frames: list[int], seed: int = 0) -> Path:
    """Overwrites the JPEG data of ``frames`` (positions) with noise, keeping the chunk
    headers (the container stays readable, the frames do not decode)."""
    data = bytearray(path.read_bytes())
    chunks = avi_frame_chunks(bytes(data))
    rng = np.random.default_rng(seed)
    for i in frames:
        offset, size = chunks[i]
        data[offset + 100 : offset + size - 100] = rng.integers(
            0, 256, size - 200, np.uint8
        ).tobytes()
    path.write_bytes(bytes(data))
    return path


def write_vfr(path: Path, frames: list[np.ndarray], times: list[float], codec: str) -> Path:
    """A video (container by ``path``'s suffix) whose frame ``i`` is at ``times[i]`` seconds:
    variable frame rate (PyAV)."""
    av = pytest.importorskip("av")
    h, w = frames[0].shape[:2]
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=20)
        stream.width, stream.height = w, h
        stream.pix_fmt = "yuvj420p" if codec == "mjpeg" else "yuv420p"
        stream.time_base = Fraction(1, 1000)
        for image, t in zip(frames, times, strict=True):
            frame = av.VideoFrame.from_ndarray(image, format="rgb24")
            frame.pts, frame.time_base = round(t * 1000), Fraction(1, 1000)
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    return path


def video_times(path: Path) -> list[float]:
    """Seconds of every frame of a video from its first (PyAV)."""
    av = pytest.importorskip("av")
    with av.open(str(path)) as container:
        times = [f.time for f in container.decode(container.streams.video[0])]
    return [t - times[0] for t in times]


@contextlib.contextmanager
def small_filesystem(folder: Path, size: str):
    """A tmpfs of ``size`` mounted on ``folder`` (skips where mounting is not permitted)."""
    folder.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({done.stderr.strip()})")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def no_jax(folder: Path) -> dict[str, str]:
    """The environment of a subprocess whose ``import jax`` raises (a fake ``jax`` package in
    ``folder``, first on ``PYTHONPATH``): it shows that a command finished before JAX loads."""
    (folder / "jax").mkdir(parents=True, exist_ok=True)
    (folder / "jax" / "__init__.py").write_text("raise ImportError('JAX was imported')\n")
    return {"PYTHONPATH": f"{folder}{os.pathsep}{REPO}"}


def predict(argv, env=None, prefix=(), **kw) -> subprocess.Popen:
    """``python -m gac_jax.cli.predict ARGV`` in a subprocess (stdout, stderr piped unless
    given)."""
    env = {**os.environ, "PYTHONPATH": str(REPO), **(env or {})}
    kw.setdefault("stdout", subprocess.PIPE)
    kw.setdefault("stderr", subprocess.PIPE)
    argv = [os.fsencode(a if isinstance(a, str | bytes | os.PathLike) else str(a)) for a in argv]
    command = [*prefix, sys.executable, "-m", "gac_jax.cli.predict", *argv]
    return subprocess.Popen(command, env=env, **kw)


def one_line(err: str, *needles: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]
