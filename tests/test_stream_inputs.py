"""What a stream reads, as recordings really are: a damaged frame or image is skipped and the
stream goes on (only many in a row end it); variable-frame-rate MKV and MPEG-TS files keep
their timing (the tracker's and the annotated video's) and are not "truncated"; a pose file is
checked against the frames actually read; a video whose name is not UTF-8 streams, and its
name prints under a strict UTF-8 locale. Inputs made here (tests/stream_cases.py), through the
tiny trained detector."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from gac_jax.data.files import write_png
from tests.stream_cases import (
    damage_avi,
    numbered,
    one_line,
    run,
    video_times,
    write_avi,
    write_vfr,
)
from tests.stream_cases import predict as predict_process


def warnings_in(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("warning: ")]


def test_a_damaged_frame_is_skipped_and_the_stream_goes_on(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys
):
    """A 40-frame AVI whose frame 20 does not decode: one warning naming the file and the
    frame, every other frame's results (none for 000020), a video of 39 frames at the input's
    times (frame 21 still at 2.1 s), the count in the summary, exit 0."""
    video = damage_avi(write_avi(tmp_path / "drive.avi", numbered(half_frames, 40)), [20])
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    code, stdout, err = run([*argv, "--out", out, "--report-every", 0], capsys)
    assert code == 0, err
    assert sorted(p.stem for p in (out / "data").glob("*.txt")) == [
        f"{i:06d}" for i in range(40) if i != 20
    ]
    expected = [i / 10 for i in range(40) if i != 20]
    np.testing.assert_allclose(video_times(out / "annotated.mp4"), expected, atol=1e-3)
    (warning,) = warnings_in(err)
    assert "drive.avi: frame 000020 cannot be decoded" in warning and "skipped" in warning
    assert "1 damaged frame of " in stdout and "no results for 000020" in stdout


def test_an_image_that_cannot_be_read_is_skipped(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys
):
    """A sequence of 6 images whose third is cut short: skipped with one warning naming it, the
    other five written (JSON lines, each with its time: index / 10 s), exit 0."""
    folder = tmp_path / "seq"
    for i, image in enumerate(half_frames[:3] * 2):
        write_png(folder / f"{i:06d}.png", image)
    data = (folder / "000002.png").read_bytes()
    (folder / "000002.png").write_bytes(data[: len(data) // 3])
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--sequence", folder, "--calib", half_calib]
    code, stdout, err = run([*argv, "--out", out, "--jsonl", "--no-video"], capsys)
    assert code == 0, err
    records = [json.loads(line) for line in (out / "detections.jsonl").read_text().splitlines()]
    assert [(r["frame"], r["time"]) for r in records] == [
        (f"{i:06d}", i / 10) for i in (0, 1, 3, 4, 5)
    ]
    (warning,) = warnings_in(err)
    assert "image 000002.png cannot be read" in warning
    assert "1 damaged image of " in stdout


def test_many_damaged_frames_in_a_row_end_the_stream(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys
):
    """Frames 10 to 44 of a 60-frame AVI damaged: the stream stops at the 25th in a row with
    one line naming the file and the count, exit 2; the 10 frames before are written."""
    video = damage_avi(write_avi(tmp_path / "bad.avi", numbered(half_frames, 60)), range(10, 45))
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    code, _, err = run([*argv, "--out", out, "--no-video", "--report-every", 0], capsys)
    warned = warnings_in(err)
    assert len(warned) == 1, err  # rate-limited: one line for the row
    err = "\n".join(line for line in err.splitlines() if line not in warned)
    assert code == 2
    one_line(err, "bad.avi: 25 damaged frames in a row (frames 000010 to 000034")
    assert sorted(p.stem for p in (out / "data").glob("*.txt")) == [f"{i:06d}" for i in range(10)]


@pytest.mark.parametrize("container, codec", [("mkv", "mjpeg"), ("ts", "mpeg2video")])
def test_a_variable_frame_rate_video_keeps_its_timing(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys, monkeypatch, container, codec
):
    """12 frames at irregular times (a phone's or dashcam's recording; the header's count and
    rate are guesses): all 12 are read (not "truncated"), the 12-line pose file fits, and the
    frames' own times are the tracker's timestamps, the annotated video's frame times and the
    JSON lines' ``time``."""
    from gac_jax.api.tracker import Tracker3D

    times = [0.0, 0.1, 0.15, 0.45, 0.5, 1.2, 1.25, 1.3, 2.0, 2.05, 2.5, 3.0]
    video = write_vfr(tmp_path / f"phone.{container}", numbered(half_frames, 12), times, codec)
    poses = tmp_path / "poses.txt"
    poses.write_text("".join(f"1 0 0 {0.5 * i} 0 1 0 0 0 0 1 0\n" for i in range(12)))
    seen = []
    update = Tracker3D.update

    def recording(self, detections, pose=None, timestamp=None, plane=None):
        seen.append(timestamp)
        return update(self, detections, pose=pose, timestamp=timestamp, plane=plane)

    monkeypatch.setattr(Tracker3D, "update", recording)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    argv += ["--out", out]
    code, stdout, err = run([*argv, "--track", "--poses", poses, "--jsonl"], capsys)
    assert code == 0, err
    assert err.strip() == "", err
    np.testing.assert_allclose(seen, times, atol=1e-3)
    np.testing.assert_allclose(video_times(out / "annotated.mp4"), times, atol=1e-3)
    records = [json.loads(line) for line in (out / "tracks.jsonl").read_text().splitlines()]
    np.testing.assert_allclose([r["time"] for r in records], times, atol=1e-3)
    assert stdout.count("12 frames -> ") == 1


@pytest.mark.parametrize("poses", [6, 14])
def test_poses_are_checked_against_the_frames_read(
    tiny_detect3d_workdir, half_frames, half_calib, tmp_path, capsys, poses
):
    """A 10-frame video: 6 poses stop the stream at frame 6 with one line naming the pose
    file (the tracks of frames 0 to 5 written), exit 2; 14 poses track all 10 frames and warn
    that 4 were not used, exit 0."""
    video = write_avi(tmp_path / "drive.avi", numbered(half_frames, 10))
    path = tmp_path / "poses.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * poses)
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--video", video, "--calib", half_calib]
    argv += ["--out", out, "--track", "--poses", path, "--no-video", "--report-every", 0]
    code, stdout, err = run(argv, capsys)
    lines = (out / "tracking" / "0000.txt").read_text().splitlines()
    assert all(int(line.split()[0]) < min(poses, 10) for line in lines)
    if poses == 6:
        assert code == 2
        one_line(err, f"{path}: no pose for frame 000006 (the file has 6 poses")
        assert "6 frames -> " in stdout
    else:
        assert code == 0, err
        (warning,) = warnings_in(err)
        assert f"{path}: 14 poses for the 10 frames read; the last 4 were not used" in warning
        assert "10 frames -> " in stdout


def test_a_name_that_is_not_utf8(tiny_detect3d_workdir, half_frames, half_calib, tmp_path):
    """A video and an output folder named in Latin-1 bytes, under a strict UTF-8 stdout: the
    stream runs (the names printed with backslash escapes), exit 0. An .avi output OpenCV would
    have to open under such a name is refused before anything runs: one line, exit 2."""
    folder = os.fsencode(tmp_path)
    video = folder + b"/drive_\xe9t\xe9.avi"
    write_avi(tmp_path / "plain.avi", numbered(half_frames, 4)).rename(os.fsdecode(video))
    out = folder + b"/r\xe9sultats"
    env = {"PYTHONIOENCODING": "utf-8:strict", "LC_ALL": "C.UTF-8"}
    argv = [b"--workdir", tiny_detect3d_workdir, b"--video", video, b"--calib", half_calib]
    process = predict_process([*argv, b"--out", out, b"--report-every", b"0"], env=env)
    stdout, stderr = process.communicate(timeout=600)
    assert process.returncode == 0, stderr.decode(errors="replace")
    assert b"drive_\\udce9t\\udce9.avi" in stdout and stderr == b""
    assert len(os.listdir(out + b"/data")) == 4 and os.path.isfile(out + b"/annotated.mp4")

    bad = [*argv, b"--out", folder + b"/o2", b"--out-video", folder + b"/v_\xe9.avi"]
    process = predict_process(bad, env=env)
    stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 2 and stdout == b""
    one_line(stderr.decode(), "OpenCV cannot write a .avi video whose path is not UTF-8")
    assert not os.path.exists(folder + b"/o2")


def test_decoding_errors_of_the_container_are_not_its_end(half_frames, half_calib, tmp_path):
    """The source alone: the damaged frame's position is skipped, the frame after it keeps
    its own; nothing is inferred from the header's frame count (a cut file ends where its
    frames end, with a truncation reported only for the frame cut in two)."""
    from gac_jax.data.files import KittiFormatError
    from gac_jax.streams import sources

    P2 = sources.load_projection(half_calib)
    video = damage_avi(write_avi(tmp_path / "v.avi", numbered(half_frames, 12)), [3, 4])
    src = sources.VideoSource(video, P2, os.fspath(half_calib), warn=lambda line: None)
    got = []
    while (frame := src.read()) is not None:
        got.append((frame.index, round(frame.time, 3)))
    src.check_complete()
    assert got == [(i, i / 10) for i in range(12) if i not in (3, 4)]
    assert src.damaged.count == 2 and src.expected_frames == 12
    data = (tmp_path / "v.avi").read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    src = sources.VideoSource(cut, P2, os.fspath(half_calib), warn=lambda line: None)
    while src.read() is not None:
        pass
    with pytest.raises(KittiFormatError, match="cut.avi: truncated or damaged at its end"):
        src.check_complete()
