"""python -m gac_jax.cli.predict --video/--sequence/--camera/--clip: streams through the tiny
trained detector -> a playable annotated video and per-frame results equal to the image-folder
predict path's; bad inputs give one line and exit 2; Ctrl-C leaves a playable video."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from gac_jax.cli import predict
from gac_jax.data.files import read_image, write_png
from gac_jax.data.kitti import read_calib, read_label, write_calib, write_plane

SIZE = (370, 1224)  # the smallest vendored frame: the others are cut to it (top-left: same P2)
REPO = Path(__file__).resolve().parents[1]


def run(argv, capsys):
    code = predict.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def frames(kitti_object_root) -> list[np.ndarray]:
    images = sorted((kitti_object_root / "training" / "image_2").glob("*.png"))
    return [read_image(p)[: SIZE[0], : SIZE[1]] for p in images]


@pytest.fixture(scope="module")
def calib(kitti_object_root):
    return read_calib(kitti_object_root / "training" / "calib" / "000001.txt")


def write_video(path: Path, images, fps: float = 10.0, codec: str = "MJPG") -> Path:
    h, w = images[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*codec), fps, (w, h))
    for image in images:
        writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def decoded_frames(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened(), path
    out = []
    while True:
        ok, bgr = capture.read()
        if not ok:
            break
        out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
    return out


def folder_predict(workdir, images, calib, planes, tmp: Path, capsys) -> dict[str, str]:
    """Result files of the image-folder predict path for ``images`` (object layout: the
    planes in ``../planes``)."""
    folder = tmp / "image_2"
    for i, image in enumerate(images):
        write_png(folder / f"{i:06d}.png", image)
        if planes[i] is not None:
            write_plane(tmp / "planes" / f"{i:06d}.txt", planes[i])
    write_calib(tmp / "calib.txt", calib)
    argv = ["--workdir", workdir, folder, "--calib", tmp / "calib.txt", "--out", tmp / "out"]
    code, _, err = run([*argv, "--no-images"], capsys)
    assert code == 0, err
    return {p.stem: p.read_text() for p in (tmp / "out" / "data").glob("*.txt")}


@pytest.fixture
def small_clip_set(tmp_path, monkeypatch) -> Path:
    """``--clip`` generates a 1-sequence, 5-frame set into a temporary cache."""
    from gac_jax.cli import stream_start

    monkeypatch.setenv("GAC_JAX_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(stream_start, "CLIP_SEQUENCES", 1)
    monkeypatch.setattr(stream_start, "CLIP_FRAMES", 5)
    return stream_start.clip_sequence(0)


def test_a_generated_clip_gives_the_image_predict_results(
    tiny_detect3d_workdir, small_clip_set, tmp_path, capsys
):
    """``--clip``: the generated tracking-layout sequence, its calibration and per-frame planes
    found by themselves -> a playable annotated video of every frame at 10 frames/s, and
    per-frame results equal to the image-folder path's (same frames, calibration, planes)."""
    from gac_jax.data.kitti import read_plane

    folder = small_clip_set
    training = folder.parent.parent
    images = [read_image(p) for p in sorted(folder.glob("*.png"))]
    planes = [read_plane(p) for p in sorted((training / "planes" / folder.name).glob("*.txt"))]
    assert len(images) == len(planes) == 5
    calib = read_calib(training / "calib" / f"{folder.name}.txt")
    expected = folder_predict(
        tiny_detect3d_workdir, images, calib, planes, tmp_path / "ref", capsys
    )
    out = tmp_path / "clip"
    code, stdout, err = run(["--workdir", tiny_detect3d_workdir, "--clip", "--out", out], capsys)
    assert code == 0, err
    assert {p.stem: p.read_text() for p in (out / "data").glob("*.txt")} == expected
    assert len(decoded_frames(out / "annotated.mp4")) == 5
    assert cv2.VideoCapture(str(out / "annotated.mp4")).get(cv2.CAP_PROP_FPS) == 10.0
    summary = [line for line in stdout.splitlines() if line.startswith("5 frames -> ")]
    assert len(summary) == 1 and "frames/s, latency median" in summary[0], stdout
    assert "per frame, each stage" in stdout and "network" in stdout
    assert "precision: jax float32, the guard's reference" in stdout
    assert "score threshold 0.00 (eval.score_threshold)" in stdout  # the tiny config deploys it


def test_a_video_file_gives_the_image_predict_results(
    tiny_detect3d_workdir, frames, calib, tmp_path, capsys
):
    """A video written by OpenCV (its decoded frames as the reference): a playable annotated
    video at the input's fps and per-frame results (KITTI files, or JSON lines) equal to the
    image-folder path's."""
    images = [frames[i % len(frames)] for i in range(6)]
    video = write_video(tmp_path / "input.avi", images, fps=12.0)
    decoded = decoded_frames(video)  # MJPG is lossy: the reference sees what the stream sees
    expected = folder_predict(
        tiny_detect3d_workdir, decoded, calib, [None] * 6, tmp_path / "ref_video", capsys
    )
    write_calib(tmp_path / "calib.txt", calib)
    out = tmp_path / "video"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", tmp_path / "calib.txt"]
    code, stdout, err = run([*argv, "--out", out, "--out-video", out / "boxes.avi"], capsys)
    assert code == 0, err
    assert {p.stem: p.read_text() for p in (out / "data").glob("*.txt")} == expected
    capture = cv2.VideoCapture(str(out / "boxes.avi"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(12.0)
    pictures = decoded_frames(out / "boxes.avi")
    assert len(pictures) == 6 and pictures[0].shape[0] == SIZE[0]
    assert pictures[0].shape[1] > SIZE[1]  # camera view + bird's-eye view

    jsonl = ["--out", tmp_path / "jsonl", "--jsonl", "--no-images", "--max-frames", 4]
    code, _, err = run([*argv, *jsonl], capsys)
    assert code == 0, err
    lines = (tmp_path / "jsonl" / "detections.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in lines]
    assert [r["frame"] for r in records] == [f"{i:06d}" for i in range(4)]
    for r in records:
        kitti = read_label(out / "data" / f"{r['frame']}.txt", with_score=True)
        scores = [o["score"] for o in r["objects"]]
        np.testing.assert_allclose(scores, kitti.score, atol=1e-4)
    assert not (tmp_path / "jsonl" / "annotated.mp4").exists()


def one_error_line(code: int, err: str, *needles: str) -> str:
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


def test_bad_inputs_give_one_line(tiny_detect3d_workdir, frames, calib, tmp_path, capsys):
    wd = tiny_detect3d_workdir
    video = write_video(tmp_path / "in.avi", frames[:2])
    code, _, err = run(["--workdir", wd, "--video", video], capsys)
    one_error_line(code, err, "in.avi", "no calibration", "--calib FILE")
    write_calib(tmp_path / "calib.txt", calib)
    small = write_video(tmp_path / "small.avi", [f[:200, :400] for f in frames[:2]])
    code, _, err = run(
        ["--workdir", wd, "--video", small, "--calib", tmp_path / "calib.txt"], capsys
    )
    one_error_line(code, err, "calib.txt", "does not fit the 400x200 frames", "outside")
    code, _, err = run(["--workdir", wd, "--sequence", tmp_path / "nothing"], capsys)
    one_error_line(code, err, "nothing", "not found")
    # a video that ends early: its frames are processed and written, then one line, exit 2
    full = write_video(tmp_path / "full.avi", [frames[i % len(frames)] for i in range(20)])
    data = full.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "cut_out"
    argv = ["--video", cut, "--calib", tmp_path / "calib.txt", "--out", out, "--no-images"]
    code, stdout, err = run(["--workdir", wd, *argv], capsys)
    warned = [line for line in err.splitlines() if line.startswith("warning: ")]
    assert len(warned) == 1 and "cut short" in warned[0], err  # the frame cut in two
    err = "\n".join(line for line in err.splitlines() if line not in warned)
    line = one_error_line(code, err, "cut.avi", "truncated or damaged at its end")
    decoded = int(line.split("the results of the ")[1].split()[0])
    assert 0 < decoded < 20 and len(list((out / "data").glob("*.txt"))) == decoded
    with pytest.raises(SystemExit):  # two inputs
        predict.main(["--workdir", str(wd), str(tmp_path), "--video", str(video)])
    with pytest.raises(SystemExit):  # the old P2/P3 option is --calib-camera now
        predict.main(["--workdir", str(wd), str(tmp_path), "--camera", "3"])


def subprocess_env() -> dict:
    return {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.mark.parametrize("case", ["truncated", "camera"])
def test_a_truncated_video_or_a_camera_that_does_not_open(
    tiny_detect3d_workdir, frames, calib, tmp_path, case
):
    """In a fresh process, so that OpenCV's and FFmpeg's own messages would show on stderr."""
    write_calib(tmp_path / "calib.txt", calib)
    if case == "truncated":
        video = write_video(tmp_path / "clip.mp4", frames, codec="mp4v")
        data = video.read_bytes()
        video.write_bytes(data[: len(data) // 2])
        source = ["--video", str(video)]
        needles = ("clip.mp4", "cannot be opened as a video")
    else:
        source = ["--camera", "99"]
        needles = ("camera 99", "could not be opened")
    argv = [
        "--workdir",
        str(tiny_detect3d_workdir),
        *source,
        "--calib",
        str(tmp_path / "calib.txt"),
    ]
    done = subprocess.run(
        [sys.executable, "-m", "gac_jax.cli.predict", *argv],
        capture_output=True,
        text=True,
        env=subprocess_env(),
        timeout=300,
    )
    one_error_line(done.returncode, done.stderr, *needles)


def test_realtime_drops_frames_and_accounts_for_them(
    tiny_detect3d_workdir, frames, calib, tmp_path, capsys
):
    """A file replayed live at 400 frames/s: the detector cannot keep up, the newest frame is
    kept, and written + dropped frames == delivered frames."""
    images = [frames[i % len(frames)] for i in range(60)]
    video = write_video(tmp_path / "fast.avi", images)
    write_calib(tmp_path / "calib.txt", calib)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", tmp_path / "calib.txt"]
    code, stdout, err = run([*argv, "--out", out, "--realtime", "--fps", 400], capsys)
    assert code == 0, err
    dropped_line = next(line for line in stdout.splitlines() if "delivered frames dropped" in line)
    dropped, delivered = (int(w) for w in dropped_line.split()[:3:2])
    written = len(list((out / "data").glob("*.txt")))
    assert dropped > 0 and delivered == 60 and written + dropped == delivered
    assert len(decoded_frames(out / "annotated.mp4")) == written
    assert (out / "data" / "000059.txt").exists()  # the last frame is not dropped


def test_ctrl_c_leaves_a_playable_video(tiny_detect3d_workdir, frames, calib, tmp_path):
    images = [frames[i % len(frames)] for i in range(400)]
    video = write_video(tmp_path / "long.avi", images)
    write_calib(tmp_path / "calib.txt", calib)
    out = tmp_path / "out"
    argv = ["--workdir", str(tiny_detect3d_workdir), "--video", str(video)]
    argv += ["--calib", str(tmp_path / "calib.txt"), "--out", str(out), "--report-every", "1"]
    process = subprocess.Popen(
        [sys.executable, "-m", "gac_jax.cli.predict", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=subprocess_env(),
    )
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and process.poll() is None:
        if len(list((out / "data").glob("*.txt"))) >= 5:
            break
        time.sleep(0.2)
    assert process.poll() is None, process.communicate()
    process.send_signal(signal.SIGINT)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 130, (stdout, stderr)
    written = len(list((out / "data").glob("*.txt")))
    assert 5 <= written < 400
    assert len(decoded_frames(out / "annotated.mp4")) == written
    assert "interrupted: reading stopped after" in stdout and "in flight finished" in stdout
    assert stderr.strip() == "", stderr
