"""What a stream writes and prints, whatever happens around it: ``--overwrite`` gives the
earlier results back unless a frame replaced them; one stream per output folder; a closed or
full stdout/stderr changes nothing; numbers, free space and the outputs are refused before
JAX loads (a ``jax`` that fails on import proves it) with one line; a signal in the first
moments gives one line; every message names the user's file. Run as a user runs them
(subprocesses) where the process matters, through the tiny trained detector."""

from __future__ import annotations

import os
import shutil
import signal
import time
from pathlib import Path

import cv2
import pytest

from gac_jax.data.files import write_png
from gac_jax.streams.output_plan import OutputPlan
from tests.stream_cases import (
    damage_avi,
    no_jax,
    numbered,
    one_line,
    run,
    small_filesystem,
    write_avi,
)
from tests.stream_cases import predict as predict_process


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones too) by relative path."""
    return {
        os.fspath(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()
    }


def earlier_run(out: Path) -> dict[str, bytes]:
    """An earlier run's results in ``out``: result files, JSON lines, a video, an incomplete
    video; returns :func:`snapshot`."""
    (out / "data").mkdir(parents=True)
    for i in (98, 99):
        (out / "data" / f"{i:06d}.txt").write_text(f"Car 0 0 0 1 2 3 4 1 1 1 0 0 {i} 0 0.5\n")
    (out / "detections.jsonl").write_text('{"frame": "000098", "index": 0, "objects": []}\n')
    (out / "annotated.mp4").write_bytes(b"an earlier video")
    (out / "annotated.incomplete.mp4").write_bytes(b"an earlier incomplete video")
    return snapshot(out)


@pytest.mark.parametrize("ending", ["missing step", "short poses", "no frame", "SIGTERM"])
def test_overwrite_gives_back_the_earlier_results_when_the_run_fails(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys, ending
):
    """``--overwrite`` over an earlier run's files, in a run that fails before writing a whole
    frame: a checkpoint that does not exist (after loading starts), a pose file shorter than
    the sequence (before), a video whose first decodable frame has no pose (in the stream),
    SIGTERM during start-up (a process). Every earlier file is back, byte for byte, and
    nothing hidden is left."""
    out = tmp_path / "out"
    before = earlier_run(out)
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 6))
    base = ["--workdir", tiny_detect3d_workdir, "--calib", half_calib, "--out", out, "--overwrite"]
    if ending == "missing step":
        code, _, err = run([*base, "--video", video, "--step", 999], capsys)
        assert code == 2 and "999" in err, err
    elif ending == "short poses":
        folder = tmp_path / "seq"
        for i in range(4):
            write_png(folder / f"{i:06d}.png", half_frames[i])
        (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
        argv = [*base, "--sequence", folder, "--track", "--poses", tmp_path / "poses.txt"]
        code, _, err = run(argv, capsys)
        assert code == 2
        one_line(err, "2 poses for 4 frames")
    elif ending == "no frame":
        damage_avi(video, [0, 1, 2])
        (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 2)
        argv = [*base, "--video", video, "--track", "--poses", tmp_path / "poses.txt"]
        code, stdout, err = run(argv, capsys)
        assert code == 2 and "no pose for frame 000003" in err, err
        assert "0 frames -> nothing" in stdout
    else:
        process = predict_process([*base, "--video", video], text=True)
        first = process.stdout.readline()  # printed once the model is loaded
        assert first.startswith("step 2 of "), (first, process.communicate())
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=120)
        assert process.returncode == 143, err
        assert err.strip() == "interrupted: SIGTERM during start-up; nothing was written"
    assert snapshot(out) == before


def test_a_set_aside_is_given_back_after_a_kill(tmp_path):
    """What a killed ``--overwrite`` run moved aside: the next stream into the folder gives it
    back where nothing replaced it (one line says so) and deletes what was replaced."""
    from gac_jax.streams import earlier_results

    out = tmp_path / "out"
    before = earlier_run(out)
    plan = OutputPlan(out, out / "annotated.mp4", out / "data", False)
    aside = earlier_results.set_aside(plan)
    assert sorted(snapshot(out)) == [
        ".gac_jax_earlier/annotated.incomplete.mp4",
        ".gac_jax_earlier/data/000098.txt",
        ".gac_jax_earlier/data/000099.txt",
        ".gac_jax_earlier/detections.jsonl",
        "annotated.mp4",  # the video is replaced only by a complete new one
    ]
    del aside  # killed: neither restored nor discarded
    (out / "data" / "000099.txt").write_text("the killed run's frame\n")
    lines = earlier_results.recover(plan)
    assert len(lines) == 1 and "gave back 3 files" in lines[0]
    after = snapshot(out)
    assert after == {**before, "data/000099.txt": b"the killed run's frame\n"}


def test_one_stream_per_output_folder(tiny_detect3d_workdir, half_frames, half_calib, tmp_path):
    """A second stream into a running stream's ``--out`` (with or without ``--overwrite``),
    or onto its ``--out-video`` from another folder, stops before JAX loads with one line
    naming the running stream's pid, exit 2; the running stream's files are untouched and it
    ends normally."""
    # paced to the file's 5 frames/s (--realtime), so that it is still running after the three
    # refused starts however loaded the machine (unpaced, a tiny model can finish first)
    video = write_avi(tmp_path / "long.avi", numbered(half_frames, 300), fps=5.0)
    out, movie = tmp_path / "out", tmp_path / "movies" / "drive.mp4"
    base = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    first = predict_process(
        [*base, "--out", out, "--out-video", movie, "--report-every", 0, "--realtime"], text=True
    )
    deadline = time.monotonic() + 300
    while first.poll() is None and time.monotonic() < deadline:
        if len(list(out.glob("data/*.txt"))) >= 3:
            break
        time.sleep(0.05)
    assert first.poll() is None, first.communicate()
    env = no_jax(tmp_path / "nojax")
    for argv, where in [
        (["--out", out], out),
        (["--out", out, "--overwrite"], out),
        (["--out", tmp_path / "other", "--out-video", movie], movie),
    ]:
        assert first.poll() is None, first.communicate()  # still running: the case is valid
        written = len(list(out.glob("data/*.txt")))
        second = predict_process([*base, *argv], env=env, text=True)
        stdout, stderr = second.communicate(timeout=120)
        assert second.returncode == 2 and stdout == "", stderr
        one_line(stderr, f"{where}: in use by another stream (pid {first.pid}")
        assert len(list(out.glob("data/*.txt"))) >= written
    assert not (tmp_path / "other").exists()
    first.send_signal(signal.SIGTERM)
    stdout, stderr = first.communicate(timeout=120)
    assert first.returncode == 143, stderr
    written = len(list(out.glob("data/*.txt")))
    assert f"{written} frames -> " in stdout and movie.is_file()


def test_a_closed_stdout_and_a_full_stderr_change_nothing(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path
):
    """stdout read for two lines and closed (``| head -2``), stderr on ``/dev/full``, progress
    lines every 50 ms: the stream runs to its end, exit 0, a complete video under its final
    name and every frame's results."""
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 40))
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    with open("/dev/full", "wb") as full:
        process = predict_process([*argv, "--out", out, "--report-every", 0.05], stderr=full)
        head = [process.stdout.readline() for _ in range(2)]
        process.stdout.close()
        assert process.wait(timeout=600) == 0, head
    assert len(list((out / "data").glob("*.txt"))) == 40
    assert sorted(p.name for p in out.iterdir()) == ["annotated.mp4", "data"]
    capture = cv2.VideoCapture(os.fspath(out / "annotated.mp4"))
    count = 0
    while capture.read()[0]:
        count += 1
    assert count == 40


NUMBERS = {
    "fps tiny": (["--fps", "0.0001"], "--fps must be 0.1 to 1000 frames/s, got 0.0001"),
    "fps huge": (["--fps", "1e300"], "--fps must be 0.1 to 1000 frames/s, got 1e+300"),
    "camera": (["--camera", "99999999999"], "--camera must be a device index 0 to 99"),
    "batch size": (["--batch-size", "0"], "--batch-size must be >= 1, got 0"),
    "threads": (["--threads", "0"], "--threads must be >= 1, got 0"),
    "precision": (["--precision", "fp16"], "argument --precision: invalid choice: 'fp16'"),
    "poses": (["--poses", "p.txt"], "--poses goes with --track"),
    "video scale": (["--video-scale", "1e-9"], "--video-scale must be 0.05 to 4, got 1e-09"),
    "requests": (
        ["--runtime", "openvino", "--network-requests", "1000"],
        "--network-requests must be 1 to 16, got 1000",
    ),
}


@pytest.mark.parametrize("case", sorted(NUMBERS))
def test_a_bad_number_is_one_line_before_jax(half_frames, half_calib, tmp_path, case):
    """Each numeric option out of its range (and the choices argparse checks): one line naming
    it, exit 2, no usage dump, before JAX is imported (it would raise here)."""
    extra, message = NUMBERS[case]
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 2))
    source = [] if "--camera" in extra else ["--video", video]
    argv = ["--workdir", tmp_path, *source, "--calib", half_calib, *extra, "--out", tmp_path / "o"]
    env = no_jax(tmp_path / "nojax")
    process = predict_process(argv, env=env, text=True)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 2 and stdout == "", stderr
    one_line(stderr, message)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("video", [True, False])
def test_too_little_space_is_refused_before_jax(half_frames, half_calib, tmp_path, video):
    """Less free space than 3 s of video (or, with ``--no-video``, than the results need):
    one line naming the folder and what it needs, exit 2, before JAX is imported, and no
    folder left behind."""
    clip = write_avi(tmp_path / "drive.avi", numbered(half_frames, 2))
    with small_filesystem(tmp_path / "small", "1m" if video else "256k") as disk:
        out = disk / "out"
        argv = ["--workdir", tmp_path, "--video", clip, "--calib", half_calib, "--out", out]
        env = no_jax(tmp_path / "nojax")
        process = predict_process(argv if video else [*argv, "--no-video"], env=env, text=True)
        stdout, stderr = process.communicate(timeout=120)
        assert process.returncode == 2 and stdout == "", stderr
        need = "the results and 3 s of video need" if video else "the results need about 1.0 MB"
        one_line(stderr, f"{out}: only ", need)
        assert list(disk.iterdir()) == []


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_in_the_first_moments_is_one_line(half_frames, half_calib, tmp_path, signum):
    """A stop signal as soon as the command runs its own code (OpenCV loading, the arguments
    parsed): one line, exit 128 + N, no traceback."""
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 2))
    argv = ["--workdir", tmp_path, "--video", video, "--calib", half_calib, "--out", tmp_path / "o"]
    process = predict_process(argv, text=True)
    maps = Path(f"/proc/{process.pid}/maps")
    deadline = time.monotonic() + 60
    while process.poll() is None and time.monotonic() < deadline:
        try:
            if "cv2" in maps.read_text():  # OpenCV is being loaded: the command's own imports
                break
        except OSError:
            pass
        time.sleep(0.001)
    process.send_signal(signum)
    stdout, stderr = process.communicate(timeout=60)
    assert process.returncode == 128 + signum, (stdout, stderr)
    name = "Ctrl-C" if signum == signal.SIGINT else "SIGTERM"
    assert stderr.strip().splitlines() == [
        f"interrupted: {name} during start-up; nothing was written"
    ]


MESSAGES = [
    "FIFO",
    "half-size calibration",
    "dangling --out",
    "--out-video exists",
    "read-only data",
]


@pytest.mark.parametrize("case", MESSAGES)
def test_each_message_names_the_users_file(
    tiny_detect3d_workdir, kitti_object_root, half_frames, half_calib, tmp_path, capsys, case
):
    """One line naming what the user gave, before the model loads: a named pipe as the video,
    the calibration of half the picture's size (its principal point at a quarter of the
    frame), an ``--out`` that is a link to nothing, an ``--out-video`` that exists elsewhere, a
    read-only ``data/`` (not our temporary file in it)."""
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 2))
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    argv += ["--out", out]
    if case == "FIFO":
        os.mkfifo(tmp_path / "pipe.mp4")
        argv[3] = tmp_path / "pipe.mp4"
        needles = (f"{tmp_path / 'pipe.mp4'}: is a named pipe (FIFO), not a video file",)
    elif case == "half-size calibration":
        full = [cv2.resize(f, None, fx=2, fy=2) for f in half_frames[:2]]
        argv[3] = write_avi(tmp_path / "full.avi", full)
        needles = (f"{half_calib}: does not fit the 1224x368 frames", "far from the centre")
    elif case == "dangling --out":
        out.symlink_to(tmp_path / "gone" / "results")
        needles = (f"{out}: is a symbolic link to {tmp_path / 'gone' / 'results'}",)
    elif case == "--out-video exists":
        (tmp_path / "movies").mkdir()
        (tmp_path / "movies" / "drive.mp4").write_bytes(b"yesterday's video")
        argv += ["--out-video", tmp_path / "movies" / "drive.mp4"]
        needles = (f"{tmp_path / 'movies' / 'drive.mp4'}: exists (an earlier run's video)",)
    else:
        (out / "data").mkdir(parents=True)
        (out / "data").chmod(0o555)
        needles = (f"{out / 'data'}: results folder cannot be written (permission denied)",)
        if os.geteuid() == 0:  # root writes anywhere: drop the capability that lets it
            if shutil.which("capsh") is None:
                pytest.skip("runs as root and capsh (to drop cap_dac_override) is not installed")
            prefix = ("capsh", "--drop=cap_dac_override", "--", "-c", 'exec "$0" "$@"')
            process = predict_process(argv, prefix=prefix, text=True)
            stdout, stderr = process.communicate(timeout=600)
            assert process.returncode == 2, (stdout, stderr)
            one_line(stderr, *needles)
            return
    code, stdout, err = run(argv, capsys)
    assert code == 2 and stdout == "", (stdout, err)
    one_line(err, *needles)
