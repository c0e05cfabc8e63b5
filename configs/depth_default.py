"""Default depth config: the embedded generated dataset, sized for a 2-core CPU.

    python train.py --task depth            # generates the dataset on first use

Trains a small ground-aware depth U-Net (ResNet-34 encoder of base width 32, 96x320 input:
the bottom 352 rows resized to 96, a random 320-column crop; both views of every training
frame, photometric distortion, mirroring) for 5 epochs on the ``depth/`` folders of the
embedded KITTI-format scenes (``data.source='synthetic'``: the detector's default frames
without its randomized car paint, a cache folder of their own generated on first use), then
evaluates itself on the left views of the generated val split: KITTI depth metrics, 16-bit
PNGs and pictures under ``WORKDIR/results/step_N``. Evaluation sees the whole width
(``eval_width`` 352 covers the 339 resized columns). Compare with the ground-plane and
row-mean baselines and the Base U-Net::

    python evaluate.py --task depth --baseline ground-plane --workdir WORKDIR
    python evaluate.py --task depth --baseline row-mean --workdir WORKDIR
    python train.py --task depth --config configs/depth_default.py:base

Variants: ``:tiny`` (tests, seconds), ``:base`` (no GAC, the "Base U-Net"), ``:multirig`` (the
embedded dataset of eight camera rigs, two held out into split ``val_heldout``; each frame's
ground plane in ``depth/planes/``, given to the GAC), ``:fixedplane`` (ignore the frames'
plane files: the GAC gets the level plane ``model.gac.camera_height`` = 1.65 m below the
camera, as without files). The multi-rig ground-plane comparison::

    python train.py --task depth --config configs/depth_default.py:multirig,base
    python train.py --task depth --config configs/depth_default.py:multirig
    python train.py --task depth --config configs/depth_default.py:multirig,fixedplane
    python evaluate.py --task depth --workdir WORKDIR --split val_heldout
"""

from __future__ import annotations

import ml_collections

from gac_jax.config import REPO_CONFIGS, load_config


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
    c = load_config(str(REPO_CONFIGS / "depth_kitti.py"))
    c.data.source = "synthetic"
    c.data.synthetic.num_frames = 1000  # the detector's frames, no randomized car paint
    c.data.synthetic.seed = 0
    c.data.synthetic.val_fraction = 0.3
    c.data.train_views = "both"
    c.data.crop_height = 352
    c.data.height = 96
    c.data.width = 320
    c.data.eval_width = 352
    c.data.batch_size = 8
    c.data.num_workers = 2
    c.data.eval_batch_size = 8
    c.model.encoder_depth = 34
    c.model.encoder_width = 32
    c.data.val_cameras = (2,)  # left views: half the evaluation time
    # other cameras' tone curves, white balance, blur, noise and JPEG (data/camera_effects.py)
    c.data.camera_effects = True
    # with it, contrast and sharpening (each on a share of the images): the generated world is
    # softer than a real camera's (data/camera_effects.py)
    c.data.sharpen_contrast = False
    c.data.sharpen_contrast_share = 0.8  # of the images, each
    c.data.contrast_range = (1.0, 1.8)  # gain on the difference from the image mean
    c.data.sharpen_range = (0.5, 2.0)  # unsharp mask amount
    c.train.num_epochs = 5
    c.train.learning_rate = 4e-4
    c.train.final_learning_rate = 4e-5
    c.train.log_every = 20
    c.train.checkpoint_every = 200

    variants = set((arg or "").split(",")) - {""}
    if "tiny" in variants:
        c.data.synthetic.num_frames = 16
        c.data.synthetic.height = 188
        c.data.synthetic.width = 621
        c.data.crop_height = 176
        c.data.height = 64
        c.data.width = 224
        c.data.eval_width = 256
        c.data.batch_size = 2
        c.data.eval_batch_size = 2
        c.data.num_workers = 0
        c.model.encoder_depth = 18
        c.model.encoder_width = 8
        c.train.num_epochs = 1
        c.train.log_every = 1
        c.train.checkpoint_every = 2
        c.eval.num_pictures = 1
    if "base" in variants:
        c.model.use_gac = False
    if "multirig" in variants:  # eight camera rigs, two held out (split val_heldout)
        c.data.synthetic.rigs = "multi"
        c.data.synthetic.val_fraction = 0.2
    if "fixedplane" in variants:  # the level plane of model.gac.camera_height everywhere
        c.data.use_planes = False
    known = ("tiny", "base", "multirig", "fixedplane")
    unknown = variants - set(known)
    if unknown:
        raise ValueError(f"unknown variants {sorted(unknown)} (known: {', '.join(known)})")
    return c
