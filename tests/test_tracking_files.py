"""Tracking files read as the official TrackEval reads them: every malformed file is refused
with one line naming FILE:LINE (exit 2), seqmaps decide the sequences and their lengths, an
empty result folder is refused unless asked for. (That the seqmap case's figures equal
TrackEval's is tests/test_tracking_eval.py's ``seqmap_subset`` case.)"""

from __future__ import annotations

import json

import pytest

from gac_jax.cli import evaluate as cli
from gac_jax.data.files import KittiFormatError
from gac_jax.evaluation.tracking.evaluator import load_tracking_folders
from gac_jax.evaluation.tracking.seqmap import parse_seqmap
from gac_jax.evaluation.tracking.tracking_files import parse_tracking_rows
from tests import tracking_cases

SEQMAP = "evaluate_tracking.seqmap.training"


def _run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def _refused(argv, capsys, *needles) -> str:
    """Runs the CLI; asserts exit 2 with one ``error:`` line holding every needle."""
    code, _, err = _run(argv, capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])
    return lines[0]


@pytest.fixture
def case(tmp_path):
    """The "hand" case (labels, results, seqmap) and the CLI arguments that score it."""
    tracking_cases.write_case("hand", tmp_path)
    argv = ["--task", "track", "--label-dir", tmp_path / "label_02"]
    return tmp_path, [*argv, "--result-dir", tmp_path / "results"]


def _lines(path):
    return path.read_text().splitlines(keepends=True)


def test_a_line_that_lost_a_column_is_refused(case, capsys):
    """A result line without its alpha among 18-column lines (TrackEval stops on the file)."""
    root, argv = case
    path = root / "results/0000.txt"
    lines = _lines(path)
    fields = lines[4].split()
    lines[4] = " ".join(fields[:5] + fields[6:]) + "\n"  # 17 columns: alpha dropped
    path.write_text("".join(lines))
    _refused(argv, capsys, "0000.txt:5", "17 columns, but line 1 has 18")
    lines[4] = " ".join(fields[:17]) + "\n"  # the score dropped: still not the file's count
    path.write_text("".join(lines))
    _refused(argv, capsys, "0000.txt:5", "17 columns")
    # a file of 17-column lines only is a file without scores: read, every score 1
    rows = parse_tracking_rows("".join(" ".join(x.split()[:17]) + "\n" for x in lines), "r", True)
    assert len(rows) == len(lines) and (rows.score == 1.0).all()


def test_frames_beyond_the_sequence_are_refused(case, capsys):
    root, argv = case
    seqmap = root / SEQMAP
    frames = parse_seqmap(seqmap.read_text())
    assert frames == {"0000": 8, "0001": 3, "0002": 3}
    res = root / "results/0002.txt"
    # frame 3 of a 3-frame sequence (the seqmap's length) in a result file
    res.write_text(_line(3))
    _refused(argv, capsys, "0002.txt:1", "frame 3 is beyond the sequence's 3 frames", "seqmap")
    # in a label file
    res.write_text("")
    labels = root / "label_02/0002.txt"
    good = labels.read_text()
    labels.write_text(good + _line(7, score=None))
    _refused(argv, capsys, "0002.txt:4", "frame 7 is beyond the sequence's 3 frames")
    # without a seqmap: the images beside label_02 give the length, else the labels (0001,
    # without labels, has no frame: its result line is refused as well)
    labels.write_text(good)
    seqmap.unlink()
    res.write_text(_line(3))
    _refused(argv, capsys, "0001.txt:1", "frame 2 is beyond the sequence's 0 frames")
    argv = [*argv, "--sequences", "0002"]
    _refused(argv, capsys, "0002.txt:1", "frame 3 is beyond", "last labelled frame")
    images = root / "image_02/0002"
    images.mkdir(parents=True)
    for k in range(4):
        (images / f"{k:06d}.png").write_bytes(b"")
    code, out, err = _run(argv, capsys)
    assert code == 0, err


def _line(frame, tid=5, score=0.5):
    text = f"{frame} {tid} Car 0 0 0 10 10 100 100 1.5 1.6 3.9 1 1.6 10 0"
    return text + (f" {score}\n" if score is not None else "\n")


def test_a_seqmap_decides_the_sequences(case, capsys):
    """Beside the labels or given with --seqmap; the training one of several; --sequences
    picks among its sequences; a malformed seqmap names its line."""
    root, argv = case
    (root / SEQMAP).write_text("0000 empty 000000 000008\n0002 empty 000000 000003\n")
    out_json = root / "out.json"
    code, out, err = _run([*argv, "--json", out_json], capsys)
    assert code == 0, err
    assert json.loads(out_json.read_text())["_meta"]["sequences"] == ["0000", "0002"]
    assert f"lengths from seqmap {root / SEQMAP}" in out
    other = root / "elsewhere.seqmap"
    other.write_text("0001 empty 000000 000003\n")
    code, out, err = _run([*argv, "--seqmap", other, "--json", out_json], capsys)
    assert code == 0, err
    assert json.loads(out_json.read_text())["_meta"]["sequences"] == ["0001"]
    (root / "evaluate_tracking.seqmap.val").write_text("0001 empty 000000 000003\n")
    seqs = load_tracking_folders(root / "label_02", root / "results")
    assert [s.name for s in seqs] == ["0000", "0002"]  # .training, as TrackEval's default
    (root / SEQMAP).rename(root / "evaluate_tracking.seqmap.test")
    _refused(argv, capsys, "several seqmaps", "--seqmap")
    _refused([*argv, "--seqmap", other, "--sequences", "0002"], capsys, "0002 is not in")
    other.write_text("0001 empty 000000 000003\n0002 empty\n")
    _refused([*argv, "--seqmap", other], capsys, "elsewhere.seqmap:2", "found 2 fields")
    other.write_text("0001 empty 000000 3.5\n")
    _refused([*argv, "--seqmap", other], capsys, "elsewhere.seqmap:1", "not an integer")
    other.write_text("0007 empty 000000 000003\n")
    _refused([*argv, "--seqmap", other], capsys, "0007.txt", "no label file")


def test_nan_and_inf_are_named_by_line_and_column(case, capsys):
    root, argv = case
    path = root / "results/0000.txt"
    lines = _lines(path)
    fields = lines[2].split()
    fields[14] = "nan"  # y of line 3 (the class column of line 1 is text, not a bad value)
    lines[2] = " ".join(fields) + "\n"
    path.write_text("".join(lines))
    _refused(argv, capsys, "0000.txt:3", "'nan'", "column 15 (y)")
    fields[14], fields[17] = "1.6", "inf"
    lines[2] = " ".join(fields) + "\n"
    path.write_text("".join(lines))
    _refused(argv, capsys, "0000.txt:3", "non-finite value 'inf'", "column 18 (score)")
    fields[17], fields[6] = "0.5", "1e"
    lines[2] = " ".join(fields) + "\n"
    path.write_text("".join(lines))
    _refused(argv, capsys, "0000.txt:3", "non-numeric value '1e'", "column 7 (x1)")


def test_an_empty_result_folder_is_refused_unless_meant(case, capsys):
    root, argv = case
    for path in (root / "results").glob("*.txt"):
        path.write_text("")
    _refused(argv, capsys, "results", "no result line", "--allow-empty-results")
    for path in (root / "results").glob("*.txt"):
        path.unlink()
    _refused(argv, capsys, "results", "no result files", "--allow-empty-results")
    code, out, err = _run([*argv, "--allow-empty-results", "--classes", "car"], capsys)
    assert code == 0, err
    assert "3 sequences without a result file" in out


def test_a_duplicate_id_names_its_line(case, capsys):
    root, argv = case
    path = root / "results/0000.txt"
    lines = _lines(path)
    path.write_text("".join(lines[:3] + [lines[0]] + lines[3:]))  # line 4 repeats line 1
    _refused(argv, capsys, "0000.txt:4", "track id 10 appears twice in frame 0 (also on line 1)")
    labels = root / "label_02/0002.txt"
    labels.write_text(labels.read_text() + _line(1, tid=0, score=None))
    path.write_text("".join(lines))
    _refused(argv, capsys, "label_02/0002.txt:4", "ground-truth track id 0 appears twice")


def test_errors_are_kitti_format_errors_with_the_line():
    with pytest.raises(KittiFormatError) as info:
        parse_tracking_rows(_line(0) + _line(1, score=None), "r.txt", with_score=True)
    assert info.value.line == 2 and info.value.path == "r.txt"
