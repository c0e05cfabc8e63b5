"""What the ground-plane anchor filter keeps per camera rig: the frame's plane vs a fixed one.

For a trained detection workdir (its anchors and priors, its eval transform) and each split,
every frame's anchors are filtered twice, with the frame's own ground plane (``planes/``
files) and with the level plane of ``model.gac.camera_height`` (what ``:fixedplane`` and the
authors' code use), and grouped by the frame's camera height and pitch (from its plane).
Reported per group: frames, the share of anchors kept (of those with a valid prior), and the
recall ceiling: the share of ground-truth Cars that keep at least one anchor of 2D IoU > 0.5
(a car without one cannot be detected, whatever the network predicts).

    python benchmarks/anchor_filter_rigs.py --workdir W [--splits val,val_heldout] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.builders import detect3d as det_builders  # noqa: E402
from gac_jax.builders.datasets import prepare_dataset  # noqa: E402
from gac_jax.data.loader import DetectionArrays, Loader  # noqa: E402
from gac_jax.data.sources import open_object_source  # noqa: E402
from gac_jax.detection.anchor_filter import ground_mask_from_constants  # noqa: E402
from gac_jax.detection.anchor_priors import make_detection_constants  # noqa: E402
from gac_jax.detection.anchors import box_iou_np, generate_anchors  # noqa: E402
from gac_jax.trained.run_config import load_run_config  # noqa: E402

MATCH_IOU = 0.5


HEIGHT_BINS = (1.2, 1.5, 1.8, 2.1, 2.5)  # m
PITCH_BINS = (-8.0, -2.0, 2.0, 8.0)  # deg, positive: camera pitched down


def rig_key(plane: np.ndarray) -> str:
    """The camera-height and pitch bin of a unit-normal plane ``(a, b, c, d)`` (``d`` the
    height; the normal is ``(0, -cos p, -sin p)`` for a camera pitched down by ``p``)."""
    _, b, c, d = (float(x) for x in plane)
    pitch = float(np.degrees(np.arctan2(-c, -b)))

    def bin_of(x, edges, unit):
        i = int(np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2))
        return (
            f"{edges[i]:+g}..{edges[i + 1]:+g} {unit}"
            if unit == "deg"
            else (f"{edges[i]:g}-{edges[i + 1]:g} {unit}")
        )

    return f"{bin_of(d, HEIGHT_BINS, 'm')}, {bin_of(pitch, PITCH_BINS, 'deg')}"


def analyse(config, root: Path, constants, split: str) -> dict:
    """``{group: {frames, cars, kept_own, kept_fixed, cars_own, cars_fixed,
    cars_unfiltered}}`` for the rig bins of ``split`` and ``'all'`` (shares in [0, 1])."""
    source = open_object_source(root, split, use_right_image=False)
    arrays = DetectionArrays(
        tuple(config.data.classes), config.data.max_objects, True, config.model.gac.camera_height
    )
    transform = det_builders.eval_transform(config)
    loader = Loader(
        source, transform, arrays, batch_size=8, shuffle=False, drop_remainder=False, num_epochs=1
    )
    options = det_builders.filter_options(config)
    boxes = np.asarray(constants.anchor_boxes)
    valid = np.asarray(constants.prior_valid).any(axis=0)
    groups = defaultdict(lambda: defaultdict(float))
    for batch in loader.iterate():
        own = np.asarray(
            ground_mask_from_constants(constants, batch["P2"], batch["plane"], **options)
        )
        fixed = np.asarray(ground_mask_from_constants(constants, batch["P2"], None, **options))
        for i in range(len(own)):
            gt = batch["gt_boxes"][i][batch["gt_mask"][i]]
            hit = (box_iou_np(boxes, gt) > MATCH_IOU) & valid[:, None]  # (N anchors, G cars)
            for g in (groups[rig_key(batch["plane"][i])], groups["all"]):
                g["frames"] += 1
                g["kept_own"] += own[i].sum() / max(valid.sum(), 1)
                g["kept_fixed"] += fixed[i].sum() / max(valid.sum(), 1)
                g["cars"] += len(gt)
                g["cars_own"] += (hit & own[i][:, None]).any(axis=0).sum()
                g["cars_fixed"] += (hit & fixed[i][:, None]).any(axis=0).sum()
                g["cars_any"] += hit.any(axis=0).sum()
    out = {}
    for key in sorted(groups, key=lambda k: (k == "all", k)):
        g = groups[key]
        n, cars = g["frames"], max(g["cars"], 1)
        out[key] = {
            "frames": int(n),
            "cars": int(g["cars"]),
            "kept_own": g["kept_own"] / n,
            "kept_fixed": g["kept_fixed"] / n,
            "cars_own": g["cars_own"] / cars,
            "cars_fixed": g["cars_fixed"] / cars,
            "cars_unfiltered": g["cars_any"] / cars,
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workdir", required=True, help="a trained detection workdir")
    parser.add_argument("--splits", default="val", help="comma-separated (default: val)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    print(one_line(describe_machine("numpy")))
    workdir = Path(args.workdir)
    config = load_run_config(workdir)
    root = prepare_dataset(config.data)
    layout = det_builders.anchor_layout(config)
    priors = det_builders.compute_priors(config, root, layout, workdir)  # cached in the workdir
    constants = make_detection_constants(generate_anchors(layout), priors)
    result = {}
    for split in args.splits.split(","):
        rows = result[split] = analyse(config, root, constants, split)
        print(f"\nsplit {split}: anchors kept (of valid) and Cars with a kept anchor, own / fixed")
        print(
            f"{'rig (height, pitch down)':28s} {'frames':>6s} {'cars':>5s} "
            f"{'anchors kept':>15s} {'cars w/ anchor':>15s} {'no filter':>9s}"
        )
        for key, r in rows.items():
            print(
                f"{key:28s} {r['frames']:6d} {r['cars']:5d} "
                f"{r['kept_own']:7.1%} {r['kept_fixed']:7.1%} "
                f"{r['cars_own']:7.1%} {r['cars_fixed']:7.1%} {r['cars_unfiltered']:9.1%}"
            )
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
