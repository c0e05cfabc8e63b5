"""The annotated video a stream writes, read back by other programs: the H.264 / Motion JPEG
MP4 decodes to its frames with PyAV and OpenCV, a real browser (headless Chromium) plays it,
and a full disk in the encoder's thread keeps whole frames and as many result files.
(The MCAP recording: tests/test_mcap_recordings.py.)"""

from __future__ import annotations

import errno
import functools
import http.server
import json
import os
import shutil
import signal
import subprocess
import threading
import time

import cv2
import numpy as np
import pytest
from test_stream_faults import count_frames

from gac_jax.data.kitti import KittiObjects
from gac_jax.streams import outputs

FPS = 10.0
SIZE = (75, 161)  # odd both ways: padded to 76 x 162


def pictures(n: int, size=SIZE) -> list[np.ndarray]:
    """Smooth moving pictures (a gradient and a box): what a codec meets in annotated frames."""
    h, w = size
    yy, xx = np.mgrid[0:h, 0:w]
    out = []
    for i in range(n):
        rgb = np.stack([(xx * 255 // w), (yy * 255 // h), np.full_like(xx, 40 + 10 * i)], -1)
        rgb = rgb.astype(np.uint8)
        cv2.rectangle(rgb, (5 + 4 * i, 10), (40 + 4 * i, 50), (255, 128, 0), 2)
        out.append(rgb)
    return out


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-12))


def decode_pyav(path) -> tuple[str, str | None, list[np.ndarray], float]:
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        codec, profile = stream.codec_context.name, stream.codec_context.profile
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        duration = container.duration / 1e6 if container.duration else float("nan")
    return codec, profile, frames, duration


@pytest.mark.parametrize("codec", ["h264", "mjpeg"])
def test_the_mp4_decodes_to_its_frames_with_pyav_and_opencv(tmp_path, codec):
    """H.264 (High profile, yuv420p) or Motion JPEG: both decoders give every frame, the
    padded row and column repeat the last ones, and the pictures come back close."""
    shown = pictures(12)
    video = outputs.AnnotatedVideo(tmp_path / "v.mp4", FPS, codec)
    for rgb in shown:
        video.write(rgb)
    assert video.close() == tmp_path / "v.mp4" and video.frames == 12
    name, profile, frames, duration = decode_pyav(tmp_path / "v.mp4")
    assert name == codec and count_frames(tmp_path / "v.mp4") == 12
    assert len(frames) == 12 and frames[0].shape == (76, 162, 3)
    assert duration == pytest.approx(1.2, abs=0.01)
    if codec == "h264":
        assert profile == "High"
    for got, want in zip(frames, shown, strict=True):  # 4:2:0 chroma: saturated edges blur
        assert psnr(got[: SIZE[0], : SIZE[1]], want) > 25
        assert psnr(got[SIZE[0], : SIZE[1]], want[-1]) > 25  # the padding repeats the last row
    assert sorted(p.name for p in tmp_path.glob(".*")) == []  # the partial was renamed


def test_a_full_disk_in_the_encoder_keeps_whole_frames_and_as_many_results(tmp_path, monkeypatch):
    """ENOSPC at the encoder thread's ``os.write`` after a few frames (as a full disk, after a
    short write): the next ``write`` raises it naming the video; closing keeps the whole
    frames as ``.incomplete.mp4`` and cuts the result files to as many."""
    real = os.write
    budget = {"bytes": None}

    def full_disk(fd, data):
        if budget["bytes"] is None or fd != video._mp4.file.fd:
            return real(fd, data)
        n = min(len(data), budget["bytes"])
        if n == 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        budget["bytes"] -= n
        return real(fd, bytes(data[:n]))

    monkeypatch.setattr(os, "write", full_disk)
    video = outputs.AnnotatedVideo(tmp_path / "v.mp4", FPS)
    results = outputs.KittiResults(tmp_path / "data")
    error = None
    for i, rgb in enumerate(pictures(30)):
        if i == 8:
            budget["bytes"] = 3000  # part of a fragment, then nothing
        try:
            video.write(rgb)
        except OSError as e:
            error = e
            break
        results.write(f"{i:06d}", i, KittiObjects.empty(), {})
        time.sleep(0.02)  # the encoder keeps up: the failure shows a few frames later
    assert error is not None and error.errno == errno.ENOSPC
    assert error.filename == str(tmp_path / "v.mp4")
    budget["bytes"] = None
    kept, close_error = outputs.close_outputs(video, [results], complete=False)
    assert close_error is None or close_error.errno == errno.ENOSPC
    assert kept[0] == tmp_path / "v.incomplete.mp4"
    written = sorted(p.name for p in (tmp_path / "data").iterdir())
    assert 0 < len(written) < 30
    assert count_frames(kept[0]) == len(decode_pyav(kept[0])[2]) == len(written)
    assert written == [f"{i:06d}.txt" for i in range(len(written))]
    assert sorted(p.name for p in tmp_path.glob(".*")) == []


class _Reports(http.server.SimpleHTTPRequestHandler):
    """Serves the page and the video; the page POSTs what the browser saw to /report."""

    reports: list = []

    def do_POST(self):  # noqa: N802 - http.server's name
        length = int(self.headers["Content-Length"])
        self.reports.append(json.loads(self.rfile.read(length)))
        self.send_response(204)
        self.end_headers()

    def log_message(self, *args) -> None:
        pass


PAGE = """<!doctype html><html><body>
<video id="v" muted playsinline preload="auto" src="v.mp4"></video>
<script>
const v = document.getElementById("v");
let presented = 0;
function count(now, meta) { presented = meta.presentedFrames; v.requestVideoFrameCallback(count); }
v.requestVideoFrameCallback(count);
function report(result) { fetch("/report", {method: "POST", body: JSON.stringify(result)}); }
v.addEventListener("error", () => report({error: v.error ? v.error.code : -1}));
v.addEventListener("ended", () => {
  const q = v.getVideoPlaybackQuality();
  report({duration: v.duration, decoded: q.totalVideoFrames, dropped: q.droppedVideoFrames,
          presented: presented, width: v.videoWidth, height: v.videoHeight});
});
v.playbackRate = 0.5;  // a loaded machine still shows every frame in time
v.play().catch(e => report({error: String(e)}));
</script></body></html>
"""


def browser_plays(folder, timeout: float = 60.0) -> dict:
    """Headless Chromium loads ``folder/index.html`` (served on the loopback) and plays
    ``folder/v.mp4``; returns what the page reported."""
    handler = functools.partial(_Reports, directory=str(folder))
    _Reports.reports = []
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{server.server_port}/index.html"
    command = ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--mute-audio",
               "--autoplay-policy=no-user-gesture-required",
               f"--user-data-dir={folder / 'profile'}", url]  # fmt: skip
    browser = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               start_new_session=True)  # fmt: skip
    try:
        deadline = time.monotonic() + timeout
        while not _Reports.reports and time.monotonic() < deadline and browser.poll() is None:
            time.sleep(0.1)
    finally:
        if browser.poll() is None:
            os.killpg(browser.pid, signal.SIGTERM)
        browser.wait(timeout=30)
        server.shutdown()
    assert _Reports.reports, f"the page reported nothing in {timeout:g} s"
    return _Reports.reports[0]


def test_a_browser_plays_the_h264_video(tmp_path):
    """Debian's Chromium (CI installs it: .ci/run) plays the video in a page: its duration,
    every frame decoded (``totalVideoFrames``: shown or dropped as late) and nearly all shown
    (a loaded machine may drop one), at the padded size."""
    if shutil.which("chromium") is None:
        pytest.skip("chromium is not installed (apt-get install chromium; .ci/run does)")
    video = outputs.AnnotatedVideo(tmp_path / "v.mp4", FPS)
    for rgb in pictures(15):
        video.write(rgb)
    video.close()
    (tmp_path / "index.html").write_text(PAGE)
    seen = browser_plays(tmp_path)
    assert "error" not in seen, seen
    assert seen["duration"] == pytest.approx(1.5, abs=0.01)
    assert seen["decoded"] == 15 and seen["presented"] >= 13, seen
    assert seen["presented"] + seen["dropped"] >= 14, seen
    assert (seen["width"], seen["height"]) == (162, 76)
