"""python -m gac_jax.cli.predict --sequence --track on a generated clip: one KITTI tracking
result file per sequence and a playable annotated video from the tiny trained detector; a pose
file with the wrong number of frames gives one line naming it and exit 2."""

from __future__ import annotations

from pathlib import Path

import cv2
import pytest

from gac_jax.cli import predict


@pytest.fixture
def clip_sequence(tmp_path) -> Path:
    """A generated clip set of one 5-frame sequence (188 x 621), its image folder."""
    from gac_jax.data.synthetic.clips import generate_clips

    generate_clips(tmp_path / "clips", 1, 5, seed=0, height=188, width=621, workers=1)
    return tmp_path / "clips" / "training" / "image_02" / "0000"


def test_track_on_a_clip_writes_a_tracking_file_and_a_video(
    tiny_detect3d_workdir, clip_sequence, tmp_path, capsys
):
    """A generated clip as a KITTI tracking sequence (calibration, planes and poses found by
    themselves). Every line of ``tracking/0000.txt`` has the KITTI tracking result format (frame in
    0..4, integer id, a class, ``-1 -1``, 13 numbers); a track id keeps its class; the video
    has the 5 frames, camera view + bird's-eye view, at ``--video-scale``'s size."""
    out = tmp_path / "out"
    argv = ["--workdir", tiny_detect3d_workdir, "--sequence", clip_sequence, "--track"]
    argv += ["--out", out, "--video-scale", 0.5]
    code = predict.main([str(a) for a in argv])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    lines = (out / "tracking" / "0000.txt").read_text().splitlines()
    assert lines, "the tiny detector (score threshold 0) finds objects"
    classes = {}
    for line in lines:
        fields = line.split()
        assert len(fields) == 18, line
        assert 0 <= int(fields[0]) <= 4 and int(fields[1]) >= 0
        assert fields[3:5] == ["-1", "-1"]
        [float(v) for v in fields[5:]]
        assert classes.setdefault(int(fields[1]), fields[2]) == fields[2]
    frames = sorted({int(line.split()[0]) for line in lines})
    assert frames[-1] == 4
    assert not (out / "data").exists()
    capture = cv2.VideoCapture(str(out / "annotated.mp4"))
    count = 0
    while capture.read()[0]:
        count += 1
    assert count == 5
    h, w = cv2.imread(str(sorted(Path(clip_sequence).glob("*.png"))[0])).shape[:2]
    assert capture.get(cv2.CAP_PROP_FRAME_HEIGHT) == round(h / 2)  # --video-scale 0.5
    assert capture.get(cv2.CAP_PROP_FRAME_WIDTH) > round(w / 2)  # camera view + bird's-eye view
    assert "tracking/0000.txt" in stdout


def test_a_pose_file_of_the_wrong_length_is_named(tmp_path, capsys):
    """Checked before the detector loads: ``error: <file>: 3 poses for 5 frames ...``."""
    import numpy as np

    from gac_jax.data.files import write_png

    folder = tmp_path / "frames"
    for i in range(5):
        write_png(folder / f"{i:06d}.png", np.zeros((60, 200, 3), np.uint8))
    P2 = "700 0 100 0 0 700 30 0 0 0 1 0"
    (folder / "calib.txt").write_text(f"P2: {P2}\n")
    bad = tmp_path / "poses.txt"
    bad.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 3)
    workdir = tmp_path / "w"
    workdir.mkdir()
    argv = ["--workdir", workdir, "--sequence", folder, "--track", "--poses", bad]
    code = predict.main([str(a) for a in argv])
    _, err = capsys.readouterr()
    assert code == 2
    assert err.strip().splitlines() == [
        f"error: {bad}: 3 poses for 5 frames (one line of 12 numbers per frame)"
    ]
