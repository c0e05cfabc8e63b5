"""The Table 3 ablation variants: configs, a few training steps and a checkpoint round trip per
new variant, the deformable regression block against a plain conv, the converter's refusal."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from gac_jax import convert, pretrained
from gac_jax.builders.detect3d import anchor_layout, build_model, init_variables, loss_config
from gac_jax.checkpointing import Checkpoints
from gac_jax.config import apply_overrides, load_config
from gac_jax.models.detection_head import DetectionHead
from gac_jax.trainers import detect3d
from tests.conftest import TINY_DETECT3D_OVERRIDES

REPO = Path(__file__).resolve().parents[1]
DEFAULT = str(REPO / "configs" / "detect3d_default.py")
KITTI = str(REPO / "configs" / "detect3d_kitti.py")

# row -> (ground filter, OHEM drop fraction, regression block)
EXPECTED = {
    "baseline": (True, 0.0, "gac"),
    "nofilter": (False, 0.0, "gac"),
    "ohem": (False, 0.5, "gac"),
    "conv": (True, 0.0, "conv"),
    "disparity": (True, 0.0, "disparity_conv"),
    "deformable": (True, 0.0, "deformable"),
}


@pytest.mark.parametrize("row", sorted(EXPECTED))
def test_every_table3_row_is_a_variant_of_both_configs(row):
    for spec in (f"{DEFAULT}:{row}", f"{DEFAULT}:tiny,{row}", f"{KITTI}:{row}"):
        c = load_config(spec)
        got = (c.anchors.filter, c.loss.ohem_drop_fraction, c.model.regression_block)
        assert got == EXPECTED[row], spec
        assert loss_config(c).ohem_drop_fraction == EXPECTED[row][1]
    assert load_config(f"{DEFAULT}:tiny,{row}").data.height == 64
    assert load_config(f"{KITTI}:multiclass,{row}").data.classes == ("Car", "Pedestrian", "Cyclist")


def test_unknown_or_conflicting_variants_are_rejected():
    with pytest.raises(ValueError, match="unknown variants"):
        load_config(f"{DEFAULT}:tiny,dcn")
    with pytest.raises(ValueError, match="choose one"):
        load_config(f"{KITTI}:conv,deformable")


def _flat(tree) -> dict:
    return traverse_util.flatten_dict(jax.device_get(tree), sep="/")


# Two trainer runs cover the three new variants (each run compiles a train step, the bulk of
# the cost): OHEM (loss only) with the deformable block (head only), and the disparity conv.
@pytest.mark.parametrize(
    "variants, block", [("ohem,deformable", "deformable_conv"), ("disparity", "disparity_conv")]
)
def test_new_variants_train_and_round_trip_through_a_checkpoint(
    variants, block, kitti_object_root, tmp_path
):
    config = load_config(f"{DEFAULT}:tiny,{variants}")
    apply_overrides(
        config,
        [
            *TINY_DETECT3D_OVERRIDES,
            f"data.root={kitti_object_root}",
            "train.num_steps=3",
            "train.eval_at_end=False",
        ],
    )
    workdir = tmp_path / "run"
    detect3d.train_and_evaluate(config, workdir)
    with Checkpoints(workdir) as ckpts:
        assert ckpts.latest_step() == 3
        restored = ckpts.restore_variables()
    model = build_model(config, anchor_layout(config).anchors_per_cell)
    init = init_variables(model, config, config.seed)
    got, want = _flat(restored), _flat(init)
    assert set(got) == set(want)  # the checkpoint holds exactly this variant's variables
    assert all(got[k].shape == want[k].shape for k in want)
    block_keys = [k for k in want if k.startswith(f"params/head/{block}/")]
    assert block_keys and not any("/gac/" in k for k in want), sorted(want)
    if block == "deformable_conv":  # DCNv2: the offset/mask conv starts at zero and learns
        assert not np.any(want["params/head/deformable_conv/conv_offset/kernel"])
        assert np.any(got["params/head/deformable_conv/conv_offset/kernel"])
    moved = [k for k in block_keys if not np.allclose(got[k], want[k])]
    assert moved, f"{block} did not train"
    if "ohem" in variants:  # OHEM counted about half of the negatives (no ground filter)
        records = [json.loads(line) for line in (workdir / "metrics.jsonl").open()]
        train = [r for r in records if r["kind"] == "train"]
        assert train and all(r["num_negatives"] > 0 for r in train)
    # The restored variables run the variant's model.
    d = config.data
    images = jnp.asarray(np.random.default_rng(0).normal(size=(1, d.height, d.width, 3)))
    P2 = jnp.asarray([[[200.0, 0, d.width / 2, 0], [0, 200.0, d.height / 4, 0], [0, 0, 1, 0]]])
    out = model.apply(restored, images.astype(jnp.float32), P2, train=False)
    assert np.isfinite(np.asarray(out["reg"])).all()


def test_deformable_block_with_zero_offsets_and_unit_masks_is_the_plain_conv_head():
    """Head 'deformable' with conv_offset = (0 offsets, mask logits -> 1) equals head 'conv'
    carrying the same main kernel and bias in its plain_conv."""
    rng = np.random.default_rng(5)
    features = jnp.asarray(rng.normal(size=(2, 4, 6, 8)).astype(np.float32))
    P2 = jnp.asarray(np.tile([[200.0, 0, 48, 0], [0, 200.0, 16, 0], [0, 0, 1, 0]], (2, 1, 1)))
    kwargs = dict(num_anchors=2, cls_features=8, reg_features=8)
    deform = DetectionHead(regression_block="deformable", **kwargs)
    conv = DetectionHead(regression_block="conv", **kwargs)
    variables = jax.device_get(
        jax.jit(deform.init, static_argnums=3)(jax.random.key(1), features, P2, False)
    )
    params = variables["params"]
    dcn = params["deformable_conv"]
    K = 9
    assert not np.any(dcn["conv_offset"]["kernel"]) and not np.any(dcn["conv_offset"]["bias"])
    dcn["bias"] = rng.normal(size=8).astype(np.float32)
    dcn["conv_offset"]["bias"] = np.concatenate([np.zeros(2 * K), np.full(K, 60.0)]).astype(
        np.float32
    )  # sigmoid(60) == 1.0 in float32
    # make the regression output non-trivial (it is zero-initialised)
    params["reg_out"]["kernel"] = rng.normal(size=params["reg_out"]["kernel"].shape).astype(
        np.float32
    )
    conv_params = {k: v for k, v in params.items() if k != "deformable_conv"}
    conv_params["plain_conv"] = {"kernel": dcn["kernel"], "bias": dcn["bias"]}
    out_d = deform.apply({**variables, "params": params}, features, P2, False)
    out_c = conv.apply({**variables, "params": conv_params}, features, P2, False)
    assert np.abs(np.asarray(out_c["reg"])).max() > 0.1
    np.testing.assert_allclose(out_d["reg"], out_c["reg"], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(out_d["cls_logits"], out_c["cls_logits"])
    # with the masks at their DCNv2 init (0.5) the block is no longer the plain conv
    dcn["conv_offset"]["bias"] = np.zeros(3 * K, np.float32)
    out_half = deform.apply({**variables, "params": params}, features, P2, False)
    assert not np.allclose(out_half["reg"], out_c["reg"], atol=1e-3)


def test_converter_refuses_the_new_heads():
    """Reference GroundAwareYolo3D weights convert only into the GAC head."""
    for row in ("deformable", "disparity", "conv"):
        with pytest.raises(pretrained.WeightsError, match="regression_block"):
            convert.gac_model_settings({}, load_config(f"{DEFAULT}:tiny,{row}"))
    assert convert.gac_model_settings({}, load_config(f"{DEFAULT}:tiny,ohem"))["depth"] == 18
