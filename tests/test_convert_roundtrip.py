"""A converted PyTorch checkpoint through ``evaluate.py`` on generated data, end to end.

The reference GroundAwareYolo3D (plain PyTorch, tests/torch_reference_models.py) at the
layout of ``configs/detect3d_default.py:tiny`` with random weights (GAC alpha non-zero, the
paper's offset formula) is saved as a ``.pth``, converted with ``python -m gac_jax.weights.convert
gac`` and evaluated by ``python evaluate.py --task detect3d --checkpoint ... --data ...`` on
a tiny embedded dataset. Oracle: the PyTorch model's own outputs on the evaluated images,
decoded and post-processed by the same :mod:`gac_jax.detection.inference` code. Checked: network
outputs (converted Flax variables vs PyTorch, 1e-4), a result file for every val frame
holding those detections, and the metrics JSON (the offline mode's schema and values).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from gac_jax.builders.detect3d import eval_transform, filter_options
from gac_jax.cli import evaluate as cli
from gac_jax.cli.evaluate_detector import load_detector, postprocess_config
from gac_jax.data.kitti import read_label, read_split
from gac_jax.data.loader import collate
from gac_jax.data.sources import open_object_source
from gac_jax.data.synthetic import generate_dataset
from gac_jax.detection.inference import make_predict_fn, postprocess
from gac_jax.evaluation.detector_evaluator import InputArrays, ground_truth
from gac_jax.evaluation.kitti_object import evaluate_detections
from gac_jax.trained.run_config import load_run_config
from gac_jax.weights import convert

torch = pytest.importorskip("torch")
from torch_reference_models import GroundAwareYolo3D, randomize_  # noqa: E402

torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]
TINY = str(REPO / "configs" / "detect3d_default.py:tiny")


class GivenOutputs:
    """Stands in for the Detector in :func:`make_predict_fn`: ``apply`` returns its
    ``variables``, i.e. the network outputs handed in (here: PyTorch's)."""

    def apply(self, variables, images, P2, train, plane=None):
        return variables


def flat(tree, prefix="") -> dict:
    """Nested metric dicts -> ``{'ap40/Car/0.70/bbox/1': value}`` (None kept)."""
    if isinstance(tree, dict):
        return {k: v for key, sub in tree.items() for k, v in flat(sub, f"{prefix}{key}/").items()}
    if isinstance(tree, list):
        return {k: v for i, sub in enumerate(tree) for k, v in flat(sub, f"{prefix}{i}/").items()}
    return {prefix.rstrip("/"): tree}


def rel_err(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / np.abs(b).max())


def test_converted_reference_checkpoint_through_evaluate_py(tmp_path):
    # A tiny embedded dataset at the tiny config's image size: 6 train / 6 val frames.
    root = tmp_path / "data"
    generate_dataset(root, 12, seed=3, height=188, width=621, val_fraction=0.5, workers=1)
    config = load_run_config(tmp_path, TINY, data_root=root)  # as evaluate.py builds it
    val_ids = read_split(root / "ImageSets" / "val.txt")
    assert len(val_ids) == 6
    source = open_object_source(root, "val", use_right_image=False)
    transform = eval_transform(config)
    batch = collate([InputArrays()(transform(dict(source[i]))) for i in range(len(source))])
    assert batch["image"].shape == (6, config.data.height, config.data.width, 3)

    # The reference model at the tiny layout: ResNet-18 of width 8, Car, 2 ratios x 16 scales.
    classes = tuple(config.data.classes)
    num_anchors = len(config.anchors.ratios) * config.anchors.num_scales
    m = config.model
    torch.manual_seed(0)  # the conv weights
    tmodel = GroundAwareYolo3D(
        depth=m.backbone_depth,
        width=m.backbone_width,
        num_classes=len(classes),
        num_anchors=num_anchors,
        cls=m.cls_features,
        reg=m.reg_features,
    )
    look = tmodel.bbox_head.reg_feature_extraction[0]
    look.alpha.data.fill_(0.7)  # the GAC path contributes
    look.formula = "fixed"  # = offset_formula 'paper', the tiny config's
    assert m.gac.offset_formula == "paper"
    images = torch.from_numpy(batch["image"]).permute(0, 3, 1, 2).contiguous()
    P2 = torch.from_numpy(batch["P2"])
    randomize_(tmodel, images, P2, seed=1)  # BN statistics near those of these images
    with torch.no_grad():
        cls, reg = (t.numpy() for t in tmodel(images, P2))
    pth = tmp_path / "gac_tiny.pth"
    torch.save(tmodel.state_dict(), pth)

    # python -m gac_jax.weights.convert gac IN.pth OUT --config TINY --offset-formula paper
    converted = tmp_path / "converted"
    argv = ["gac", pth, converted, "--config", TINY, "--offset-formula", "paper"]
    assert convert.main([str(a) for a in argv]) == 0

    # python evaluate.py --task detect3d --checkpoint OUT --config TINY --data ROOT --workdir W
    workdir = tmp_path / "work"
    ap_json = tmp_path / "ap.json"
    proc = subprocess.run(
        [
            sys.executable,
            str(REPO / "evaluate.py"),
            "--task",
            "detect3d",
            "--checkpoint",
            str(converted),
            "--config",
            TINY,
            "--data",
            str(root),
            "--workdir",
            str(workdir),
            "--json",
            str(ap_json),
        ],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO), JAX_PLATFORMS="cpu"),
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "computing anchor priors" in proc.stdout and "KITTI AP|R40" in proc.stdout
    out_dir = workdir / "eval" / "val_converted"
    result_dir = out_dir / "data"
    assert sorted(p.stem for p in result_dir.glob("*.txt")) == val_ids  # every val frame

    # The converted weights as evaluate.py restores them compute PyTorch's outputs.
    detector = load_detector(workdir, config, checkpoint=converted)
    out = jax.jit(lambda v, x, p: detector.model.apply(v, x, p, train=False))(
        detector.variables, batch["image"], batch["P2"]
    )
    k = len(classes)
    assert out["reg"].shape == reg.shape == (6, 4 * 16 * num_anchors, 12)
    assert rel_err(out["cls_logits"], cls[..., :k]) < 1e-4
    assert rel_err(out["sign_logits"], cls[..., k]) < 1e-4
    assert rel_err(out["reg"], reg) < 1e-4

    # PyTorch's raw outputs through the same decoding (evaluate.py's anchors, priors and
    # ground filter) and post-processing: the detections in the result files.
    predict = make_predict_fn(
        GivenOutputs(),
        detector.constants,
        top_k=config.eval.top_k,
        filter_options=filter_options(config),
        use_ground_filter=config.anchors.filter,
    )
    torch_outputs = {"cls_logits": cls[..., :k], "sign_logits": cls[..., k], "reg": reg}
    candidates = predict(torch_outputs, batch["image"], batch["P2"])
    expected = postprocess(candidates, batch, classes, postprocess_config(config))
    assert [str(f) for f in batch["frame_id"]] == val_ids
    total = 0
    for fid, want in zip(val_ids, expected, strict=True):
        got = read_label(result_dir / f"{fid}.txt", with_score=True)
        assert len(got) == len(want), fid
        total += len(got)
        assert list(got.type) == list(want.type)
        # Written with 2 (bbox) and 6 decimals; the two networks differ by ~1e-6 relative.
        np.testing.assert_allclose(got.bbox, want.bbox, atol=0.006)
        for field in ("alpha", "dimensions", "location", "rotation_y", "score"):
            np.testing.assert_allclose(
                getattr(got, field), getattr(want, field), rtol=1e-4, atol=2e-5, err_msg=field
            )
    assert total >= len(val_ids), total  # enough detections for the comparison to mean much

    # The metrics: the offline mode's JSON schema and values (the offline mode scores every
    # KITTI class, from the rounded files), and PyTorch's detections score the same AP.
    metrics = json.loads(ap_json.read_text())
    assert set(metrics.pop("_meta")["min_overlap"]) == set(classes)
    assert set(metrics) == {"ap11", "ap40"}
    for ap in metrics.values():
        assert set(ap) == set(classes)
        assert set(ap["Car"]) == {"0.70", "0.50"}
        for entry in ap["Car"].values():
            assert set(entry) == {"bbox", "bev", "3d", "aos"}
            assert all(len(entry[key]) == 3 for key in ("bbox", "bev", "3d"))
    offline_json = tmp_path / "offline.json"
    offline = [
        "--task",
        "detect3d",
        "--label-dir",
        root / "training" / "label_2",
        "--result-dir",
        result_dir,
        "--split-file",
        root / "ImageSets" / "val.txt",
        "--json",
        offline_json,
    ]
    assert cli.main([str(a) for a in offline]) == 0
    from_files = json.loads(offline_json.read_text())
    from_files.pop("_meta")
    assert set(from_files["ap40"]) == {"Car", "Pedestrian", "Cyclist"}
    from_files = {ap: {c: from_files[ap][c] for c in classes} for ap in from_files}
    assert flat(from_files) == pytest.approx(flat(metrics), abs=1e-4)
    gt = [ground_truth(source, i) for i in range(len(source))]
    from_torch = evaluate_detections(gt, expected, classes=classes)
    assert flat(from_torch) == pytest.approx(flat(metrics), abs=1e-4)
    summary = json.loads((out_dir / "metrics.json").read_text())
    assert summary["metrics"] == metrics
    assert summary["predicted"] == summary["num_frames"] == 6 and summary["resumed"] == 0
    assert summary["weights"] == f"converted weights {converted.resolve()}"
