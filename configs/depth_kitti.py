"""The paper's KITTI setup for the ground-aware depth U-Net (ResNet-34, 352x1216, batch 8).

Command (``ROOT`` = a KITTI-depth root: ``data_depth_annotated/{train,val}`` and the raw
drives under ``raw/<date>/``)::

    python train.py --task depth --config configs/depth_kitti.py --workdir runs/depth_kitti \\
        data.root=ROOT model.pretrained_backbone=/data/resnet34_flax \\
        data.val_selection=ROOT/depth_selection/val_selection_cropped

``model.pretrained_backbone`` is an ImageNet ResNet-34 converted with ``python -m
gac_jax.weights.convert torchvision-resnet --depth 34 resnet34-b627a593.pth OUT`` (the paper starts
from a pretrained encoder). Without ``data.val_selection`` the run evaluates on every
annotated frame of ``data_depth_annotated/val``. Test-server PNGs::

    python evaluate.py --task depth --workdir runs/depth_kitti \\
        --data ROOT/depth_selection/test_depth_prediction_anonymous --out submission/

Setup: Adam 1e-4, gradient clipping 1.0, cosine stepped per epoch to 1e-5 over 8 epochs
(reference_impl.md 7.4), scale-invariant loss lambda = 0.3 and edge-aware smoothness
alpha = 0.3 on all three output scales (the paper), bottom 352 rows, random 1216-column crop,
photometric distortion and mirroring in training; the left 1216 columns at test time. An
epoch visits every training frame once, as its left or right view drawn at random (the
reference's dataset). The GAC gets the input's projection at each map's true stride.

Variants: ``:base`` - no GAC (the paper's "Base U-Net"); ``:reference`` - the released code:
DCNv2 second decoder conv, the reference's GAC intrinsics (K scaled twice, translation
dropped), its loss options (no smoothness, edge sharpness 20) and no photometric distortion.

Expected (paper, KITTI depth *test* server): SILog 12.13, sqErrorRel 2.61 %, absErrorRel
9.41 %, iRMSE 12.65 1/km; Base U-Net 12.78 / 3.11 % / 10.12 % / 13.46. A reference retrain
scored SILog 9.38, absRel 6.33 %, sqRel 1.14 %, iRMSE 7.21 on val_selection_cropped
(reference_impl.md 9, issue #66).
"""

from __future__ import annotations

import ml_collections

from gac_jax.builders.datasets import synthetic_config
from gac_jax.depth.depth_loss import PAPER_LOSS_OPTIONS, REFERENCE_LOSS_OPTIONS


def _loss(options) -> ml_collections.ConfigDict:
    return ml_collections.ConfigDict(
        {
            **{k: v for k, v in options.items() if k != "scale_weights"},
            "scale_weights": dict(options["scale_weights"]),
        }
    )


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
    c = ml_collections.ConfigDict()
    c.seed = 0

    c.data = ml_collections.ConfigDict()
    c.data.source = "kitti"  # 'kitti' (KITTI-depth root or prepared TFDS) | 'synthetic'
    c.data.root = ""
    # The embedded dataset (data.source='synthetic'): the detector's cache, its ROOT/depth.
    c.data.synthetic = synthetic_config()  # used with data.source='synthetic'
    # Each frame's planes/<drive>/<frame>.txt ground plane where it has one (KITTI-depth has
    # none; the multi-rig embedded dataset has); False: always the level plane of
    # model.gac.camera_height (the fixed-height arm of the ground-plane comparison)
    c.data.use_planes = True
    c.data.train_split = "train"
    c.data.val_split = "val"
    c.data.val_selection = ""  # a depth_selection folder to evaluate on instead of val_split
    c.data.train_cameras = (2, 3)
    c.data.val_cameras = (2, 3)
    c.data.train_views = "random"  # 'random': one view per frame and epoch | 'both': two items
    c.data.crop_height = 352  # keep the bottom rows
    c.data.height = 352  # network input rows (< crop_height: resize, aspect kept)
    c.data.width = 1216  # training crop width (random offset)
    c.data.eval_width = 1216  # test-time width (left columns; zero-padded when narrower)
    c.data.flip_prob = 0.5
    c.data.photometric = True
    # share of the training images given random cast shadows (data/cast_shadows.py); 0 = off
    c.data.cast_shadows = 0.0
    # share of the training images filtered by a random convolution (data/random_convolution.py)
    c.data.random_convolution = 0.0
    c.data.batch_size = 8  # global batch
    c.data.num_workers = 4
    c.data.eval_batch_size = 4

    c.model = ml_collections.ConfigDict()
    c.model.encoder_depth = 34
    c.model.encoder_width = 64
    c.model.pretrained_backbone = ""  # a converted ImageNet ResNet-34
    c.model.use_gac = True
    c.model.decoder_conv = "plain"  # 'plain' (paper) | 'deformable' (reference DCNv2)
    c.model.intrinsics_mode = "correct"  # 'correct' | 'reference' (K scaled twice)
    c.model.decoder_features = ()  # () = (4w, w, w)
    c.model.prior_max_frames = 2000  # training GT maps averaged for prior_mean (0 = all)
    # the residual's base: 'mean' (prior_mean, the reference) | 'ground_plane' (the road's
    # depth at every pixel through the frame's P and ground plane, prior_max_depth above it)
    c.model.output_prior = "mean"
    c.model.prior_max_depth = 75.0
    c.model.gac = ml_collections.ConfigDict(
        dict(baseline=0.54, camera_height=1.65, object_height=1.535, offset_formula="paper")
    )

    c.loss = _loss(PAPER_LOSS_OPTIONS)

    c.train = ml_collections.ConfigDict()
    c.train.num_epochs = 8
    c.train.num_steps = 0  # > 0 overrides num_epochs
    c.train.learning_rate = 1e-4
    c.train.final_learning_rate = 1e-5
    c.train.per_epoch_schedule = True  # reference: CosineAnnealingLR stepped per epoch
    c.train.warmup_steps = 0
    c.train.clip_norm = 1.0
    c.train.weight_decay = 0.0
    c.train.log_every = 50
    c.train.checkpoint_every = 2000
    c.train.keep_checkpoints = 3
    c.train.eval_every = 0  # steps; 0 = only at the end (reference: every 2 epochs)
    c.train.eval_max_batches = 0  # 0 = the whole split
    c.train.eval_at_end = True
    # 'bfloat16': convolutions and activations in bfloat16 (GPU/TPU), parameters, optimizer
    # state, BatchNorm statistics and the loss in float32; checkpoints resume either way
    c.train.compute_dtype = "float32"
    # (start, count): a jax.profiler trace of those steps into WORKDIR/tensorboard (None: off)
    c.train.profile_steps = None

    c.eval = ml_collections.ConfigDict()
    c.eval.num_pictures = 4  # val frames drawn at each evaluation
    c.eval.picture_max_depth = 80.0  # far end of the pictures' colour scale (m)

    c.log = ml_collections.ConfigDict()
    # TensorBoard event files in WORKDIR/tensorboard beside metrics.jsonl (scalars of every
    # logged step and evaluation, evaluation pictures): tensorboard --logdir workdirs
    c.log.tensorboard = True

    variants = set((arg or "").split(",")) - {""}
    if "base" in variants:
        c.model.use_gac = False
    if "reference" in variants:
        c.model.decoder_conv = "deformable"
        c.model.intrinsics_mode = "reference"
        c.loss = _loss(REFERENCE_LOSS_OPTIONS)
        c.data.photometric = False
    unknown = variants - {"base", "reference"}
    if unknown:
        raise ValueError(f"unknown variants {sorted(unknown)} (known: base, reference)")
    return c
