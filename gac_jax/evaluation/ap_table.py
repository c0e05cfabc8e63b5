"""The report of a KITTI detection result (:func:`gac_jax.evaluation.kitti_object.
evaluate_detections`): the printed AP table and the minimum overlaps behind each entry."""

from __future__ import annotations

from gac_jax.evaluation.kitti_object import CLASSES, MIN_OVERLAPS, iou_key


def overlap_meta(result: dict) -> dict:
    """The minimum overlaps behind each entry of an :func:`evaluate_detections` result.

    Entries are keyed by their bev/3d overlap only; the loose setting keeps the
    2D box (and so AOS) overlap at the strict value, as the devkit port, mmdet3d
    and papers do. Returns ``{class: {iou_key: {"setting": "strict"|"loose",
    "bbox"|"aos"|"bev"|"3d": min_overlap}}}`` for the classes in ``result``.
    """
    classes = {cls for ap in ("ap11", "ap40") for cls in result.get(ap, {})}
    meta: dict = {}
    for cls in (c for c in CLASSES if c in classes):
        meta[cls] = {}
        for name, (bbox, bev, d3) in zip(("strict", "loose"), MIN_OVERLAPS[cls], strict=True):
            entry = {"setting": name, "bbox": bbox, "aos": bbox, "bev": bev, "3d": d3}
            meta[cls][iou_key(bev)] = entry
    return meta


def format_table(result: dict) -> str:
    """Readable table of :func:`evaluate_detections` output: class x difficulty per metric."""
    lines = []
    for ap_key, title in (("ap40", "AP|R40"), ("ap11", "AP|R11")):
        if ap_key not in result:
            continue
        lines.append(f"{'KITTI ' + title + ' (%)':<34}{'Easy':>9}{'Moderate':>10}{'Hard':>9}")
        for cls, settings in result[ap_key].items():
            strict_bbox = MIN_OVERLAPS[cls][0][0] if cls in MIN_OVERLAPS else None
            for key, entry in settings.items():
                bbox_thr = f"{strict_bbox:.2f}" if strict_bbox is not None else "?"
                lines.append(f"{cls} @ bbox {bbox_thr}, bev/3d {key}")
                for metric in ("bbox", "bev", "3d", "aos"):
                    vals = entry.get(metric)
                    if vals is None:
                        continue
                    lines.append(f"  {metric:<32}" + "".join(f"{v:>9.2f} " for v in vals).rstrip())
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"
