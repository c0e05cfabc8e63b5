"""The Table 3 ablation variants: configs, a few training steps and a checkpoint round trip per
new variant, the deformable regression block against a plain conv, the converter's refusal."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import traverse_util

from gac_jax.builders.detect3d import anchor_layout, build_model, init_variables, loss_config
from gac_jax.config import apply_overrides, load_config
from gac_jax.models.detection_head import DetectionHead
from gac_jax.trainers import detect3d
from gac_jax.training.checkpointing import Checkpoints
from gac_jax.weights import convert, pretrained
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


# ----------------------------------------------------------------------------- the report


def _report_module():
    from gac_jax.cli.ablations import report

    return report


def test_paper_numbers_in_the_report_match_the_paper_source():
    rep = _report_module()
    tex = REPO.parent / "shared" / "spec" / "paper_gac.tex"
    if not tex.exists():
        pytest.skip(f"paper source not found at {tex}")
    assert rep.paper_table3_from_tex(tex.read_text()) == rep.PAPER_TABLE3


def _fake_run(workdir: Path, values: dict | None, step: int = 4, failed: bool = False):
    """A workdir as the trainer + runner leave it: metrics.jsonl, results, markers."""
    workdir.mkdir(parents=True)
    lines = [json.dumps({"step": s, "kind": "train", "loss": 1.0}) for s in range(1, step + 1)]
    (workdir / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    if failed:
        (workdir / "ablation_failed.json").write_text(json.dumps({"returncode": 1}))
    if values is None:
        return
    ap = {
        "Car": {
            "0.70": {"bbox": [0, values["2D@0.7"], 0], "3d": [0, values["3D@0.7"], 0]},
            "0.50": {"bev": [0, values["BEV@0.5"], 0], "3d": [0, values["3D@0.5"], 0]},
        }
    }  # fmt: skip
    _finish_run(workdir, {"ap40": ap, "ap11": {}}, step, wall_s=60.0)


def _finish_run(workdir: Path, metrics: dict, step: int, wall_s: float):
    """The final evaluation's metrics.json and the runner's done marker."""
    result = workdir / "results" / f"step_{step}"
    result.mkdir(parents=True)
    (result / "metrics.json").write_text(json.dumps({"metrics": metrics}))
    (workdir / "ablation_run.json").write_text(json.dumps({"final_step": step, "wall_s": wall_s}))


def test_report_statistics_and_unfinished_seeds(tmp_path):
    rep = _report_module()
    out = tmp_path / "out"
    names = ("3D@0.7", "3D@0.5", "BEV@0.5", "2D@0.7")
    base = [(10.0, 40.0, 45.0, 70.0), (12.0, 42.0, 47.0, 71.0), (11.0, 41.0, 46.0, 72.0)]
    conv = [(13.5, 30.0, 46.0, 70.5), (14.0, 31.0, 47.5, 71.5), None]
    for s in range(3):
        _fake_run(
            out / "detect3d" / "baseline" / f"seed_{s}", dict(zip(names, base[s], strict=True))
        )
    _fake_run(out / "detect3d" / "conv" / "seed_0", dict(zip(names, conv[0], strict=True)))
    _fake_run(out / "detect3d" / "conv" / "seed_1", dict(zip(names, conv[1], strict=True)))
    _fake_run(out / "detect3d" / "conv" / "seed_2", None, step=7)  # interrupted
    _fake_run(out / "detect3d" / "ohem" / "seed_0", None, step=3, failed=True)
    rows = ["baseline", "conv", "ohem", "deformable"]
    plan = {
        "config": "configs/detect3d_default.py",
        "overrides": [],
        "rows": rows,
        "seeds": [0, 1, 2],
    }
    (out / "plan.json").write_text(json.dumps({"detect3d": plan}))
    text = rep.render(out)
    b = np.asarray(base, np.float64)
    mean, std = b.mean(0), b.std(0, ddof=1)
    cell = f"{mean[1]:.2f} ± {std[1]:.2f} [{b[:, 1].min():.2f}, {b[:, 1].max():.2f}]"
    assert cell in text  # 3D@0.5 of the baseline over its three seeds
    c = np.asarray(conv[:2], np.float64)
    assert f"{c[:, 0].mean():.2f} ± {c[:, 0].std(ddof=1):.2f} [13.50, 14.00] (2 of 3 seeds)" in text
    assert "| `conv` | 2 | interrupted (step 7) |" in text
    assert "| `ohem` | 0 | failed (step 3) |" in text and "| `ohem` | 1 | not started |" in text
    assert "| `deformable` | 0 | not started |" in text
    assert "no finished run" in text and "0/3 |" in text
    # conv vs baseline: 3D@0.5 -10.5 beyond the spread, the paper's sign (-1.01); 3D@0.7
    # +2.75 beyond the spread, opposite to the paper (-0.90); BEV/2D within the spread.
    assert "`conv` 3D@0.5 -10.50 (worse, beyond the seed spread; paper -1.01, same sign)" in text
    assert (
        "`conv` 3D@0.7 +2.75 (better, beyond the seed spread; paper -0.90, opposite sign)" in text
    )
    assert "`conv` BEV@0.5 +0.75 (better, within the seed spread)" in text
    assert "`conv` 2D@0.7 +0.00 (equal means, within the seed spread)" in text
    assert "Not compared (fewer than 2 finished seeds" in text and "`ohem`, `deformable`" in text
    assert "## Depth (Base U-Net vs GAC U-Net)\n\nNot run yet" in text


def test_report_says_when_no_row_can_be_compared_yet(tmp_path):
    """One finished seed per row (a first session's state): no claim about differences."""
    rep = _report_module()
    out = tmp_path / "out"
    names = ("3D@0.7", "3D@0.5", "BEV@0.5", "2D@0.7")
    for row, values in (("baseline", (8.3, 36.5, 41.2, 76.0)), ("ohem", (8.3, 35.9, 41.3, 76.3))):
        _fake_run(out / "detect3d" / row / "seed_0", dict(zip(names, values, strict=True)))
    plan = {"config": "configs/detect3d_default.py", "overrides": [], "rows": ["baseline", "ohem"]}
    (out / "plan.json").write_text(json.dumps({"detect3d": plan | {"seeds": [0, 1]}}))
    text = rep.render(out)
    assert "No row can be compared with `baseline` yet." in text
    assert "exceeds the seed spread" not in text
    assert "1 of 2 seeds, no spread" in text


def _fake_depth_run(workdir: Path, silog: float, abs_rel: float, irmse: float, step: int = 4):
    workdir.mkdir(parents=True)
    (workdir / "metrics.jsonl").write_text(json.dumps({"step": step, "kind": "train"}) + "\n")
    metrics = {"silog": silog, "abs_rel": abs_rel, "irmse": irmse, "rmse": 4000.0}
    _finish_run(workdir, metrics, step, wall_s=120.0)


def test_depth_report_lower_is_better(tmp_path):
    """Depth errors: a lower mean is "better", compared with the paper's GAC - Base sign."""
    rep = _report_module()
    out = tmp_path / "out"
    runs = {
        "base": [(14.0, 8.5, 11.4), (14.2, 8.7, 11.6)],
        "gac": [(13.0, 8.6, 11.9), (13.1, 8.4, 12.0)],
    }
    for row, seeds in runs.items():
        for s, values in enumerate(seeds):
            _fake_depth_run(out / "depth" / row / f"seed_{s}", *values)
    plan = {"config": "configs/depth_default.py", "overrides": [], "rows": ["base", "gac"]}
    (out / "plan.json").write_text(json.dumps({"depth": plan | {"seeds": [0, 1]}}))
    text = rep.render(out)
    assert "## Detection (paper Table 3)\n\nNot run yet" in text
    assert "| `base` | 12.78 | 10.12 | 13.46 | 14.10 ± 0.14 [14.00, 14.20] |" in text
    assert "| `gac` | 1 | done (step 4) | 13.10 | 8.40 | 12.00 | 2 min |" in text
    # paper: GAC - Base = 12.13 - 12.78 = -0.65 SILog, 12.65 - 13.46 = -0.81 iRMSE
    assert "`gac` SILog -1.05 (better, beyond the seed spread; paper -0.65, same sign)" in text
    assert "`gac` iRMSE +0.45 (worse, beyond the seed spread; paper -0.81, opposite sign)" in text
    assert "`gac` absRel % -0.10 (better, within the seed spread)" in text


def test_depth_extra_split_reads_evaluate_json(tmp_path):
    """``evaluate.py --task depth --workdir W --split S --json`` keeps the metrics under
    ``metrics`` (the multi-rig depth comparison's ``val_heldout`` table)."""
    rep = _report_module()
    out = tmp_path / "out"
    for row, silog in (("gac", 13.0), ("fixedplane", 15.0)):
        workdir = out / "depth" / row / "seed_0"
        _fake_depth_run(workdir, silog, 8.0, 11.0)
        held = {"metrics": {"silog": silog + 5, "abs_rel": 9.0, "irmse": 12.0}, "num_frames": 3}
        (workdir / "ablation_eval").mkdir()
        (workdir / "ablation_eval" / "val_heldout.json").write_text(json.dumps(held))
    plan = {"config": "configs/depth_default.py:multirig", "overrides": [], "seeds": [0]}
    plan |= {"rows": ["gac", "fixedplane"], "eval_splits": ["val_heldout"]}
    (out / "plan.json").write_text(json.dumps({"depth": plan}))
    held_part = rep.render(out).split("### On split `val_heldout`")[1]
    assert "| `fixedplane` | 0 | done (step 4) | 20.00 | 9.00 | 12.00 |" in held_part


def _write_eval(workdir: Path, split: str, values: dict):
    """What the runner leaves after ``evaluate.py --workdir W --split S --json``."""
    ap = {
        "Car": {
            "0.70": {"bbox": [0, values["2D@0.7"], 0], "3d": [0, values["3D@0.7"], 0]},
            "0.50": {"bev": [0, values["BEV@0.5"], 0], "3d": [0, values["3D@0.5"], 0]},
        }
    }  # fmt: skip
    path = workdir / "ablation_eval" / f"{split}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"ap40": ap, "ap11": {}}))


def test_extra_split_tables_and_named_sections(tmp_path):
    """A multi-rig experiment: its own section (kept when the paper's tables are rewritten,
    replaced in place when rerun) with a table per extra split, from the runner's files."""
    rep = _report_module()
    out = tmp_path / "multirig"
    names = ("3D@0.7", "3D@0.5", "BEV@0.5", "2D@0.7")
    val = {"baseline": [(9, 40, 45, 70), (10, 41, 46, 71)], "fixedplane": [(9, 39, 44, 70)] * 2}
    held = {"baseline": [(5.0, 30.0, 35, 60), (6.0, 31.0, 36, 61)], "fixedplane": [(2, 20, 25, 50)]}
    for row, seeds in val.items():
        for s, v in enumerate(seeds):
            workdir = out / "detect3d" / row / f"seed_{s}"
            _fake_run(workdir, dict(zip(names, v, strict=True)))
            if s < len(held[row]):
                _write_eval(workdir, "val_heldout", dict(zip(names, held[row][s], strict=True)))
    plan = {
        "config": "configs/detect3d_default.py:multirig",
        "overrides": [],
        "rows": ["baseline", "fixedplane"],
        "seeds": [0, 1],
        "eval_splits": ["val_heldout"],
        "section": "multirig",
        "title": "Multi-rig detection",
    }
    (out / "plan.json").write_text(json.dumps({"detect3d": plan}))
    main = tmp_path / "main"
    _fake_run(
        main / "detect3d" / "baseline" / "seed_0", dict(zip(names, (1, 2, 3, 4), strict=True))
    )
    main_plan = {"config": "c.py", "overrides": [], "rows": ["baseline"], "seeds": [0]}
    (main / "plan.json").write_text(json.dumps({"detect3d": main_plan}))

    first = rep.compose_report("", out, "multirig")  # no report yet: header + the section
    assert first.startswith("# Ablations with seed spread (generated)")
    assert "## Multi-rig detection\n" in first and "### On split `val_heldout`" in first
    assert "| `fixedplane` | 1 | not evaluated (step 4) |" in first
    held_part = first[first.index("### On split `val_heldout`") :]
    assert "| `baseline` | 16.16 | 42.18 | 5.50 ± 0.71 [5.00, 6.00] |" in held_part
    assert "`fixedplane` 3D@0.5 -1.50 (worse, beyond the seed spread)" in first  # val split
    assert "Not compared (fewer than 2 finished seeds" in held_part  # fixedplane: 1 seed
    with_main = rep.compose_report(first, main, None)  # the paper's tables rewritten
    assert with_main.count("<!-- ablation section multirig:") == 1
    assert (
        "## Multi-rig detection" in with_main
        and "| `baseline` | 0 | done (step 4) | 1.00" in with_main
    )
    _write_eval(
        out / "detect3d" / "fixedplane" / "seed_1",
        "val_heldout",
        dict(zip(names, (3, 21, 26, 51), strict=True)),
    )
    again = rep.compose_report(with_main, out, "multirig")  # rerun: replaced in place
    assert again.count("## Multi-rig detection") == 1
    assert again.index("| `baseline` | 0 | done (step 4) | 1.00") < again.index("## Multi-rig")
    assert "`fixedplane` 3D@0.5 -10.00 (worse, beyond the seed spread)" in again


def test_runner_plan_keeps_extra_splits_and_refuses_another_section(tmp_path, capsys):
    from gac_jax.cli.ablations import runner as table

    entry = {"config": "c.py:multirig", "overrides": [], "rows": ["baseline"], "seeds": [0]}
    entry |= {"eval_splits": ["val_heldout"], "section": "multirig", "title": "T"}
    table.update_plan(tmp_path, "detect3d", entry)
    more = entry | {"rows": ["conv"], "seeds": [1], "eval_splits": ["val_kitti_rig"]}
    plan = table.update_plan(tmp_path, "detect3d", more | {"title": None})["detect3d"]
    assert plan["rows"] == ["baseline", "conv"] and plan["seeds"] == [0, 1]
    assert plan["eval_splits"] == ["val_heldout", "val_kitti_rig"] and plan["title"] == "T"
    assert "--eval-splits val_heldout,val_kitti_rig --section multirig --title T" in plan["command"]
    with pytest.raises(SystemExit):
        table.update_plan(tmp_path, "detect3d", entry | {"section": "other"})
    assert "section=" in capsys.readouterr().err


def test_report_names_no_folder_of_the_machine(tmp_path):
    """Run folders: relative to the repository inside it, ``workdirs/<name>`` outside it, in
    the section text and in the command the report prints; never an absolute path."""
    rep = _report_module()
    assert rep.shown(rep.REPO / "workdirs" / "abl") == "workdirs/abl"
    assert rep.shown(tmp_path / "runs" / "abl_multirig") == "workdirs/abl_multirig"
    assert rep.shown(tmp_path / "x" / ".." / "abl", repo=tmp_path) == "abl"
    out = tmp_path / "elsewhere" / "abl_crossrig"
    names = ("3D@0.7", "3D@0.5", "BEV@0.5", "2D@0.7")
    _fake_run(out / "detect3d" / "baseline" / "seed_0", dict(zip(names, (1, 2, 3, 4), strict=True)))
    plan = {"config": "configs/detect3d_default.py:multirig,kittirig", "rows": ["baseline"]}
    plan |= {"seeds": [0], "eval_splits": [], "section": "crossrig", "title": "Cross-rig"}
    # a plan.json written by an older runner: its stored command names the absolute folder
    plan |= {"overrides": ["train.num_epochs=30"], "command": f"python x.py --out {out}"}
    (out / "plan.json").write_text(json.dumps({"detect3d": plan}))
    text = rep.compose_report("", out, "crossrig")
    assert str(tmp_path) not in text and "/elsewhere" not in text
    assert "Runs in `workdirs/abl_crossrig/detect3d`" in text
    assert (
        "python -m gac_jax.cli.ablations --task detect3d --rows baseline --seeds 0 --out "
        "workdirs/abl_crossrig --config configs/detect3d_default.py:multirig,kittirig "
        "--section crossrig --title Cross-rig train.num_epochs=30" in text
    )
    assert not re.search(r"(^|[\s`(])/(work|tmp|home|root|Users)/", text, re.M)


def test_committed_report_names_no_folder_of_the_machine():
    text = (REPO / "docs" / "ablations.md").read_text()
    assert not re.search(r"(^|[\s`(=])/[A-Za-z]", text, re.M), "an absolute path in the report"
    assert "python -m gac_jax.cli.ablations" in text and "benchmarks/ablation" not in text
    # its header and rows are the generator's (the file was not edited by hand there)
    fresh = _report_module().render(REPO / "workdirs" / "none", plan={})
    assert text.startswith(fresh[: fresh.index("## Detection (paper Table 3)")])


def test_runner_entry_point_help():
    """``python -m gac_jax.cli.ablations`` is the documented command."""
    proc = subprocess.run(
        [sys.executable, "-m", "gac_jax.cli.ablations", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert "python -m gac_jax.cli.ablations --rows baseline" in proc.stdout
