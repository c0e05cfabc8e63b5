"""Streams never lose a recording: a disk that fills up, SIGTERM mid-stream and during
start-up, outputs that cannot be written or would destroy the input, and bad numbers give
one line, keep what was finished valid and exit 1 / 143 / 2 (run as a user runs them, in
subprocesses); a failed write inside the video and result writers keeps whole frames and
lines; a script without a ``__main__`` guard gets an int8 model on first use."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from gac_jax.data.files import read_image
from gac_jax.data.kitti import KittiObjects, read_calib, write_calib
from gac_jax.streams import outputs
from tests import stream_cases
from tests.stream_cases import one_line, small_filesystem

SIZE = (370, 1224)  # the smallest vendored frame: the others are cut to it (same P2)
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def stream_input(kitti_object_root, tmp_path_factory):
    """``(make_video, calib)``: ``make_video(name, n, fps)`` writes an MJPG video of the
    vendored frames; ``calib`` their calibration file."""
    folder = tmp_path_factory.mktemp("stream_input")
    images = sorted((kitti_object_root / "training" / "image_2").glob("*.png"))
    frames = [read_image(p)[: SIZE[0], : SIZE[1]] for p in images]
    calib = folder / "calib.txt"
    write_calib(calib, read_calib(kitti_object_root / "training" / "calib" / "000001.txt"))

    def make_video(name: str, n: int, fps: float) -> Path:
        path = folder / name
        if path.exists():  # made by an earlier test of the module
            return path
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, SIZE[::-1])
        for i in range(n):
            writer.write(cv2.cvtColor(frames[i % len(frames)], cv2.COLOR_RGB2BGR))
        writer.release()
        return path

    return make_video, calib


def count_frames(path: Path) -> int:
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened(), path
    n = 0
    while capture.read()[0]:
        n += 1
    return n


def decoded_frames(path: Path) -> tuple[str, int]:
    """The codec of an MP4 and the frames PyAV decodes."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return stream.codec_context.name, sum(1 for _ in container.decode(stream))


def recorded_stamps(path: Path) -> list[int]:
    """Stamps of the first channel's messages in the whole chunks of an MCAP file (one
    without a summary ends at its cut)."""
    import io

    from mcap.stream_reader import StreamReader

    stamps = []
    with contextlib.suppress(Exception):  # the cut: EndOfFile, or a record cut short
        for record in StreamReader(io.BytesIO(path.read_bytes()), skip_magic=False).records:
            if type(record).__name__ == "Message" and record.channel_id == 1:
                stamps.append(record.log_time)
    return stamps


def hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob(".*"))


def predict(argv, prefix=(), **kw) -> subprocess.Popen:
    return stream_cases.predict(argv, prefix=prefix, text=True, **kw)


def test_a_full_disk_keeps_a_playable_prefix_and_the_earlier_video(
    tiny_detect3d_workdir, stream_input, tmp_path
):
    """The video, results and an MCAP recording on a 4 MB filesystem that fills up after
    about 15 frames, over an earlier video of the same name (``--overwrite``): one line naming
    the file and "no space left", exit 1; the frames written so far play as
    ``annotated.incomplete.mp4`` (H.264) and match the result files one to one; the recording
    is kept as ``run.incomplete.mcap`` and reads back to its last whole chunk; the earlier
    video is untouched; nothing hidden."""
    make_video, calib = stream_input
    video = make_video("slow.avi", 60, fps=2.0)  # 2 frames/s: a few seconds of video fit
    with small_filesystem(tmp_path / "small", "4m") as disk:
        out = disk / "out"
        out.mkdir()
        earlier = outputs.AnnotatedVideo(out / "annotated.mp4", 5.0)
        for value in (40, 200):
            earlier.write(np.full((32, 48, 3), value, np.uint8))
        earlier.close()
        before = (out / "annotated.mp4").read_bytes()
        argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", calib]
        mcap = ["--mcap", out / "run.mcap"]
        process = predict([*argv, "--out", out, "--overwrite", "--report-every", 0, *mcap])
        stdout, stderr = process.communicate(timeout=300)
        assert process.returncode == 1, (stdout, stderr)
        one_line(stderr, "no space left on device", str(out))
        assert "stopped: writing failed after" in stdout, stdout
        written = len(list((out / "data").glob("*.txt")))
        assert 0 < written < 60
        assert count_frames(out / "annotated.incomplete.mp4") == written
        assert decoded_frames(out / "annotated.incomplete.mp4") == ("h264", written)
        stamps = recorded_stamps(out / "run.incomplete.mcap")  # the video lags by a few frames
        assert len(stamps) <= written + 4 and stamps == [
            i * 500_000_000 for i in range(len(stamps))
        ]
        assert (out / "annotated.mp4").read_bytes() == before
        assert hidden(out) == []


@pytest.mark.parametrize("when", ["stream", "start-up"])
def test_sigterm_ends_a_stream_as_ctrl_c_does(tiny_detect3d_workdir, stream_input, tmp_path, when):
    """SIGTERM mid-stream: reading stops, the frames in flight finish, a playable H.264 video
    and a finished MCAP recording (its summary written: the last chunk finished) of exactly
    the frames with result files, the summary, exit 143. During start-up (the output folder is
    made after the input opened, before the model loads): one line, exit 143, nothing
    written, no traceback, nothing hidden."""
    make_video, calib = stream_input
    video = make_video("long.avi", 400, fps=10.0)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", calib, "--out", out,
            "--mcap", out / "run.mcap"]  # fmt: skip
    process = predict(argv)
    deadline = time.monotonic() + 240
    target = 5 if when == "stream" else 0
    while time.monotonic() < deadline and process.poll() is None:
        if out.is_dir() and len(list(out.glob("data/*.txt"))) >= target:
            break
        time.sleep(0.05)
    assert process.poll() is None, process.communicate()
    process.send_signal(signal.SIGTERM)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, (stdout, stderr)
    assert hidden(out) == []
    if when == "start-up":
        assert "start-up: " not in stdout, stdout  # it stopped before the stream began
        one_line(stderr.replace("interrupted:", "error: interrupted:"), "SIGTERM during start-up")
        assert list(out.iterdir()) == []
        return
    written = len(list((out / "data").glob("*.txt")))
    assert 5 <= written < 400 and count_frames(out / "annotated.mp4") == written
    assert decoded_frames(out / "annotated.mp4") == ("h264", written)
    from mcap.reader import make_reader

    with open(out / "run.mcap", "rb") as f:
        counts = make_reader(f).get_summary().statistics.channel_message_counts
    assert counts and set(counts.values()) == {written}
    assert "SIGTERM: reading stopped" in stdout and "in flight finished" in stdout
    assert f"{written} frames -> " in stdout and stderr.strip() == "", stderr


def test_outputs_and_numbers_are_refused_before_the_model_loads(
    tiny_detect3d_workdir, stream_input, tmp_path
):
    """One line, exit 2, in about a second (no model loaded: JAX is not even imported)."""
    make_video, calib = stream_input
    video = make_video("short.avi", 2, fps=10.0)
    (tmp_path / "file").write_text("x")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    base = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", calib]
    cases = [
        ([*base, "--out", tmp_path / "o1", "--out-video", video], (), ("is the input",)),
        ([*base, "--out", tmp_path / "file"], (), ("file", "needs a folder")),
        ([*base, "--out", tmp_path / "o2", "--out-video", tmp_path], (), ("is a folder",)),
        (["--workdir", tiny_detect3d_workdir, "--camera", -1, "--calib", calib], (), ("--camera",)),
        ([*base, "--report-every", -1], (), ("--report-every", ">= 0")),
        ([*base, "--fps", "nan"], (), ("--fps",)),
        ([*base, "--out", tmp_path / "o3", "--codec", "vp9"], (), ("--codec", "unknown codec")),
        ([*base, "--out", tmp_path / "o4", "--mcap", tmp_path], (), ("is a folder", "--mcap")),
        ([*base, "--out", tmp_path / "o5", "--mcap-profile", "ros2"], (), ("goes with --mcap",)),
    ]
    if os.geteuid() == 0:  # root writes anywhere: drop the capability that lets it
        if shutil.which("capsh") is None:
            pytest.skip("runs as root and capsh (to drop cap_dac_override) is not installed")
        cases.append(([*base, "--out", locked / "out"], ("capsh", "--drop=cap_dac_override",
                      "--", "-c", 'exec "$0" "$@"'), ("permission denied",)))  # fmt: skip
    else:
        cases.append(([*base, "--out", locked / "out"], (), ("permission denied",)))
    for argv, prefix, needles in cases:
        t0 = time.monotonic()
        process = predict(argv, prefix)
        stdout, stderr = process.communicate(timeout=60)
        seconds = time.monotonic() - t0
        assert process.returncode == 2, (argv, stdout, stderr)
        one_line(stderr, *needles)
        assert stdout == "" and seconds < 10, (argv, seconds)  # ~0.3 s unloaded
    # an earlier run's results: refused, then replaced with --overwrite (stale files gone)
    out = tmp_path / "again"
    (out / "data").mkdir(parents=True)
    (out / "data" / "000099.txt").write_text("stale\n")
    process = predict([*base, "--out", out, "--no-images"])
    _, stderr = process.communicate(timeout=60)
    assert process.returncode == 2
    one_line(stderr, "earlier run", "1 result files", "--overwrite")
    process = predict([*base, "--out", out, "--no-images", "--overwrite"])
    stdout, stderr = process.communicate(timeout=300)
    assert process.returncode == 0, stderr
    assert sorted(p.name for p in (out / "data").iterdir()) == ["000000.txt", "000001.txt"]
    startup = [line for line in stdout.splitlines() if line.startswith("start-up: ")]
    assert len(startup) == 1 and "not counted in the rates" in startup[0], stdout


def test_a_failed_write_keeps_whole_lines(tmp_path, monkeypatch):
    """ENOSPC injected at the JSON lines writer's ``os.pwrite`` (as a full disk answers,
    after a short write): the file ends on its last whole line and is kept as ``.incomplete``
    (the video's full disk: tests/test_stream_recordings.py)."""
    real = os.pwrite
    budget = {"bytes": None}

    def full_disk(fd, data, offset):
        if budget["bytes"] is None:
            return real(fd, data, offset)
        n = min(len(data), budget["bytes"])
        if n == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        budget["bytes"] -= n
        return real(fd, bytes(data[:n]), offset)

    monkeypatch.setattr(os, "pwrite", full_disk)
    results = outputs.JsonlResults(tmp_path / "r.jsonl")
    results.write("000000", 0, KittiObjects.empty(), {"objects": []})
    budget["bytes"] = 7
    with pytest.raises(OSError, match="No space left"):
        results.write("000001", 1, KittiObjects.empty(), {"objects": []})
    budget["bytes"] = None
    kept = results.close(complete=False)
    assert kept == tmp_path / "r.incomplete.jsonl"
    assert [json.loads(line)["frame"] for line in kept.read_text().splitlines()] == ["000000"]


NO_MAIN_GUARD = """
from gac_jax.api import Detector3D

detector = Detector3D.from_workdir({workdir!r}, runtime="openvino", precision="int8")
print("precision:", detector.precision)
"""


def test_a_script_without_a_main_guard_gets_an_int8_model(tiny_detect3d_workdir, tmp_path):
    """A user's script with no ``if __name__ == "__main__"`` asks for an int8 model of a run
    trained on the embedded dataset, whose dataset must be generated (in a process pool) for
    the calibration: the pool does not run the script again, and the dataset goes into the
    cache the run recorded, not the ``GAC_JAX_CACHE`` of the script's environment."""
    pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
    pytest.importorskip("nncf", reason="deploy extra (nncf) not installed")
    wd = tmp_path / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "export"))
    config = json.loads((wd / "config.json").read_text())
    config["data"].update(source="synthetic", root=None, train_split="train", val_split="val")
    config["data"]["synthetic"].update(num_frames=6, workers=2, val_fraction=0.5)
    (wd / "config.json").write_text(json.dumps(config))
    trained, elsewhere = tmp_path / "trained_cache", tmp_path / "script_cache"
    (wd / "data_cache.json").write_text(json.dumps({"cache": str(trained)}))
    script = tmp_path / "user_script.py"
    script.write_text(NO_MAIN_GUARD.format(workdir=str(wd)))
    env = {**os.environ, "PYTHONPATH": str(REPO), "GAC_JAX_CACHE": str(elsewhere)}
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          env=env, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    assert "precision: int8" in done.stdout
    assert done.stdout.count("quantizing (NNCF, 3 calibration frames (of 16 asked") == 1
    assert (wd / "export" / "step2" / "model_int8.xml").is_file()
    assert len(list(trained.glob("synthetic_n6_*"))) == 1 and not elsewhere.exists()
