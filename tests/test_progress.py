"""Long waits talk (gac_jax.progress): a line per ~10 % in logs and pipes, a bar on a terminal;
the embedded-dataset generator announces what, where and about how long."""

from __future__ import annotations

import io
import re

import pytest

from gac_jax.progress import Progress, about, duration


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_duration_and_estimate_text():
    assert [duration(s) for s in (0, 59.4, 61, 3600 + 62)] == ["0:00", "0:59", "1:01", "1:01:02"]
    assert [about(s) for s in (0.2, 40, 270, 7200)] == [
        "about 1 s",
        "about 40 s",
        "about 4.5 min",
        "about 2.0 h",
    ]


@pytest.mark.parametrize("total", [1, 7, 10, 95, 1000])
def test_plain_lines_every_tenth_and_at_the_end(total):
    out, bar = io.StringIO(), io.StringIO()
    with Progress(total, "synthetic KITTI", "frame", stream=out, bar_stream=bar) as p:
        for _ in range(total):
            p.update()
    lines = out.getvalue().splitlines()
    assert not bar.getvalue()
    assert 1 <= len(lines) <= 10
    assert lines[-1].startswith(f"synthetic KITTI: {total}/{total} frames (100%), ")
    done = [int(re.match(r"synthetic KITTI: (\d+)/", line).group(1)) for line in lines]
    # each line crosses the next tenth: no two lines inside one tenth
    assert [d * 10 // total for d in done] == sorted({d * 10 // total for d in done})
    if total >= 10:
        assert len(lines) == 10
        assert "about" in lines[0] and "left" in lines[0]


def test_a_terminal_gets_a_bar_not_lines():
    out, term = io.StringIO(), _Terminal()
    with Progress(20, "anchor priors", "frame", stream=out, bar_stream=term) as p:
        p.update(20)
    assert not out.getvalue()
    assert "anchor priors" in term.getvalue() and "20/20" in term.getvalue()


def test_disabled_or_empty_is_silent():
    out, term = io.StringIO(), _Terminal()
    for total, enabled in ((5, False), (0, True)):
        with Progress(total, "x", stream=out, bar_stream=term, enabled=enabled) as p:
            p.update(5)
    assert not out.getvalue() and not term.getvalue()


def test_generator_announces_then_reports(tmp_path, capsys):
    """One line before the work (frames, size, folder, an estimate from the measured first
    frame), then progress lines; nothing when the dataset is already complete."""
    from gac_jax.data.synthetic import generate_dataset

    args = dict(num_frames=4, height=48, width=160, workers=1, progress=True)
    result = generate_dataset(tmp_path / "ds", **args)
    lines = capsys.readouterr().out.splitlines()
    assert result.generated == 4
    first = lines[0]
    assert first.startswith("generating the embedded dataset (4 frames, 48x160, rigs kitti) into ")
    assert str(tmp_path / "ds") in first
    found = re.search(r": about .* \((\d+\.\d+) s per frame measured, 1 at a time\)", first)
    seconds = float(found.group(1))
    assert seconds == pytest.approx(result.frame_seconds[0], abs=0.006)
    assert lines[-1].startswith("synthetic KITTI: 4/4 frames (100%)")
    assert len(lines) == 5  # the announcement and a line per frame (each is >= 10 %)
    assert generate_dataset(tmp_path / "ds", **args).generated == 0
    assert not capsys.readouterr().out
