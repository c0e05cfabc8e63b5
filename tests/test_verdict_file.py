"""Which verdict applies to a run (gac_jax.guard.verdict_file), on toy export folders: an
int8 verdict holds only for the int8 model it was decided for, whatever that model was
calibrated on, and a verdict of an earlier rule is re-decided. No runtime is needed."""

from __future__ import annotations

import pytest

from gac_jax.deploy.export import artifact
from gac_jax.deploy.int8 import Int8Settings
from gac_jax.guard import verdict_file as gv

ONNX = b"a toy exported graph"
SHA = "5" * 64
CALIBRATION = {"split": "train", "data_root": "/data/G", "frames": 16, "seed": 0}


def _export(folder, calibration: dict, ir_sha256: str | None) -> None:
    """A toy export folder whose ``export.json`` describes an int8 model (not written)."""
    block = {
        "source_sha256": artifact.sha256_bytes(ONNX),
        "calibration": calibration,
        "keep_float": [],
        "ir_sha256": ir_sha256,
    }
    artifact.write_export(folder, ONNX, {"int8": block})


def _guard(folder, version: int = gv.RULE_VERSION) -> None:
    settings = Int8Settings()
    network = gv.network_identity(folder, "openvino", "int8", settings)
    rule = {"version": version, "min_score": 0.0, "margin_points": 0.5}
    entry = gv.verdict_entry(
        "openvino", "int8", settings, network, verdict="within", reason="toy", frames=4000,
        created="2026-12-01", rule=rule,
    )  # fmt: skip
    model = gv.model_identity(folder, "step5", SHA)
    gv.write_guard(folder, model, rule, {"openvino:int8": entry})


def _status(folder) -> tuple[str, str]:
    status, _, why = gv.verdict_for(folder, "step5", SHA, "openvino", "int8", Int8Settings())
    return status, why


@pytest.mark.parametrize(
    "changed, words",
    [
        ({"data_root": "/data/other"}, "data_root '/data/G' -> '/data/other'"),
        ({"split": "val"}, "split 'train' -> 'val'"),
        ({"seed": 3}, "seed 0 -> 3"),
    ],
)
def test_a_recalibrated_int8_model_is_not_guarded(tmp_path, changed, words):
    _export(tmp_path, CALIBRATION, "a" * 64)
    _guard(tmp_path)
    assert _status(tmp_path) == ("within", "")
    # the folder's int8 model rebuilt from other calibration frames (evaluate.py on a run
    # whose data root or split moved): another IR, not the one the verdict was decided for
    _export(tmp_path, CALIBRATION | changed, "b" * 64)
    status, why = _status(tmp_path)
    assert status == "not guarded", why
    assert why.startswith("the int8 model differs from the one guarded: calibrated otherwise")
    assert words in why


def test_the_int8_model_itself_decides_not_its_recipe(tmp_path):
    _export(tmp_path, CALIBRATION, "a" * 64)
    _guard(tmp_path)
    # the same recipe, another IR (a replaced file): not guarded
    _export(tmp_path, CALIBRATION, "c" * 64)
    assert _status(tmp_path) == (
        "not guarded",
        "the int8 model differs from the one guarded: its IR's sha256 differs",
    )
    # another recipe that came out as the very same IR: the guarded network runs
    _export(tmp_path, CALIBRATION | {"data_root": "/data/copy"}, "a" * 64)
    assert _status(tmp_path) == ("within", "")
    # no int8 model described: not guarded
    _export(tmp_path, CALIBRATION, None)
    assert _status(tmp_path)[1].endswith("no int8 model in the export folder")


def test_a_verdict_of_the_earlier_rule_is_re_decided(tmp_path):
    _export(tmp_path, CALIBRATION, "a" * 64)
    _guard(tmp_path, version=2)
    status, why = _status(tmp_path)
    assert status == "not guarded"
    assert why.startswith("decided under the earlier rule, whose intervals did not hold")
    assert why.endswith("python -m gac_jax.cli.guard re-decides")
    # the depth guard's rule did not change: its version-2 verdicts stand
    depth = {"rule": {"version": gv.DEPTH_RULE_VERSION, "margin_silog": 0.2}}
    assert gv.rule_mismatch(depth) is None
    assert "recall-only" in gv.rule_mismatch({"rule": {"version": 1, "margin_points": 0.5}})
