"""The depth trainer: compile-once step that learns, resume == uninterrupted, NaN stop, the
cached prior mean, and ``evaluate.py --task depth --workdir`` end to end.

Runs the ``:tiny`` default config (ResNet-18 of width 8, 64x224 input) on the real KITTI-depth
frame of ``../shared`` (one frame, both cameras: one batch of 2 per step).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest

from gac_jax import geometry
from gac_jax.builders import depth as depth_builders
from gac_jax.cli import evaluate as cli
from gac_jax.config import apply_overrides, load_config
from gac_jax.data.files import read_depth_png
from gac_jax.data.sources import KittiDepthSource
from gac_jax.evaluation.depth_evaluator import prediction_relpath, to_original_geometry
from gac_jax.trained.depth import restore_depth_model
from gac_jax.trainers import depth
from gac_jax.trainers.common import create_train_state
from gac_jax.training import parallel
from gac_jax.training.checkpointing import Checkpoints

REPO = Path(__file__).resolve().parents[1]
DRIVE = "2011_09_26_drive_0001_sync"
STEPS = 4


def tiny_config(depth_root: Path, *overrides: str):
    config = load_config(str(REPO / "configs" / "depth_default.py:tiny"))
    apply_overrides(
        config,
        [
            "data.source=kitti",
            f"data.root={depth_root}",
            "data.val_split=train",
            "data.val_cameras=(2, 3)",
            "data.crop_height=352",
            f"train.num_steps={STEPS}",
            "train.checkpoint_every=2",
            *overrides,
        ],
    )
    return config


def restore_params(workdir: Path, step: int) -> dict:
    return restore_depth_model(workdir, step)[2]["params"]


@pytest.fixture(scope="module")
def depth_root(kitti_samples) -> Path:
    return kitti_samples / "depth"


@pytest.fixture(scope="module")
def trained(depth_root, tmp_path_factory):
    """One uninterrupted tiny run (checkpoints 2 and 4, evaluation at the end)."""
    workdir = tmp_path_factory.mktemp("depth_run")
    config = tiny_config(depth_root)
    result = depth.train_and_evaluate(config, workdir)
    return workdir, result


def planar_batch(batch_size: int, height: int = 64, width: int = 224) -> dict:
    """Textured images of a flat road (exact ground-plane depth, sparse) under a far wall."""
    rng = np.random.default_rng(0)
    f = 721.5 * height / 352
    P = np.array([[f, 0, width / 2, 0], [0, f, 0.3 * height, 0], [0, 0, 1, 0]], np.float32)
    z = np.minimum(geometry.ground_depth(np.arange(height), P), 60.0)
    depth = np.broadcast_to(z[:, None], (height, width)).astype(np.float32)
    images = rng.normal(0, 0.3, (batch_size, height, width, 3)).astype(np.float32)
    images += (np.log(depth) / 4.0)[None, :, :, None]  # the texture darkens with depth
    keep = rng.random((batch_size, height, width)) < 0.3
    return {  # the loader's depth batch layout (frame ids aside)
        "image": images,
        "P2": np.repeat(P[None], batch_size, 0),
        "plane": np.tile(geometry.level_plane(1.65).astype(np.float32), (batch_size, 1)),
        "depth": np.where(keep, depth[None], 0.0).astype(np.float32),
        "image_transform": np.repeat(np.eye(3, dtype=np.float32)[None], batch_size, 0),
        "original_size": np.full((batch_size, 2), (height, width), np.int32),
    }


def test_train_step_compiles_once_and_learns_a_fixed_batch(depth_root, tmp_path):
    """The trainer's step (its optimizer, its prior, its batch layout) on a fixed planar batch."""
    config = tiny_config(depth_root)
    mesh = parallel.make_mesh(jax.devices()[:1])
    source = depth_builders.train_source(config, depth_root)
    prior = depth.load_or_compute_prior_mean(config, source, tmp_path)
    model = depth_builders.build_model(config, prior)
    _, tx = depth.optimizer(config, total_steps=STEPS, steps_per_epoch=1)
    state, sharding = create_train_state(
        depth_builders.init_variables(model, config, 0), tx, 0, mesh
    )
    step = depth.make_train_step(model, tx, depth_builders.loss_options(config), mesh, sharding)
    host = planar_batch(2)
    losses = []
    for i in range(12):  # the plane is an input: a new one per step compiles nothing new
        plane = host["plane"] + np.float32([0, 0, 0, 0.002 * i])
        batch = parallel.to_global(dict(host, plane=plane), mesh)
        state, metrics = step(state, batch)
        losses.append(float(metrics["loss"]))
    assert step._cache_size() == 1
    assert np.all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.6 * losses[0], losses
    assert float(metrics["valid/scale_1"]) == float((batch["depth"] > 0.1).sum())


def test_run_writes_prior_checkpoints_metrics_and_evaluation(trained, depth_root):
    workdir, result = trained
    with Checkpoints(workdir) as ckpts:
        assert ckpts.all_steps() == [2, 4]
        assert ckpts.restore_meta(4)["prior_mean"] == pytest.approx(
            depth_builders.read_prior_mean(workdir)
        )
    # prior_mean: mean natural log of the valid GT depths of both views (float64 reference).
    source = KittiDepthSource(depth_root, "train", (2, 3))
    logs = np.concatenate(
        [
            np.log(d[(d > 0.1) & (d < 100)].astype(np.float64))
            for d in (read_depth_png(source.layout.groundtruth("train", f)) for f in source.frames)
        ]
    )
    assert depth_builders.read_prior_mean(workdir) == pytest.approx(logs.mean(), rel=1e-12)
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    train = [r for r in records if r["kind"] == "train"]
    assert [r["step"] for r in train] == [1, 2, 3, 4]
    assert {"loss", "si/scale_1", "smooth/scale_8", "grad_norm", "lr"} <= set(train[0])
    assert result["num_frames"] == result["num_scored"] == 2
    assert set(result["metrics"]) >= {"silog", "abs_rel", "irmse", "delta1"}
    step_dir = workdir / "results" / f"step_{STEPS}"
    assert json.loads((step_dir / "metrics.json").read_text())["metrics"] == result["metrics"]
    assert len(list((step_dir / "pictures").glob("*.png"))) == 1
    for cam in (2, 3):
        png = step_dir / "depth" / prediction_relpath(f"{DRIVE}/0000000005", cam)
        assert read_depth_png(png).shape == (375, 1242)


def test_nan_stop_keeps_the_last_good_checkpoint_and_resume_matches(
    trained, depth_root, tmp_path, monkeypatch
):
    """A NaN batch at step 3 stops the run with checkpoint 2 kept; resuming from it (clean
    data) ends at the same parameters as the uninterrupted run."""
    clean_dir, _ = trained
    config = tiny_config(depth_root, "train.eval_at_end=False")
    calls = {"n": 0}
    original = parallel.to_global

    def poisoned(batch, mesh):
        calls["n"] += 1
        if calls["n"] == 3:
            batch = dict(batch, image=np.full_like(batch["image"], np.nan))
        return original(batch, mesh)

    monkeypatch.setattr(depth.parallel, "to_global", poisoned)
    with pytest.raises(depth.NonFiniteLossError, match="non-finite loss at step 3"):
        depth.train_and_evaluate(config, tmp_path)
    with Checkpoints(tmp_path) as ckpts:
        assert ckpts.latest_step() == 2
    assert all(np.isfinite(x).all() for x in jax.tree.leaves(restore_params(tmp_path, 2)))

    monkeypatch.setattr(depth.parallel, "to_global", original)
    depth.train_and_evaluate(config, tmp_path)
    a, b = restore_params(tmp_path, STEPS), restore_params(clean_dir, STEPS)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-7)
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in records if r["kind"] == "train"] == [1, 2, 3, 4]  # one history


def test_evaluate_cli_runs_the_trained_model_on_the_real_frame(trained, depth_root, tmp_path):
    workdir, result = trained
    out = tmp_path / "eval"
    code = cli.main(
        [
            "--task",
            "depth",
            "--workdir",
            str(workdir),
            "--out",
            str(out),
            "--json",
            str(tmp_path / "r.json"),
        ]
    )
    assert code == 0
    cli_result = json.loads((tmp_path / "r.json").read_text())
    assert cli_result["step"] == STEPS and cli_result["num_scored"] == 2
    assert cli_result["metrics"] == pytest.approx(result["metrics"], rel=1e-12)

    # The PNGs decode to the network's prediction (to 1/256 m) at the original size.
    config, model, variables, _ = restore_depth_model(workdir)
    sample = dict(KittiDepthSource(depth_root, "train", (2,))[0])
    sample = depth_builders.eval_transform(config)(sample)
    log_depth = jax.jit(lambda v, x, P: model.apply(v, x, P, train=False))(
        variables, sample["image"][None], sample["P2"][None]
    )
    expected = to_original_geometry(
        np.asarray(log_depth["log_depth"]["scale_1"][0]), sample["image_transform"], (375, 1242)
    )
    written = read_depth_png(out / "depth" / prediction_relpath(f"{DRIVE}/0000000005", 2))
    assert written.shape == (375, 1242)
    np.testing.assert_array_less(np.abs(written - expected), 1 / 512 + 1e-5 * expected)

    # Re-scored offline from the PNGs: the same numbers.
    gt_dir = depth_root / "data_depth_annotated" / "train"
    metrics, count = cli.evaluate_depth_folders(gt_dir, out / "depth")
    assert count == 2 and metrics == pytest.approx(cli_result["metrics"], rel=1e-12)


def test_configs_build_the_paper_base_and_reference_models(depth_root):
    paper = load_config(str(REPO / "configs" / "depth_kitti.py"))
    assert (paper.data.height, paper.data.width, paper.data.batch_size) == (352, 1216, 8)
    assert (paper.train.learning_rate, paper.train.final_learning_rate) == (1e-4, 1e-5)
    assert (paper.train.num_epochs, paper.train.clip_norm) == (8, 1.0)
    model = depth_builders.build_model(paper, 2.5)
    assert (model.depth, model.width, model.use_gac, model.decoder_conv) == (34, 64, True, "plain")
    opts = depth_builders.loss_options(paper)
    assert (opts["si_lambda"], opts["smooth_weight"], opts["edge_sharpness"]) == (0.3, 0.3, 1.0)
    assert not depth_builders.build_model(
        load_config(f"{REPO}/configs/depth_kitti.py:base"), 2.5
    ).use_gac
    ref = load_config(str(REPO / "configs" / "depth_kitti.py:reference"))
    model = depth_builders.build_model(ref, 2.5)
    assert (model.decoder_conv, model.intrinsics_mode) == ("deformable", "reference")
    assert depth_builders.loss_options(ref)["smooth_weight"] == 0.0 and not ref.data.photometric
    default = load_config(str(REPO / "configs" / "depth_default.py"))
    assert default.data.source == "synthetic" and default.data.train_views == "both"
    with pytest.raises(ValueError, match="unknown variants"):
        load_config(str(REPO / "configs" / "depth_default.py:nope"))

    # 'random' views: one item per frame and epoch, on the paper's 352x1216 crop.
    paper.data.root, paper.data.num_workers = str(depth_root), 0
    source = depth_builders.train_source(paper, depth_root)
    mesh = parallel.make_mesh(jax.devices()[:1])
    loader = depth.make_train_loader(paper, source, per_process_batch=1, mesh=mesh)
    assert len(source) == 2 and loader.steps_per_epoch == 1
    batch = loader.load_batch(0)
    assert batch["image"].shape == (1, 352, 1216, 3) and batch["depth"].shape == (1, 352, 1216)
