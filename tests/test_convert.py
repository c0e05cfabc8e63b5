"""Tests of the PyTorch weight import (gac_jax.weights.convert) and the converted-weights layout
(gac_jax.weights.pretrained).

Oracles: plain-PyTorch models (tests/torch_reference_models.py) - a ResNet with torchvision's
layer naming and the reference GroundAwareYolo3D (ResNet trunk through layer3, cls branch, reg
branch with LookGround using grid_sample(border, align_corners=True), AnchorFlatten) built from
reference_impl.md §3 - run in eval mode with random weights and random BatchNorm statistics;
the reference state-dict listing ../shared/spec/reference_state_dict.md (that comparison skips
when the file is absent). Reading .pth files: tests/test_torch_state_dict.py.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from gac_jax.models.detector import Detector
from gac_jax.models.resnet import ResNet
from gac_jax.weights import convert, pretrained

torch = pytest.importorskip("torch")
from torch_reference_models import (  # noqa: E402  (tests/ is on sys.path under pytest)
    GroundAwareYolo3D,
    TorchResNet,
    randomize_,
)

from tests.conftest import SHARED  # noqa: E402

torch.set_num_threads(1)

REPO_ROOT = Path(__file__).resolve().parents[1]
REFERENCE_STATE_DICT = SHARED / "spec" / "reference_state_dict.md"  # ../shared (optional)


def state_dict_np(model) -> dict[str, np.ndarray]:
    return {k: v.detach().numpy().copy() for k, v in model.state_dict().items()}


def nhwc(t) -> np.ndarray:
    return t.detach().permute(0, 2, 3, 1).numpy()


def rel_err(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.abs(a - b).max() / np.abs(b).max())


def images_nchw(shape, seed):
    return torch.from_numpy(np.random.default_rng(seed).normal(size=shape).astype(np.float32))


def P2_batch() -> np.ndarray:
    """Two KITTI-like projections for 64x256 inputs (horizon near the top: the GAC offsets
    are large and differ per image)."""
    P = np.array([[180.0, 0, 128, 11.2], [0, 180, 12, 0.05], [0, 0, 1, 0.003]], np.float32)
    Q = P.copy()
    Q[1, 2], Q[1, 1] = 20.0, 170.0
    return np.stack([P, Q])


def abstract(model, *args):
    variables = jax.eval_shape(lambda: model.init(jax.random.key(0), *args, train=False))
    return {c: variables[c] for c in ("params", "batch_stats")}


def run_cli(argv, capsys):
    status = convert.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


# ---------------------------------------------------------------------------------------------
# torchvision ResNets


@pytest.mark.parametrize("depth", [34, 50, 101])
def test_torchvision_resnet_converts_to_the_same_features(depth):
    width = 16  # any width: the converter reads it from conv1
    images = images_nchw((2, 3, 64, 96), depth)
    tnet = randomize_(TorchResNet(depth, width=width), images, seed=depth)
    with torch.no_grad():
        expected = [nhwc(t) for t in tnet(images)]
    variables, model = convert.convert_torchvision_resnet(state_dict_np(tnet))
    assert model == {"depth": depth, "width": width, "num_stages": 4}
    net = ResNet(depth=depth, num_stages=4, width=width)
    out = jax.jit(lambda v, x: net.apply(v, x, train=False))(variables, nhwc(images))
    assert (
        out["layer3"].shape
        == expected[2].shape
        == (2, 4, 6, net.width * 4 * (4 if depth >= 50 else 1))
    )
    assert rel_err(out["layer3"], expected[2]) < 1e-4  # stride 16
    assert rel_err(out["layer4"], expected[3]) < 1e-4


def test_torchvision_resnet18_through_the_cli_and_backbone_init(tmp_path, capsys):
    images = images_nchw((2, 3, 64, 96), 18)
    tnet = randomize_(TorchResNet(18), images, seed=18)  # full torchvision layout incl. fc
    with torch.no_grad():
        expected = nhwc(tnet(images)[2])
    pth = tmp_path / "resnet18.pth"
    torch.save(tnet.state_dict(), pth)
    status, out, err = run_cli(["torchvision-resnet", pth, tmp_path / "rn18"], capsys)
    assert status == 0, err
    assert "checkpoints/0" in out

    meta = pretrained.read_converted_meta(tmp_path / "rn18")
    assert meta["kind"] == "torchvision_resnet" and meta["model"]["depth"] == 18
    assert meta["sha256"] == hashlib.sha256(pth.read_bytes()).hexdigest()
    assert meta["source"] == str(pth.resolve())
    readable = json.loads((tmp_path / "rn18" / "conversion.json").read_text())
    assert readable["sha256"] == meta["sha256"] and "date" in readable and "shapes" not in readable

    # 3-stage trunk (the detector's) from the 4-stage checkpoint: layer4 is dropped
    net = ResNet(depth=18, num_stages=3)
    fresh = abstract(net, nhwc(images))  # only shapes and dtypes matter
    variables = pretrained.load_backbone_init(tmp_path / "rn18" / "checkpoints" / "0", fresh)
    assert jax.tree.structure(variables) == jax.tree.structure(fresh)
    got = jax.jit(lambda v, x: net.apply(v, x, train=False))(variables, nhwc(images))["layer3"]
    assert rel_err(got, expected) < 1e-4

    # the same weights merged into a whole detector: only the backbone changes
    det = Detector(depth=18, num_classes=1, num_anchors=4, cls_features=8, reg_features=8)
    det_vars = abstract(det, jnp.zeros((1, 64, 96, 3)), jnp.zeros((1, 3, 4)))
    merged = pretrained.init_backbone(det_vars, tmp_path / "rn18")
    assert merged["params"]["head"] is det_vars["params"]["head"]
    np.testing.assert_array_equal(
        merged["params"]["backbone"]["conv1"]["kernel"],
        tnet.conv1.weight.detach().numpy().transpose(2, 3, 1, 0),
    )
    np.testing.assert_array_equal(
        merged["batch_stats"]["backbone"]["layer3_1"]["bn2"]["var"],
        tnet.layer3[1].bn2.running_var.numpy(),
    )

    # whole 4-stage variables, and a wrong template
    full = pretrained.load_converted_variables(
        tmp_path / "rn18", abstract(ResNet(depth=18), jnp.zeros((1, 32, 32, 3)))
    )
    assert "layer4_1" in full["params"]
    with pytest.raises(pretrained.WeightsError, match="does not fit") as info:
        pretrained.load_backbone_init(
            tmp_path / "rn18", abstract(ResNet(depth=34, num_stages=3), jnp.zeros((1, 32, 32, 3)))
        )
    assert any("layer1_2/conv1/kernel" in d for d in info.value.details)
    with pytest.raises(pretrained.WeightsError, match="width 64") as info:
        pretrained.load_backbone_init(
            tmp_path / "rn18", abstract(ResNet(depth=18, width=32), jnp.zeros((1, 32, 32, 3)))
        )
    mismatch = "shape mismatch: params/conv1/kernel is [7, 7, 3, 64] in the checkpoint, "
    assert mismatch + "[7, 7, 3, 32] in the model" in info.value.details

    # a second conversion into the same folder needs --overwrite
    status, _, err = run_cli(["torchvision-resnet", pth, tmp_path / "rn18"], capsys)
    assert status == 2 and "--overwrite" in err
    assert run_cli(["torchvision-resnet", pth, tmp_path / "rn18", "--overwrite"], capsys)[0] == 0


# ---------------------------------------------------------------------------------------------
# the reference GroundAwareYolo3D, full size (Car only, ResNet-101)


def reference_entries() -> list[tuple[str, tuple[int, ...], str]]:
    if not REFERENCE_STATE_DICT.is_file():
        pytest.skip(f"reference state-dict listing not found at {REFERENCE_STATE_DICT}")
    text = REFERENCE_STATE_DICT.read_text()
    body = text.split("### GroundAwareYolo3D: every state_dict entry", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(
        r"^\|\s*\d+\s*\|\s*`([^`]+)`\s*\|\s*\[([\d,\s]*)\]\s*\|\s*\w+\s*\|\s*(\w+)", body, re.M
    )
    return [(k, tuple(int(n) for n in s.split(",") if n.strip()), kind) for k, s, kind in rows]


@pytest.fixture(scope="module")
def reference_gac():
    images = images_nchw((2, 3, 64, 256), 7)
    P2 = P2_batch()
    tmodel = GroundAwareYolo3D()
    tmodel.bbox_head.reg_feature_extraction[0].alpha.data.fill_(0.5)  # GAC path matters
    randomize_(tmodel, images, torch.from_numpy(P2), seed=3)
    sd = state_dict_np(tmodel)
    return tmodel, sd, images, P2


def test_reference_model_has_the_reference_state_dict(reference_gac):
    tmodel, sd, _, _ = reference_gac
    assert len(sd) == 594
    assert sum(p.numel() for p in tmodel.parameters()) == 58_388_994
    entries = reference_entries()
    assert [(k, s) for k, s, _ in entries] == [(k, tuple(v.shape)) for k, v in sd.items()]
    params = {n for n, _ in tmodel.named_parameters()}
    assert {k for k, _, kind in entries if kind == "param"} == params


@pytest.mark.parametrize(
    ("torch_formula", "flax_formula"), [("release_1.0", "reference_v1"), ("fixed", "paper")]
)
def test_reference_gac_converts_to_the_same_outputs(reference_gac, torch_formula, flax_formula):
    tmodel, sd, images, P2 = reference_gac
    look = tmodel.bbox_head.reg_feature_extraction[0]
    look.formula = torch_formula
    with torch.no_grad():
        cls, reg = (t.numpy() for t in tmodel(images, torch.from_numpy(P2)))
    look.formula = "release_1.0"

    settings = convert.gac_model_settings(sd, overrides={"offset_formula": flax_formula})
    assert settings == {
        "depth": 101,
        "width": 64,
        "num_classes": 1,
        "num_anchors": 32,
        "cls_features": 512,
        "reg_features": 1024,
        "regression_block": "gac",
        "offset_formula": flax_formula,
    }
    variables = convert.convert_gac(sd, settings)
    model = convert.make_detector(settings)
    out = jax.jit(lambda v, x, p: model.apply(v, x, p, train=False))(variables, nhwc(images), P2)
    assert out["reg"].shape == reg.shape == (2, 4 * 16 * 32, 12)
    assert rel_err(out["cls_logits"], cls[..., :1]) < 1e-4
    assert rel_err(out["sign_logits"], cls[..., 1]) < 1e-4
    assert rel_err(out["reg"], reg) < 1e-4
    # the formulas give different regression outputs: the test tells them apart
    other = "fixed" if torch_formula == "release_1.0" else "release_1.0"
    look.formula = other
    with torch.no_grad():
        _, reg_other = tmodel(images, torch.from_numpy(P2))
    look.formula = "release_1.0"
    assert rel_err(reg_other.numpy(), reg) > 1e-2


def test_reference_gac_with_an_extra_or_wrong_head_is_refused(reference_gac):
    _, sd, _, _ = reference_gac
    settings = convert.gac_model_settings(sd)
    extra = dict(sd, **{"bbox_head.cls_feature_extraction.9.weight": np.zeros((2, 2, 3, 3))})
    with pytest.raises(pretrained.WeightsError, match="1 unused tensors") as info:
        convert.convert_gac(extra, settings)
    assert info.value.details == [
        "unused tensor: bbox_head.cls_feature_extraction.9.weight (no rule)"
    ]
    # a Car-only file for a 3-class model
    with pytest.raises(pretrained.WeightsError, match=r"num_classes=3 \(file: 1\)") as info:
        convert.convert_gac(sd, dict(settings, num_classes=3))
    assert any("cls_feature_extraction.6.weight" in d for d in info.value.details)
    # a truncated dict (last 20 tensors missing)
    keys = list(sd)[:-20]
    with pytest.raises(pretrained.WeightsError, match="Flax leaves not filled") as info:
        convert.convert_gac({k: sd[k] for k in keys}, settings)
    assert info.value.details[0] == "not filled: backbone/layer3_21/bn3 (batch_stats/var)"
    assert "not filled: backbone/layer3_22/conv1 (params/kernel)" in info.value.details


# ---------------------------------------------------------------------------------------------
# the CLI on a tiny GAC model with a config file


TINY_CONFIG = """
import ml_collections


def get_config(arg=None):
    c = ml_collections.ConfigDict()
    c.data = ml_collections.ConfigDict({"classes": ("Car", "Pedestrian")})
    c.anchors = ml_collections.ConfigDict({"ratios": (0.5, 1.0), "scales": (1.0, 2.0)})
    c.model = ml_collections.ConfigDict(
        {"backbone_depth": 18, "backbone_width": 8, "regression_block": "gac",
         "gac": {"offset_formula": "paper"}}
    )
    return c
"""


@pytest.mark.parametrize(
    "configured, trained, noted",
    [
        ("paper", "reference", False),
        ("reference", "paper", False),
        ("paper", "paper", False),
        ("reference_v1", "reference_v1", False),
        (None, "reference_v1", False),
        ("paper", "reference_v1", True),
        ("reference", "reference_v1", True),
        ("reference_v1", "paper", True),
        ("reference_v1", "reference", True),
    ],
)
def test_offset_formula_note_only_when_offsets_differ(configured, trained, noted):
    """'paper' and 'reference' give the same offsets (checked here); only 'reference_v1' differs."""
    from gac_jax.models.ground_aware_conv import OFFSET_FORMULAS, base_offset

    P = jnp.asarray(P2_batch())
    rows = {f: np.asarray(base_offset(16, P, 4, offset_formula=f)) for f in OFFSET_FORMULAS}
    np.testing.assert_allclose(rows["paper"], rows["reference"], rtol=1e-6, atol=1e-6)
    assert np.abs(rows["paper"] - rows["reference_v1"]).max() > 0.1
    note = convert.offset_formula_note("cfg.py", configured, trained)
    assert (note is not None) == noted
    if noted:
        assert f"model.gac.offset_formula={trained}" in note and "cfg.py" in note


def test_gac_cli_with_a_config_round_trip(tmp_path, capsys):
    images, P2 = images_nchw((2, 3, 64, 256), 11), P2_batch()
    tmodel = GroundAwareYolo3D(depth=18, width=8, num_classes=2, num_anchors=4, cls=16, reg=32)
    tmodel.bbox_head.reg_feature_extraction[0].alpha.data.fill_(0.8)
    tmodel.bbox_head.reg_feature_extraction[0].formula = "fixed"
    randomize_(tmodel, images, torch.from_numpy(P2), seed=5)
    with torch.no_grad():
        cls, reg = (t.numpy() for t in tmodel(images, torch.from_numpy(P2)))
    pth, cfg = tmp_path / "gac.pth", tmp_path / "tiny.py"
    torch.save({"epoch": 3, "model": {"state_dict": tmodel.state_dict()}}, pth)  # wrapped
    cfg.write_text(TINY_CONFIG)

    argv = ["gac", pth, tmp_path / "out", "--config", cfg, "--offset-formula", "paper"]
    status, _, err = run_cli(argv, capsys)
    assert status == 0, err
    meta = pretrained.read_converted_meta(tmp_path / "out")
    assert meta["kind"] == "gac_detector"
    assert meta["model"] == {
        "depth": 18,
        "width": 8,
        "num_classes": 2,
        "num_anchors": 4,
        "cls_features": 16,
        "reg_features": 32,
        "regression_block": "gac",
        "offset_formula": "paper",
    }
    model = convert.make_detector(meta["model"])
    template = abstract(model, jnp.zeros((1, 64, 256, 3)), jnp.zeros((1, 3, 4)))
    variables = pretrained.load_converted_variables(tmp_path / "out", template)
    out = model.apply(variables, nhwc(images), P2, train=False)
    assert rel_err(out["cls_logits"], cls[..., :2]) < 1e-4
    assert rel_err(out["sign_logits"], cls[..., 2]) < 1e-4
    assert rel_err(out["reg"], reg) < 1e-4

    # default formula (release 1.0) differs from the config's: converted, with a note
    status, _, err = run_cli(["gac", pth, tmp_path / "v1", "--config", cfg], capsys)
    assert status == 0 and "note:" in err and "offset_formula=reference_v1" in err
    # 'reference' is the config's 'paper' formula written another way: no note
    argv = ["gac", pth, tmp_path / "ref", "--config", cfg, "--offset-formula", "reference"]
    status, _, err = run_cli(argv, capsys)
    assert status == 0 and "note" not in err, err
    assert (
        pretrained.read_converted_meta(tmp_path / "v1")["model"]["offset_formula"] == "reference_v1"
    )

    # a config asking for another model: exit 2 naming the keys
    status, _, err = run_cli(
        ["gac", pth, tmp_path / "bad", "--config", cfg, "--num-anchors", "8"], capsys
    )
    assert status == 2
    first, *rest = err.strip().splitlines()
    assert (
        first.startswith("error: the weights do not fit a Detector(")
        and "num_anchors=8 (file: 4)" in first
    )
    assert any("reg_feature_extraction.7.weight" in line for line in rest)
    assert "Traceback" not in err
    # the detector checkpoint can also seed a backbone
    backbone = pretrained.load_backbone_init(
        tmp_path / "out", {c: template[c]["backbone"] for c in ("params", "batch_stats")}
    )
    np.testing.assert_array_equal(
        backbone["params"]["layer2_0"]["downsample_0"]["kernel"],
        variables["params"]["backbone"]["layer2_0"]["downsample_0"]["kernel"],
    )


# ---------------------------------------------------------------------------------------------
# wrong files


def test_depth50_state_dict_for_depth101_is_refused(tmp_path, capsys):
    sd = state_dict_np(TorchResNet(50, width=8))
    with pytest.raises(pretrained.WeightsError, match="ResNet-50 \\(blocks 3-4-6-3") as info:
        convert.convert_torchvision_resnet(sd, depth=101)
    assert "255 Flax leaves not filled" in str(info.value)
    # 17 missing bottlenecks (layer3_6 .. layer3_22) of 3 convs + 3 BNs, listed per module
    assert len(info.value.details) == 17 * 6
    bn1 = "layer3_6/bn1 (batch_stats/mean, batch_stats/var, params/bias, params/scale)"
    assert info.value.details[0] == f"not filled: {bn1}"
    assert "not filled: layer3_22/conv3 (params/kernel)" in info.value.details
    pth = tmp_path / "r50.pth"
    torch.save(TorchResNet(50, width=8).state_dict(), pth)
    status, out, err = run_cli(
        ["torchvision-resnet", pth, tmp_path / "o", "--depth", "101"], capsys
    )
    assert status == 2 and out == ""
    assert err.splitlines()[0].startswith("error: the weights do not fit a 4-stage ResNet-101")
    assert bn1 in err and "... and 42 more" in err  # long lists are cut
    assert not (tmp_path / "o" / "checkpoints").exists()
    # a depth-18 file where depth 50 is asked: the message says what the file holds
    sd18 = state_dict_np(TorchResNet(18, width=8))
    with pytest.raises(pretrained.WeightsError, match="ResNet-18"):
        convert.convert_torchvision_resnet(sd18, depth=50)


def test_converted_layout_refuses_foreign_folders(tmp_path):
    with pytest.raises(pretrained.WeightsError, match="no converted weights here"):
        pretrained.read_converted_meta(tmp_path)
    from gac_jax.training.checkpointing import Checkpoints

    with Checkpoints(tmp_path / "train") as ckpts:  # a training workdir
        ckpts.save(5, {"params": {"w": np.zeros(2, np.float32)}}, {"task": "detect3d"})
    with pytest.raises(pretrained.WeightsError, match="not converted weights"):
        pretrained.read_converted_meta(tmp_path / "train")
    variables = {"params": {"w": np.zeros(2, np.float32)}}
    meta = {"kind": "torchvision_resnet", "model": {}}
    with pytest.raises(pretrained.WeightsError, match="already holds checkpoints"):
        pretrained.save_converted(tmp_path / "train", variables, meta, overwrite=True)
    flat = traverse_util.flatten_dict(
        pretrained.restore_converted(pretrained.save_converted(tmp_path / "conv", variables, meta))[
            0
        ],
        sep="/",
    )
    assert list(flat) == ["params/w"]


def test_config_model_settings_reads_the_keys_defensively():
    import ml_collections

    config = ml_collections.ConfigDict(
        {
            "data": {"classes": ("Car", "Pedestrian", "Cyclist")},
            "anchors": {"ratios": (0.5, 1.0, 2.0), "num_scales": 16},
            "model": {"backbone_depth": 50, "gac": {"offset_formula": "paper"}},
        }
    )
    got = convert.config_model_settings(config)
    assert got == {
        "depth": 50,
        "width": None,
        "num_classes": 3,
        "num_anchors": 48,
        "cls_features": None,
        "reg_features": None,
        "regression_block": None,
        "offset_formula": "paper",
    }
    config.model.num_classes = 2  # an explicit model key wins over the class list
    config.model.regression_block = "conv"
    assert convert.config_model_settings(config)["num_classes"] == 2
    sd = {"core.backbone.conv1.weight": np.zeros((64, 3, 7, 7), np.float32)}
    with pytest.raises(pretrained.WeightsError, match="regression_block 'conv'"):
        convert.gac_model_settings(sd, config)
    assert convert.config_model_settings(ml_collections.ConfigDict())["num_anchors"] is None
