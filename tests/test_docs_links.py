"""Every relative link and image of the README, the changelog and docs/*.md resolves.

A link ``[text](path)`` or image ``![alt](path)`` must name an existing file or folder
(relative to the markdown file); a ``#anchor`` (alone or after a ``.md`` path) must be the
GitHub slug of a heading of that file. Links inside code (fenced blocks, inline code) are not
links and are skipped, as are absolute URLs (``https:``, ``mailto:``).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = sorted([REPO / "README.md", REPO / "CHANGELOG.md", *(REPO / "docs").glob("*.md")])

FENCE = re.compile(r"^(```|~~~)")
INLINE_CODE = re.compile(r"`+[^`]*`+")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
HTML_SRC = re.compile(r"<img\s[^>]*src=\"([^\"]+)\"", re.I)
HEADING = re.compile(r"^ {0,3}(#{1,6})\s+(.*?)\s*#*\s*$")


def prose_lines(text: str):
    """(line number, line) outside fenced code blocks, with inline code removed."""
    fenced = False
    for number, line in enumerate(text.splitlines(), 1):
        if FENCE.match(line.strip()):
            fenced = not fenced
            continue
        if not fenced:
            yield number, INLINE_CODE.sub("", line)


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: the rendered text lower-cased, punctuation other
    than ``-`` and ``_`` dropped, each space a ``-``."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links -> their text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    text = text.lower()
    text = "".join(ch for ch in text if ch.isalnum() or ch in " -_")
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every heading anchor of a markdown file (repeated slugs get -1, -2, ...)."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text().splitlines():
        if FENCE.match(line.strip()):
            fenced = not fenced
            continue
        m = None if fenced else HEADING.match(line)
        if m:
            slug = github_slug(m[2])
            n = seen.get(slug, 0)
            out.add(slug if n == 0 else f"{slug}-{n}")
            seen[slug] = n + 1
    return out


def broken_links(path: Path, root: Path = REPO) -> list[str]:
    """``file:line: target: problem`` (``file`` relative to ``root``) for every link of
    ``path`` that does not resolve."""
    problems = []
    for number, line in prose_lines(path.read_text()):
        for target in [m[1] for m in LINK.finditer(line)] + HTML_SRC.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # https:, mailto:, ...
                continue
            file_part, _, anchor = target.partition("#")
            where = f"{path.relative_to(root).as_posix()}:{number}: {target}"
            dest = (path.parent / file_part).resolve() if file_part else path
            if not dest.exists():
                problems.append(f"{where}: no such file")
                continue
            if anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                problems.append(f"{where}: no heading with this anchor in {dest.name}")
            elif anchor and dest.suffix != ".md":
                problems.append(f"{where}: an anchor into a file that is not markdown")
    return problems


@pytest.mark.parametrize("path", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_links_resolve(path):
    assert broken_links(path) == []


def test_the_docs_are_all_checked():
    names = {p.relative_to(REPO).as_posix() for p in DOCS}
    assert {"README.md", "CHANGELOG.md", "docs/results.md", "docs/ablations.md"} <= names


def test_github_slugs():
    """Slugs as GitHub writes them (checked by hand on rendered pages)."""
    assert github_slug("Deployment: ONNX Runtime and OpenVINO") == (
        "deployment-onnx-runtime-and-openvino"
    )
    assert github_slug(
        "Multi-rig detection: GAC with each frame's ground plane vs the fixed 1.65 m plane "
        "vs a plain conv"
    ) == (
        "multi-rig-detection-gac-with-each-frames-ground-plane-vs-the-fixed-165-m-plane-vs-a-plain-conv"
    )
    assert github_slug("Train in bfloat16, data wait, memory, profiles") == (
        "train-in-bfloat16-data-wait-memory-profiles"
    )
    assert github_slug("The `run_dir` of [a run](x.md)") == "the-run_dir-of-a-run"
    assert github_slug("Depth (Base U-Net vs GAC U-Net)") == "depth-base-u-net-vs-gac-u-net"


def test_the_checker_finds_what_is_broken(tmp_path):
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "images").mkdir()
    (docs / "images" / "a.png").write_bytes(b"png")
    (docs / "other.md").write_text("# Other page\n\n## A section\n\n```\n# not a heading\n```\n")
    page = docs / "page.md"
    page.write_text(
        "# Page\n\n## Same\n\n## Same\n\n"
        "[ok](other.md) [ok](other.md#a-section) [ok](#same-1) ![ok](images/a.png)\n"
        "[ok](https://example.org/x) `[code](missing.md)`\n"
        "```\n[in a block](missing.md)\n```\n"
        "[bad](missing.md) [bad](other.md#not-a-heading) [bad](#same-2)\n"
        '![bad](images/b.png) <img src="images/c.png">\n'
    )
    found = broken_links(page, root=tmp_path)
    assert [p.split(": ")[1] for p in found] == [
        "missing.md",
        "other.md#not-a-heading",
        "#same-2",
        "images/b.png",
        "images/c.png",
    ]
    assert all(p.startswith("docs/page.md:") for p in found)
