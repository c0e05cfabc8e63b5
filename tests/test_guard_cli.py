"""The guard command (gac_jax.cli.guard) and int8 with the heading kept, end to end.

On a copy of the tiny trained workdir (4 real KITTI frames): the guard runs jax float32 and
the candidates, writes ``guard.json`` beside the export (undecided: 4 frames are far too few,
with the frames that would decide), the int8 model keeps exactly the heading convs in float32
(found in the exported graph), and ``evaluate.py`` says which precision it runs and what the
guard decided for it ("not guarded" for one the guard did not see). Skipped without the
deploy extra or NNCF.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import pytest

pytest.importorskip("onnx", reason="deploy extra (onnx) not installed")
pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
pytest.importorskip("nncf", reason="deploy extra (nncf) not installed")

from gac_jax.cli import evaluate as evaluate_cli  # noqa: E402
from gac_jax.cli import guard  # noqa: E402
from gac_jax.deploy import int8  # noqa: E402
from gac_jax.deploy.export import artifact  # noqa: E402
from gac_jax.guard import verdict_file  # noqa: E402

FRAMES = "3"


@pytest.fixture(scope="module")
def guarded(tiny_detect3d_workdir, tmp_path_factory):
    wd = tmp_path_factory.mktemp("guard") / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "export"))
    argv = ["--workdir", str(wd), "--candidates", "onnxruntime:f32,openvino:int8+heading"]
    argv += ["--int8-frames", FRAMES, "--json", str(wd.parent / "guard_report.json")]
    assert guard.main(argv) == 0
    return wd, json.loads((wd.parent / "guard_report.json").read_text())


def test_guard_writes_undecided_verdicts_with_the_frames_needed(guarded, capsys):
    wd, report = guarded
    data = verdict_file.read_guard(wd / "export" / "step2")
    assert set(data["verdicts"]) == {"onnxruntime:f32", "openvino:int8+heading"}
    assert data["model"]["weights"] == "step2" and data["model"]["onnx_sha256"]
    for entry in data["verdicts"].values():
        assert entry["verdict"] == "undecided" and entry["frames"] == 4
        assert entry["frames_needed"] is None or entry["frames_needed"] > 4
        assert "too few frames" in entry["reason"]
    # ONNX Runtime float32 finds exactly the objects jax float32 finds
    crit = report["candidates"]["onnxruntime:f32"]["decision"]["criteria"]
    counts = [r for r in crit.values() if r["kind"] != "ap"]
    assert counts and all(r["ref_only"] == r["cand_only"] == 0 for r in counts)
    assert data["verdicts"]["openvino:int8+heading"]["int8"]["keep_heading"] is True


def test_int8_keep_heading_keeps_the_heading_convs_in_float32(guarded):
    wd, _ = guarded
    out = wd / "export" / "step2"
    names = ["backbone/conv1", "head/cls_out", "head/reg_out"]
    assert int8.heading_convs(out / "model.onnx") == names
    block = artifact.read_export(out)["int8"]
    assert block["keep_float"] == [n + r"\b" for n in names]
    ov = pytest.importorskip("openvino")
    model = ov.Core().read_model(str(out / int8.INT8_MODEL))
    quantized = {
        n.get_friendly_name()
        for n in model.get_ordered_ops()
        if n.get_type_name() == "FakeQuantize" or "FakeConvert" in n.get_type_name()
    }
    convs = {  # OpenVINO names a conv with a bias '<onnx name>/WithoutBiases'
        n.get_friendly_name().removesuffix("/WithoutBiases"): n
        for n in model.get_ordered_ops()
        if n.get_type_name() == "Convolution"
    }
    assert quantized and "head/reg_out" in convs and "head/cls_out" in convs

    def weight_quantized(name: str) -> bool:  # an int8 constant behind the conv's weights
        seen = [convs[name].input_value(1).get_node()]
        while seen:
            node = seen.pop()
            if node.get_type_name() == "Constant" and node.get_element_type().get_type_name() in (
                "i8",
                "u8",
            ):
                return True
            seen += [v.get_node() for v in node.input_values()]
        return False

    assert not any(weight_quantized(n) for n in names)
    assert weight_quantized("head/cls_conv1") and weight_quantized("backbone/layer1_0/conv1")


def test_evaluate_says_which_precision_and_what_the_guard_decided(guarded, capsys):
    wd, _ = guarded
    base = ["--task", "detect3d", "--workdir", str(wd)]
    assert evaluate_cli.main([*base, "--runtime", "onnxruntime"]) == 0
    assert "precision: onnxruntime float32; guard: undecided on 4 frames" in capsys.readouterr().out
    heading = ["--precision", "int8", "--int8-keep-heading", "--int8-frames", FRAMES]
    assert evaluate_cli.main([*base, "--runtime", "openvino", *heading]) == 0
    out = capsys.readouterr().out
    assert "precision: openvino int8 (heading kept in float32); guard: undecided" in out
    # other calibration settings: a different int8 model, not the guarded one
    other = ["--precision", "int8", "--int8-keep-heading", "--int8-frames", "2"]
    shutil.rmtree(wd / "eval" / "labeled_step2_openvino_int8")  # results of other settings
    assert evaluate_cli.main([*base, "--runtime", "openvino", *other]) == 0
    assert "not guarded for these weights" in capsys.readouterr().out


def test_the_api_says_what_the_guard_decided(guarded):
    from gac_jax import Detector3D

    wd, _ = guarded
    settings = int8.Int8Settings(frames=int(FRAMES), keep_heading=True)
    det = Detector3D.from_workdir(wd, runtime="openvino", precision="int8", int8=settings)
    line = det.precision_line()
    assert "precision: openvino int8 (heading kept in float32); guard: undecided on 4" in line
    other = int8.Int8Settings(frames=2, keep_heading=True)  # not the guarded int8 model
    line = Detector3D.from_workdir(wd, runtime="openvino", precision="int8", int8=other)
    assert "not guarded for these weights" in line.precision_line()


def test_bad_candidates_are_one_line(capsys, tmp_path):
    for text, words in (
        ("openvino", "RUNTIME:PRECISION"),
        ("openvino:bf16+heading", "only int8"),
        ("jax:f32", "reference"),
    ):
        with pytest.raises(SystemExit) as info:
            guard.main(["--workdir", str(tmp_path), "--candidates", text])
        assert info.value.code == 2 and words in capsys.readouterr().err
    assert guard.main(["--workdir", str(tmp_path), "--candidates", "openvino:f32"]) == 2
    assert "not a trained workdir" in capsys.readouterr().err
    argv = ["--workdir", str(tmp_path), "--candidates", "openvino:f32", "--fp-cap", "0"]
    assert guard.main(argv) == 2
    assert "--fp-cap: must be positive, got 0.0" in capsys.readouterr().err


def replace_checkpoint(workdir, step: int, seed: int) -> None:
    """Model B at model A's step: the checkpoint ``step`` rewritten with other weights (every
    parameter moved by seeded noise), as a run retrained with another seed leaves it."""
    import numpy as np

    from gac_jax.training.checkpointing import Checkpoints

    rng = np.random.default_rng(seed)
    with Checkpoints(workdir) as ckpts:
        state, meta = ckpts.restore_local(step)
    state["params"] = jax.tree.map(
        lambda p: (p + 0.05 * rng.standard_normal(p.shape) * (np.std(p) + 1e-3)).astype(p.dtype),
        state["params"],
    )
    shutil.rmtree(workdir / "checkpoints" / str(step))
    with Checkpoints(workdir) as ckpts:
        ckpts.save(step, state, meta)


def test_retrained_weights_at_the_same_step_get_a_fresh_export_and_no_verdict(
    guarded, tmp_path, capsys
):
    """The identity of an export, a verdict and a result folder is the weights' sha256, not
    the step: model B at model A's step runs B's network in every runtime, is "not guarded",
    and A's result files are not resumed for B."""
    import numpy as np

    from gac_jax import Detector3D
    from gac_jax.trained.fingerprint import weights_sha256
    from gac_jax.training.checkpointing import Checkpoints
    from tests.test_api import labeled_frames

    wd = tmp_path / "wd"
    shutil.copytree(guarded[0], wd)
    export = wd / "export" / "step2"
    a = artifact.read_export(export)
    assert (
        evaluate_cli.main(["--task", "detect3d", "--workdir", str(wd), "--runtime", "onnxruntime"])
        == 0
    )
    assert "guard: undecided on 4 frames" in capsys.readouterr().out

    replace_checkpoint(wd, 2, seed=1)
    with Checkpoints(wd) as ckpts:
        b_sha = weights_sha256(ckpts.restore_variables(2))
    assert b_sha != a["weights"]["sha256"]
    det = Detector3D.from_workdir(wd, runtime="onnxruntime", threads=1)
    out = capsys.readouterr().out
    assert f"exporting again into {export}: the export there was made from other weights" in out
    b = artifact.read_export(export)
    assert b["weights"] == {"step": 2, "sha256": b_sha} and b["sha256"] != a["sha256"]
    line = det.precision_line()
    assert "not guarded for these weights: the verdicts are for other weights" in line
    assert f"these are {b_sha[:12]}" in line
    # ONNX Runtime runs model B: the detections of jax on B, to float32 rounding
    root = Path(json.loads((wd / "config.json").read_text())["data"]["root"])
    _, image, P2 = labeled_frames(root)[0]
    ref, got = Detector3D.from_workdir(wd).predict(image, P2), det.predict(image, P2)
    assert len(ref.scores) == len(got.scores) > 0
    np.testing.assert_allclose(got.scores, ref.scores, atol=1e-3)
    np.testing.assert_allclose(got.locations, ref.locations, atol=1e-2)
    # the result folder of A's onnxruntime run starts again for B
    assert (
        evaluate_cli.main(["--task", "detect3d", "--workdir", str(wd), "--runtime", "onnxruntime"])
        == 0
    )
    out = capsys.readouterr().out
    assert "starting" in out and "its results were made from other weights" in out
    assert "(0 already done)" in out and "not guarded for these weights" in out


def test_a_changed_score_threshold_is_not_guarded(guarded):
    from gac_jax import Detector3D

    det = Detector3D.from_workdir(guarded[0], runtime="onnxruntime", score_threshold=0.3)
    line = det.precision_line()
    assert (
        "not guarded for these weights: decided at score threshold 0.0, this run uses 0.3" in line
    )


def test_the_verdict_records_its_rule_and_look(guarded):
    wd, _ = guarded
    out = wd / "export" / "step2"
    data = verdict_file.read_guard(out)
    entry = data["verdicts"]["onnxruntime:f32"]
    rule = entry["rule"]
    assert rule["version"] == verdict_file.RULE_VERSION and rule["min_score"] == 0.0
    assert rule["score_thresholds"] == [0.0, 0.3, 0.5, 0.7, 0.9] and rule["margin_points"] == 0.5
    assert entry["look"] == 1 and entry["alpha_look"] == 0.025 and len(entry["looks"]) == 1
    assert verdict_file.rule_mismatch(entry, 0.0, 0.5) is None
    assert "score threshold 0.0, this run uses 0.3" in verdict_file.rule_mismatch(entry, 0.3)
    assert "margin 0.5" in verdict_file.rule_mismatch(entry, 0.0, 1.0)
    old = {k: v for k, v in entry.items() if k not in ("rule", "looks")}
    assert "earlier recall-only rule" in verdict_file.rule_mismatch(old, 0.0)
    # the next guard run of this model and candidate is look 2
    looks = verdict_file.previous_looks(out, data["model"], "onnxruntime:f32")
    assert [look["frames"] for look in looks] == [4]
    assert verdict_file.previous_looks(out, {"weights": "other"}, "onnxruntime:f32") == []
