"""int8 deployment (gac_jax.deploy.int8): NNCF post-training quantization, end to end.

On the tiny trained detector workdir (real KITTI frames; the training split ``labeled`` is the
calibration split) and a tiny depth U-Net: ``evaluate.py --runtime openvino --precision int8``
quantizes beside the float export and scores the split; ``export.json`` describes the
calibration; the int8 outputs stay close to float32 (tolerance below); a stale or damaged
int8 model is rebuilt, a float32 layer scope that matches nothing is refused, and int8 on a
runtime or CPU that cannot do it is one line. Skipped without the deploy extra or NNCF.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("onnx", reason="deploy extra (onnx) not installed")
pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
pytest.importorskip("nncf", reason="deploy extra (nncf) not installed")

from gac_jax.cli import evaluate as cli  # noqa: E402
from gac_jax.deploy import int8, runtimes  # noqa: E402
from gac_jax.deploy.export import __main__ as export_cli  # noqa: E402
from gac_jax.deploy.export import artifact  # noqa: E402
from gac_jax.trained.run_config import load_run_config  # noqa: E402

FRAMES = 3  # of the 4 vendored frames: the 4th is never seen by the calibration

# int8 vs float32 outputs: RMS(int8 - f32) / RMS(f32) per output and frame. Each 8-bit
# quantizer adds a uniform rounding error of about range / (256 sqrt 12), 0.1 % of the
# tensor's calibrated range; ~25 quantized convs in series, ranges several times the typical
# value and the tiny calibration set (3 frames) give a few per cent (measured: 1-7 %). 0.15
# is twice the worst measured value and far below what a wrong scale or layout gives (>= 1).
RMS_TOLERANCE = 0.15
MIN_CORRELATION = 0.99  # measured >= 0.998


def refused(argv, capsys) -> str:
    """stderr of a command line refused with exit status 2 (argparse or the runtime check)."""
    with pytest.raises(SystemExit) as info:
        cli.main([str(a) for a in argv])
    assert info.value.code == 2
    return capsys.readouterr().err


def relative_rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2) / np.mean(a**2)))


@pytest.fixture(scope="module")
def int8_run(tiny_detect3d_workdir, tmp_path_factory):
    """A copy of the workdir evaluated with ``--runtime openvino --precision int8``."""
    wd = tmp_path_factory.mktemp("int8") / "wd"
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "export"))
    out_json = wd.parent / "ap.json"
    argv = ["--task", "detect3d", "--workdir", str(wd), "--runtime", "openvino"]
    argv += ["--precision", "int8", "--int8-frames", str(FRAMES), "--json", str(out_json)]
    assert cli.main(argv) == 0
    return wd, json.loads(out_json.read_text())


def test_int8_evaluate_end_to_end_describes_the_calibration(int8_run):
    wd, metrics = int8_run
    out = wd / "export" / "step2"
    meta = artifact.read_export(out)
    block = meta["int8"]
    assert block["source_sha256"] == meta["sha256"] and block["preset"] == "mixed"
    cal = block["calibration_frames"]
    assert cal["split"] == "labeled" and cal["frames"] == FRAMES and cal["seed"] == 0
    assert len(cal["frame_ids"]) == FRAMES and cal["transform"].endswith("eval_transform")
    assert set(block["libraries"]) == {"nncf", "openvino"}
    for name, digest in block["sha256"].items():
        assert artifact.sha256_bytes((out / name).read_bytes()) == digest
    assert not list(out.glob(".*"))  # the atomic writes left nothing behind
    result = wd / "eval" / "labeled_step2_openvino_int8"
    assert len(list((result / "data").glob("*.txt"))) == 4
    assert json.loads((result / "run.json").read_text())["int8"]["frames"] == FRAMES
    assert "Car" in metrics["ap40"]


def test_int8_outputs_are_close_to_float32(int8_run):
    wd, _ = int8_run
    out = wd / "export" / "step2"
    config = load_run_config(wd, None, [])
    feeds, described = int8.calibration_frames("detect3d", config, 4, 0)  # all 4 frames
    assert len(described["frame_ids"]) == 4
    kw = {"outputs": runtimes.DETECTOR_OUTPUTS, "image_size": (64, 256), "batch_size": 1}
    f32 = runtimes.OnnxNetwork(out / "model.onnx", "openvino", "f32", **kw)
    q = runtimes.OnnxNetwork(out / int8.INT8_MODEL, "openvino", "int8", **kw)
    assert q.precision_in_effect == "f32"  # the unquantized ops stay float32
    for feed in feeds:
        a, b = f32(*(feed[k] for k in runtimes.INPUTS)), q(*(feed[k] for k in runtimes.INPUTS))
        for key in runtimes.DETECTOR_OUTPUTS:
            assert relative_rms(a[key], b[key]) <= RMS_TOLERANCE, key
            assert np.corrcoef(a[key].ravel(), b[key].ravel())[0, 1] >= MIN_CORRELATION, key


def test_stale_or_damaged_int8_model_is_rebuilt(int8_run, tmp_path, capsys):
    wd = tmp_path / "wd"
    shutil.copytree(int8_run[0], wd, ignore=shutil.ignore_patterns("eval"))
    out = wd / "export" / "step2"
    config = load_run_config(wd, None, [])
    settings = int8.Int8Settings(frames=FRAMES)
    assert int8.ensure_int8(out, "detect3d", config, settings) == out / int8.INT8_MODEL
    assert "quantizing" not in capsys.readouterr().out  # matching: reused
    int8.ensure_int8(out, "detect3d", config, int8.Int8Settings(frames=FRAMES, seed=1))
    assert "int8 model made with other calibration; quantizing" in capsys.readouterr().out
    (out / int8.INT8_WEIGHTS).write_bytes(b"\0" * 64)
    int8.ensure_int8(out, "detect3d", config, int8.Int8Settings(frames=FRAMES, seed=1))
    assert f"{int8.INT8_WEIGHTS} damaged or replaced" in capsys.readouterr().out
    assert artifact.read_export(out)["int8"]["calibration"]["seed"] == 1


def test_export_cli_int8_keeps_a_scope_in_float32(tiny_detect3d_workdir, tmp_path, capsys):
    import openvino as ov

    out = tmp_path / "exp"
    argv = ["--task", "detect3d", "--workdir", tiny_detect3d_workdir, "--out", out]
    argv += ["--precision", "int8", "--int8-frames", 2, "--int8-keep-float", "head/"]
    assert export_cli.main([str(a) for a in argv]) == 0
    assert artifact.read_export(out)["int8"]["keep_float"] == ["head/"]
    model = ov.Core().read_model(str(out / int8.INT8_MODEL))
    quantized = set()  # convolutions with a FakeQuantize on an input (activation or weight)
    for op in model.get_ordered_ops():
        if op.get_type_name() == "Convolution":
            sources = [i.get_source_output().get_node() for i in op.inputs()]
            if any(s.get_type_name() in ("FakeQuantize", "Convert") for s in sources):
                quantized.add(op.get_friendly_name())
    assert any(n.startswith("backbone/") for n in quantized)
    assert not any(n.startswith("head/") for n in quantized)
    # a scope that matches nothing: one line naming the model and the layer names
    argv[-1] = "nope/"
    assert export_cli.main([str(a) for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'nope/' matches no layer" in err and "backbone" in err


def test_int8_depth_network_is_close_to_float32(kitti_samples, tmp_path, capsys):
    from gac_jax.builders import depth as builders
    from gac_jax.config import apply_overrides, load_config
    from gac_jax.deploy.export.sources import depth_source, export_source

    config = load_config("configs/depth_default.py:tiny")
    apply_overrides(
        config,
        ["data.source=kitti", f"data.root={kitti_samples / 'depth'}", "data.crop_height=352"],
    )
    model = builders.build_model(config, 2.5)
    variables = builders.init_variables(model, config, 0)
    out = tmp_path / "depth"
    export_source(depth_source(config, model, variables, step=0), out)
    path = int8.ensure_int8(out, "depth", config, int8.Int8Settings(frames=2))
    assert "quantizing" in capsys.readouterr().out
    size = (config.data.height, config.data.eval_width)
    kw = {"outputs": runtimes.DEPTH_OUTPUTS, "image_size": size, "batch_size": 1}
    f32 = runtimes.OnnxNetwork(out / "model.onnx", "openvino", "f32", **kw)
    q = runtimes.OnnxNetwork(path, "openvino", "int8", **kw)
    feeds, _ = int8.calibration_frames("depth", config, 2, 0)
    for feed in feeds:
        a, b = f32(*(feed[k] for k in runtimes.INPUTS)), q(*(feed[k] for k in runtimes.INPUTS))
        # log depth around log(prior mean): compare the part the network adds to it
        a0, b0 = a["log_depth"] - a["log_depth"].mean(), b["log_depth"] - a["log_depth"].mean()
        assert relative_rms(a0, b0) <= RMS_TOLERANCE


def test_int8_needs_openvino_and_says_so_in_one_line(monkeypatch, tiny_detect3d_workdir, capsys):
    wd = tiny_detect3d_workdir
    argv = ["--task", "detect3d", "--workdir", wd, "--runtime", "onnxruntime"]
    err = refused([*argv, "--precision", "int8"], capsys)
    assert err.count("\n") == 1 and "OpenVINO only" in err
    monkeypatch.setattr(runtimes, "openvino_capabilities", lambda: ["FP32", "BF16"])
    with pytest.raises(runtimes.RuntimeUnavailableError, match="lists no INT8 capability"):
        runtimes.check_runtime("openvino", "int8")
    # a CPU without int8 dot products (no VNNI, no AMX): runs, with one note
    monkeypatch.setattr(runtimes, "openvino_capabilities", lambda: ["FP32", "INT8"])
    flags = {**runtimes.cpu_flags(), "int8_dot": False, "cpu": "Old CPU"}
    monkeypatch.setattr(runtimes, "cpu_flags", lambda: flags)
    note = runtimes.check_runtime("openvino", "int8")
    assert "\n" not in note and "Old CPU" in note and "no int8 dot-product" in note
    with pytest.raises(ValueError, match="--int8-frames must be >= 1"):
        int8.Int8Settings(frames=0)
    err = refused(["--task", "detect3d", "--workdir", wd, "--int8-frames", 3], capsys)
    assert "--int8-frames only applies with --precision int8" in err
