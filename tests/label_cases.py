"""Hand-made KITTI label and result lines for the tests of false-positive counts, the operating
point (test_operating_point) and the real-frame benchmark's box medians
(test_real_frames_benchmark)."""

from __future__ import annotations

from gac_jax.data.kitti import KittiObjects, parse_label


def label_line(kind: str, box, z: float = 20.0, score: float | None = None) -> str:
    """One KITTI line of class ``kind`` with 2D box ``box`` (xyxy) at depth ``z``; a result
    line (with its score) when ``score`` is given."""
    x0, y0, x1, y1 = box
    s = f"{kind} 0 0 0 {x0} {y0} {x1} {y1} 1.5 1.6 3.9 0 1.6 {z} 0"
    return s if score is None else f"{s} {score}"


def objects(lines: list[str], with_score: bool) -> KittiObjects:
    return parse_label("\n".join(lines), with_score=with_score)
