"""What the ablation report says about its rows: the paper's numbers and each row's change.

Data only (no JAX), shared by :mod:`gac_jax.cli.ablations.report` (the tables) and the tests
(which check the paper numbers against the paper's source).
"""

from __future__ import annotations

import re

# Paper Table 3 ("3D Detection Ablation Study Results of Car on KITTI Validation Set",
# paper_gac.tex, tab:ablation_study), 3D AP|R40 easy / moderate / hard in %.
PAPER_TABLE3 = {
    "baseline": {"3D@0.7": (23.63, 16.16, 12.06), "3D@0.5": (60.92, 42.18, 32.02)},
    "nofilter": {"3D@0.7": (21.39, 14.35, 11.11), "3D@0.5": (59.76, 41.00, 31.10)},
    "ohem": {"3D@0.7": (22.45, 15.10, 11.29), "3D@0.5": (60.71, 42.01, 31.88)},
    "conv": {"3D@0.7": (21.57, 15.26, 11.35), "3D@0.5": (58.17, 41.17, 32.58)},
    "disparity": {"3D@0.7": (22.13, 15.42, 11.34), "3D@0.5": (60.13, 41.62, 33.07)},
    "deformable": {"3D@0.7": (22.16, 15.71, 11.75), "3D@0.5": (62.24, 43.93, 33.76)},
}
PAPER_TABLE3_NAMES = {
    "baseline": "Baseline Model",
    "nofilter": "w/o Anchor Filtering",
    "ohem": "w OHEM",
    "conv": "w Conv",
    "disparity": "w DisparityConv",
    "deformable": "w Deformable Conv",
}
# Paper depth table (tab:depth_validation_results, KITTI depth val).
PAPER_DEPTH = {
    "base": {"silog": 12.78, "sq_rel": 3.11, "abs_rel": 10.12, "irmse": 13.46},
    "gac": {"silog": 12.13, "sq_rel": 2.61, "abs_rel": 9.41, "irmse": 12.65},
}
PAPER_DEPTH_NAMES = {"base": "Base U-Net", "gac": "Ours"}


VARIANTS_TEXT = """## The rows

Detection rows are variants of `configs/detect3d_default.py` (the same names work on
`configs/detect3d_kitti.py`, e.g. `configs/detect3d_kitti.py:ohem`):
"""

VARIANT_ROWS = (
    (
        "baseline",
        "nothing: ground-aware convolution (GAC) in the regression branch, ground-plane anchor "
        "filter in training and at test",
    ),
    ("nofilter", "`anchors.filter=False`: every anchor is used in training and at test"),
    (
        "ohem",
        "no ground-plane filter; in training, per image, the easiest half of the negative "
        "anchors leaves the loss (`loss.ohem_drop_fraction=0.5`); no filter at test",
    ),
    ("conv", "GAC replaced by conv3x3 C->C + ReLU"),
    ("disparity", "GAC replaced by conv3x3 over [disparity prior map, features] (C+1 -> C) + ReLU"),
    (
        "deformable",
        "GAC replaced by a modulated deformable conv v2 3x3 C->C + ReLU "
        "(`gac_jax/models/deformable_conv.py`): per-pixel tap offsets and masks from a "
        "zero-initialised 3x3 conv as in DCNv2, so it starts as half a plain conv",
    ),
    (
        "fixedplane",
        "the `baseline` model, but the frames' `planes/` files are ignored "
        "(`data.use_planes=False`): GAC, the anchor filter and the export get the level plane "
        "1.65 m below the camera, as in the paper and the authors' code (only differs from "
        "`baseline` on data that carries planes, e.g. `:multirig`)",
    ),
)
VARIANTS_TEXT += "\n| row | paper Table 3 | what changes |\n|---|---|---|\n" + "".join(
    f"| `{row}` | {PAPER_TABLE3_NAMES.get(row, '-')} | {text} |\n" for row, text in VARIANT_ROWS
)
VARIANTS_TEXT += """
OHEM exactly (`gac_jax/detection/detection_loss.py`, `ohem_negative_mask`): the paper says only "we
filter out half of the easy negative anchors during training". Here, per image `j`, after
the usual assignment (positive at IoU >= 0.5, negative below 0.4, ignored between), the
`floor(0.5 * num_neg_j)` negatives with the lowest classification loss (the focal loss of the
anchor summed over classes, computed before the reference's zeroing of losses below 1e-5;
among equal losses the lower anchor index goes first) are treated like ignored anchors: they
add nothing to the focal-loss sum and are not counted in the normaliser `num_pos_j +
num_neg_j`, just as anchors removed by the ground filter are not. The selection is per image
(not per batch: the ground filter, which removes about half of the negatives, is per image
too, and a per-image choice does not depend on how a batch is split over devices), it carries
no gradient, and positives, ignored anchors and the regression terms are unchanged. It acts on
top of the focal loss, which already down-weights easy negatives by `p^2`: the dropped half
contributes little loss anyway, so the main effect is the smaller normaliser (about twice the
classification loss per anchor, as with the ground filter) and that the easiest half gives no
gradient at all.

Depth rows: `base` = `configs/depth_default.py:base` (the paper's "Base U-Net", no GAC),
`gac` = `configs/depth_default.py` (the GAC U-Net) and `fixedplane` (the GAC U-Net with the
frames' `planes/` files ignored: the level plane 1.65 m below the camera; only differs from
`gac` on data that carries planes, e.g. `:multirig`).
"""


def paper_table3_from_tex(tex: str) -> dict[str, dict[str, tuple[float, ...]]]:
    """Parses tab:ablation_study of the paper source (to check :data:`PAPER_TABLE3`)."""
    start = tex.index(r"\caption{3D Detection Ablation Study")
    body = tex[start : tex.index(r"\end{tabular*}", start)]
    out = {}
    for row, name in PAPER_TABLE3_NAMES.items():
        line = next(ln for ln in body.splitlines() if name in ln)
        numbers = [float(x) for x in re.findall(r"(\d+\.\d+)", line)]
        out[row] = {"3D@0.7": tuple(numbers[:3]), "3D@0.5": tuple(numbers[3:6])}
    return out
