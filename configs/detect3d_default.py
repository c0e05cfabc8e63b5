"""Default detector config: the embedded generated dataset, sized for a 2-core CPU.

    python train.py --task detect3d            # generates the dataset on first use

Trains a small GAC detector (ResNet-18 trunk of half width, 160x720 input after
cropping the top 100 rows) on the embedded KITTI-format scenes and evaluates itself
on the generated val split, printing the KITTI AP table. Variants (comma-separated):
``tiny`` (tests, seconds) and the rows of the paper's Table 3, as in
``configs/detect3d_kitti.py``: ``baseline`` (= no variant), ``nofilter`` (no ground-plane
anchor filtering), ``ohem`` (no filter; the easiest half of the negatives left out of the
loss), ``conv`` (GAC replaced by a plain conv), ``disparity`` (disparity-conditioned conv),
``deformable`` (modulated deformable conv v2). ``python -m gac_jax.cli.ablations`` runs them all
over several seeds (docs/ablations.md). ``multirig``: the embedded dataset of eight camera
rigs (heights 1.2-2.4 m, pitch -6..+7 deg, other intrinsics and image sizes; two rigs held
out into split ``val_heldout``, evaluate with ``evaluate.py --workdir W --split val_heldout``);
``kittirig`` (with ``multirig``): train on the KITTI-like rig's frames only (cross-rig).
``fixedplane``: ignore the frames' ``planes/`` files (GAC, the anchor filter and the export
get the level plane 1.65 m below the camera, as without files). ``long``: 3,000 generated
frames (2,700 train / 300 val) for 1,750 steps (the earlier default's), at about 11 more minutes
of generation; on generated val and on the real KITTI frames it was no better than the default
of then (docs/results.md "Real KITTI frames"; measured before the randomized car paint joined
the default). ``steps2x``: 3,500 steps on the default's frames (twice the earlier default's
1,750), about 40 minutes of training on 2 cores instead of 24: on generated val and on the real
KITTI frames it transferred better than 1,750 steps (docs/results.md "Real KITTI frames").
``long`` and ``steps2x`` train at the learning rate they were measured with (4e-4 to 4e-5). The
default trains 2,100 steps, the most that fit the first run's 30 minutes, at twice that rate.
The default's frames give 70 % of the cars of half the frames a random paint
(``data.synthetic.randomize_cars``); ``tiny`` and ``multirig`` leave it out.
"""

from __future__ import annotations

import math
from pathlib import Path

import ml_collections

from gac_jax.config import load_config


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
    variants = set((arg or "").split(",")) - {""}
    # Everything but 'tiny' is a variant of the KITTI config (the Table 3 rows, multiclass);
    # none of the settings below touches what those variants set.
    local = {"tiny", "multirig", "kittirig", "fixedplane", "long", "steps2x"}
    passed = sorted(variants - local)
    try:
        c = load_config(str(Path(__file__).with_name("detect3d_kitti.py")) + ":" + ",".join(passed))
    except ValueError as e:
        raise ValueError(f"{e} (or {', '.join(sorted(local))} here)") from None
    c.data.source = "synthetic"
    c.data.synthetic.num_frames = 1000
    c.data.synthetic.seed = 0
    c.data.synthetic.val_fraction = 0.3  # 700 train / 300 val frames
    # random paint, glass tint and tyre shades on 70 % of the cars of half the frames
    # (data/synthetic/domain_randomization.py): on the real KITTI frames it raised Car 2D AP
    # at IoU 0.7 and 3D AP for each of three seeds (docs/results.md "Real KITTI frames")
    c.data.synthetic.randomize_cars = 0.5
    c.data.use_right_image = True
    c.data.crop_top = 100
    c.data.height = 160
    c.data.width = 720
    c.data.reproject_boxes = False  # 2D targets = the labelled boxes, as evaluated
    # other cameras' tone curves, white balance, blur, noise and JPEG (data/camera_effects.py),
    # besides the reference's photometric distortion: for frames of real cameras
    c.data.camera_effects = True
    # with it, contrast and sharpening (each on a share of the images): the generated world is
    # softer than a real camera's (data/camera_effects.py); on the real KITTI frames this
    # doubled Car 2D AP at IoU 0.5 and cut the false positives (docs/results.md)
    c.data.sharpen_contrast = True
    c.data.sharpen_contrast_share = 0.8  # of the images, each
    c.data.contrast_range = (1.0, 1.8)  # gain on the difference from the image mean
    c.data.sharpen_range = (0.5, 2.0)  # unsharp mask amount
    c.data.batch_size = 8
    c.data.num_workers = 2
    c.data.eval_batch_size = 8
    c.anchors.base_size = 13.3  # 24 px at 288 rows, scaled to 160 rows
    c.anchors.sign_axis = math.pi / 4  # no sign-bit ambiguity for cars seen from behind
    c.loss.match_low_quality = True  # small far cars get their best anchor as a positive
    c.model.backbone_depth = 18
    c.model.backbone_width = 32
    c.model.cls_features = 128
    c.model.reg_features = 128
    c.train.num_epochs = 12  # 2,100 steps of 8: the most that fits the first run's 30 minutes
    # twice the rate of the earlier default (4e-4 to 4e-5): in the same steps, generated val
    # 2D AP up 3-6 points and real Car 2D AP at IoU 0.5 up for each of three seeds
    # (docs/results.md "Real KITTI frames")
    c.train.learning_rate = 8e-4
    c.train.final_learning_rate = 8e-5
    c.train.clip_norm = 1.0
    c.train.log_every = 20
    c.train.checkpoint_every = 200
    c.eval.score_threshold = 0.5  # AP needs the low-scoring boxes
    # a camera runs at the operating point the final evaluation records on val: best F0.5, which
    # weighs precision twice as much as recall. This detector of the generated world makes more
    # false boxes per frame on real KITTI frames than on its generated val; at F0.5's threshold
    # (0.75-0.80 for three seeds) it makes 0.2-0.6 there instead of 1.1-3.0 at F1's (0.65-0.70),
    # and finds 11-13 of the 32 real cars instead of 15-16 (docs/results.md "Real KITTI frames")
    c.eval.deploy_threshold = "operating_point"
    c.eval.operating_point_beta = 0.5

    if "kittirig" in variants and "multirig" not in variants:
        raise ValueError("variant 'kittirig' needs 'multirig' (e.g. :multirig,kittirig)")
    if "multirig" in variants:
        c.data.synthetic.rigs = "multi"
        c.data.synthetic.randomize_cars = 0.0  # the eight rigs' frames as measured
        c.data.synthetic.val_fraction = 0.2  # of the training rigs; held-out rigs: val_heldout
    if "kittirig" in variants:
        c.data.train_split = "train_kitti_rig"
    if "fixedplane" in variants:
        c.data.use_planes = False
    if "long" in variants or "steps2x" in variants:
        c.train.learning_rate = 4e-4  # the rate they were measured with
        c.train.final_learning_rate = 4e-5
    if "long" in variants:  # more frames, the same steps
        c.data.synthetic.num_frames = 3000
        c.data.synthetic.val_fraction = 0.1
        c.train.num_steps = 1750
    if "steps2x" in variants:  # the same frames, 3,500 steps of 8 (twice the earlier 1,750)
        c.train.num_epochs = 20
        c.train.num_steps = 2 * c.train.num_steps  # (0: from the epochs)

    if "tiny" in variants:
        c.data.synthetic.num_frames = 16
        c.data.synthetic.randomize_cars = 0.0  # the cache the depth config's 'tiny' shares
        c.data.synthetic.height = 188
        c.data.synthetic.width = 621
        c.data.crop_top = 50
        c.data.height = 64
        c.data.width = 256
        c.data.batch_size = 2
        c.data.eval_batch_size = 2
        c.data.num_workers = 0
        c.anchors.base_size = 12.0
        c.anchors.prior_min_count = 1
        c.model.backbone_width = 8
        c.model.cls_features = 16
        c.model.reg_features = 16
        c.train.num_epochs = 1
        c.train.learning_rate = 4e-4  # the tests' few steps were tuned at this rate
        c.train.final_learning_rate = 4e-5
        c.train.log_every = 1
        c.train.checkpoint_every = 2
        c.eval.hill_climbing = False
        c.eval.top_k = 20
        c.eval.deploy_threshold = "score_threshold"  # tests set eval.score_threshold
    return c
