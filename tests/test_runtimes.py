"""Deployment runtimes end to end on the tiny trained detector workdir (real KITTI frames).

``evaluate.py --runtime onnxruntime`` must write the result files of the jitted path (the
trainer's final evaluation of the same checkpoint, which ``test_evaluate_model`` shows is
byte-identical to ``evaluate.py --runtime jax``) to their printed precision; the export CLI
writes a described, checksummed folder; corrupted, mismatched and stale exports and
unsupported precisions fail with one clear line. Skipped without the deploy extra.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnx", reason="deploy extra (onnx) not installed")
pytest.importorskip("onnxruntime", reason="deploy extra (onnxruntime) not installed")

from gac_jax.cli import evaluate as cli  # noqa: E402
from gac_jax.data.files import KittiFormatError  # noqa: E402
from gac_jax.deploy import runtimes  # noqa: E402
from gac_jax.deploy.export import __main__ as export_cli  # noqa: E402
from gac_jax.deploy.export import artifact  # noqa: E402
from gac_jax.trained.fingerprint import weights_sha256  # noqa: E402
from gac_jax.training.checkpointing import Checkpoints  # noqa: E402

PRINTED = 0.01 + 1e-9  # result files print 2 decimals


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def flatten(tree, prefix: str = "") -> dict:
    if isinstance(tree, dict):
        return {
            k: v for key, sub in tree.items() for k, v in flatten(sub, f"{prefix}/{key}").items()
        }
    return {prefix: np.asarray(tree, float)}


def assert_same_results(mine: Path, reference: Path) -> None:
    ref = {p.name: p.read_text().split("\n") for p in sorted(reference.glob("*.txt"))}
    got = {p.name: p.read_text().split("\n") for p in sorted(mine.glob("*.txt"))}
    assert got.keys() == ref.keys() and len(ref) >= 4
    assert sum(len(lines) for lines in ref.values()) > 2 * len(ref)
    for name, lines in ref.items():
        assert len(got[name]) == len(lines), name
        for a, b in zip(got[name], lines, strict=True):
            ta, tb = a.split(), b.split()
            assert len(ta) == len(tb) and ta[:1] == tb[:1], (name, a, b)
            va, vb = np.array(ta[1:], float), np.array(tb[1:], float)
            assert np.abs(va - vb).max(initial=0.0) <= PRINTED, (name, a, b)


@pytest.fixture(scope="module")
def onnx_run(tiny_detect3d_workdir, tmp_path_factory):
    """A copy of the workdir evaluated once with ``--runtime onnxruntime``."""
    wd = tmp_path_factory.mktemp("runtimes") / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval"))
    out_json = wd.parent / "ap.json"
    code = cli.main(
        ["--task", "detect3d", "--workdir", str(wd), "--runtime", "onnxruntime"]
        + ["--json", str(out_json)]
    )
    assert code == 0
    return wd, json.loads(out_json.read_text())


def test_onnxruntime_writes_the_jax_result_files(onnx_run):
    wd, metrics = onnx_run
    trainer = wd / "results" / "step_2"
    assert_same_results(wd / "eval" / "labeled_step2_onnxruntime_f32" / "data", trainer / "data")
    reference = json.loads((trainer / "metrics.json").read_text())["metrics"]
    metrics = dict(metrics)
    assert set(metrics.pop("_meta")["min_overlap"]) == set(reference["ap40"])  # --json's overlaps
    assert flatten(metrics).keys() == flatten(reference).keys()
    for key, value in flatten(reference).items():
        np.testing.assert_allclose(flatten(metrics)[key], value, atol=0.02, err_msg=key)
    meta = json.loads((wd / "export" / "step2" / "export.json").read_text())
    with Checkpoints(wd) as ckpts:  # the export is bound to the weights' contents
        sha = weights_sha256(ckpts.restore_variables(2))
    assert meta["weights"] == {"step": 2, "sha256": sha} and meta["task"] == "detect3d"
    assert meta["input_size"] == [64, 256] and meta["opset"] == artifact.DEFAULT_OPSET


def test_export_cli_writes_a_described_checksummed_model(tiny_detect3d_workdir, tmp_path, capsys):
    out = tmp_path / "exp"
    argv = ["--task", "detect3d", "--workdir", tiny_detect3d_workdir, "--out", out]
    assert export_cli.main([str(a) for a in argv]) == 0
    meta = artifact.read_export(out)  # checks the sha256
    assert meta["source"]["step"] == 2 and meta["inputs"]["P2"] == ["batch", 3, 4]
    assert meta["inputs"]["plane"] == ["batch", 4]
    assert meta["decoding"]["num_anchors"] > 0 and meta["libraries"]["onnx"] != "not installed"
    assert not list(out.glob(".*tmp"))  # atomic writes leave no temporary file


def test_corrupted_and_stale_exports_are_refused(onnx_run, tmp_path, capsys):
    wd = tmp_path / "wd"  # the run with its export, without its results
    shutil.copytree(onnx_run[0], wd, ignore=shutil.ignore_patterns("eval"))
    exported = wd / "export" / "step2"
    argv = ["--task", "detect3d", "--workdir", wd, "--runtime", "onnxruntime"]
    # stale: the config changes the network (GAC camera height)
    code, _, err = run([*argv, "model.gac.camera_height=1.8"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"{exported / 'model.onnx'}: stale export" in err
    assert "network_config.model.gac.camera_height (export: 1.65, run: 1.8)" in err
    # corrupted: a truncated model.onnx
    data = (exported / "model.onnx").read_bytes()
    (exported / "model.onnx").write_bytes(data[: len(data) // 2])
    code, _, err = run(argv, capsys)
    assert code == 2 and err.count("\n") == 1
    assert f"{exported / 'model.onnx'}: corrupted or replaced" in err


def test_check_export_names_another_step():
    meta = {"task": "detect3d", "weights": {"step": 2}, "input_size": [64, 256]}
    meta["network_config"] = {"model": {"a": 1}}
    expected = {**meta, "weights": {"step": 4}}
    with pytest.raises(KittiFormatError, match=r"weights.step \(export: 2, run: 4\)"):
        artifact.check_export("dir", meta, expected)


def test_mismatched_model_file_is_named(onnx_run, tmp_path):
    model = onnx_run[0] / "export" / "step2" / "model.onnx"
    with pytest.raises(KittiFormatError, match=r"model input is 64x256, the run feeds 32x128"):
        runtimes.OnnxNetwork(
            model, "onnxruntime", outputs=runtimes.DETECTOR_OUTPUTS, image_size=(32, 128)
        )
    with pytest.raises(KittiFormatError, match="lack log_depth"):
        runtimes.OnnxNetwork(
            model, "onnxruntime", outputs=runtimes.DEPTH_OUTPUTS, image_size=(64, 256)
        )
    garbage = tmp_path / "model.onnx"
    garbage.write_bytes(b"not a protobuf at all")
    with pytest.raises(KittiFormatError, match=f"{garbage}: onnxruntime cannot load it"):
        runtimes.OnnxNetwork(
            garbage, "onnxruntime", outputs=runtimes.DETECTOR_OUTPUTS, image_size=(64, 256)
        )


def test_openvino_float32_matches_onnxruntime(onnx_run):
    pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
    model = onnx_run[0] / "export" / "step2" / "model.onnx"
    kw = {"outputs": runtimes.DETECTOR_OUTPUTS, "image_size": (64, 256)}
    ort_net = runtimes.OnnxNetwork(model, "onnxruntime", **kw)
    ov_net = runtimes.OnnxNetwork(model, "openvino", "f32", batch_size=2, **kw)
    assert ov_net.precision_in_effect == "f32"
    images = np.random.default_rng(0).normal(size=(2, 64, 256, 3)).astype(np.float32)
    P2 = np.tile(
        np.array([[700, 0, 128, 45], [0, 700, 16, 0], [0, 0, 1, 0]], np.float32), (2, 1, 1)
    )
    plane = np.float32([[0.0, -0.94, -0.34, 1.6], [0.0, -1.0, 0.0, 1.65]])  # pitched, level
    plane[:, :3] /= np.linalg.norm(plane[:, :3], axis=1, keepdims=True)
    a, b = ort_net(images, P2, plane), ov_net(images, P2, plane)
    for key in runtimes.DETECTOR_OUTPUTS:
        scale = np.abs(a[key]).max()
        assert np.abs(a[key] - b[key]).max() <= 1e-4 * scale, key


def test_bf16_without_native_support_is_one_line(monkeypatch):
    with pytest.raises(runtimes.RuntimeUnavailableError, match="ONNX Runtime's CPU provider"):
        runtimes.check_runtime("onnxruntime", "bf16")
    if runtimes.importlib.util.find_spec("openvino") is not None:
        monkeypatch.setattr(runtimes, "openvino_capabilities", lambda: ["FP32", "INT8"])
        with pytest.raises(runtimes.RuntimeUnavailableError) as info:
            runtimes.check_runtime("openvino", "bf16")
        assert "no native bf16 support" in str(info.value) and "\n" not in str(info.value)
    note = runtimes.check_runtime("jax", "bf16")
    assert "XLA:CPU" in note and "\n" not in note


def test_predict_with_openvino_gives_the_jax_results(onnx_run, kitti_object_root, tmp_path, capsys):
    """``python -m gac_jax.cli.predict --runtime openvino`` (float32, batch 3: the last batch is
    padded) on the training images, reusing the run's export: the trainer's results."""
    pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
    from gac_jax.cli import predict

    wd, out = onnx_run[0], tmp_path / "out"
    images = kitti_object_root / "training" / "image_2"
    argv = [
        *("--workdir", wd, images, "--out", out, "--batch-size", 3, "--no-images"),
        *("--runtime", "openvino", "--precision", "f32"),
    ]
    code = predict.main([str(a) for a in argv])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    assert "openvino f32" in stdout and "exported" not in stdout  # the existing export
    assert_same_results(out / "data", wd / "results" / "step_2" / "data")
