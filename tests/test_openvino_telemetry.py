"""OpenVINO / NNCF usage telemetry is off in gac_jax (gac_jax/deploy/telemetry.py).

On a machine without OpenVINO's consent file, ``import openvino`` and NNCF send usage events
by forking the process from a helper thread (``multiprocessing`` with ``fork``), which can
deadlock a process whose JAX threads run. Each case runs in a fresh interpreter as a user's
program does: not under pytest (NNCF silences itself there), without ``CI=true`` (which
declines consent) and with an empty home folder (no consent file). Forks are counted with
``os.register_at_fork`` until the interpreter's last exit handler, after the telemetry
sender's threads have been joined.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("openvino", reason="deploy extra (openvino) not installed")
pytest.importorskip("nncf", reason="deploy extra (nncf) not installed")

from tests.conftest import REPO_ROOT  # noqa: E402

PREAMBLE = """
import atexit, json, os, sys
forks = []
os.register_at_fork(before=lambda: forks.append(1))
atexit.register(lambda: print(json.dumps({"forks": len(forks)})))  # runs last
"""

BARE = PREAMBLE + "import openvino\n"

THROUGH_GAC_JAX = (
    PREAMBLE
    + """
from pathlib import Path
import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper
from gac_jax.deploy import int8, runtimes

w = np.random.default_rng(0).normal(size=(4, 3, 3, 3)).astype(np.float32)
conv = helper.make_node("Conv", ["x", "w"], ["y"], pads=[1, 1, 1, 1], name="head/conv")
graph = helper.make_graph(
    [conv], "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, 8, 8])],
    [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4, 8, 8])],
    [numpy_helper.from_array(w, "w")])
path = Path(sys.argv[1]) / "conv.onnx"
onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
runtimes.openvino_capabilities()  # the runtime's import
feeds = [{"x": np.random.default_rng(i).normal(size=(1, 3, 8, 8)).astype(np.float32)}
         for i in range(3)]
int8.quantize_model(path, feeds)  # NNCF's import and its quantize events
"""
)


def forks_of(script: str, tmp_path) -> int:
    home = tmp_path / "home"
    home.mkdir(parents=True)
    env = {k: v for k, v in os.environ.items() if k not in ("CI", "TF_BUILD", "JENKINS_URL")}
    env.update(HOME=str(home), PYTHONPATH=str(REPO_ROOT), NNCF_CI="", NNCF_DEV="")
    proc = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])["forks"]


def test_openvino_and_nncf_through_gac_jax_never_fork(tmp_path):
    bare = forks_of(BARE, tmp_path / "bare")
    if bare == 0:
        pytest.skip("this openvino sends no telemetry on import: the case cannot tell")
    assert forks_of(THROUGH_GAC_JAX, tmp_path / "gac") == 0
    assert not (tmp_path / "gac" / "home" / "intel").exists()  # no consent or client-id files
