"""Tests of reading PyTorch ``.pth`` files (gac_jax.weights.torch_state_dict), through the
``python -m gac_jax.weights.convert`` command where the exit status and message matter.

Oracle: state dicts of the plain-PyTorch ResNet (tests/torch_reference_models.py) saved with
``torch.save``; truncated and foreign files are made from them.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gac_jax.weights import convert, pretrained
from gac_jax.weights.torch_state_dict import read_torch_state_dict

torch = pytest.importorskip("torch")
from torch_reference_models import TorchResNet  # noqa: E402  (tests/ is on sys.path)

REPO_ROOT = Path(__file__).resolve().parents[1]


def run_cli(argv, capsys):
    status = convert.main([str(a) for a in argv])
    captured = capsys.readouterr()
    return status, captured.out, captured.err


def test_truncated_and_foreign_files_exit_2_without_a_traceback(tmp_path, capsys):
    pth = tmp_path / "r18.pth"
    torch.save(TorchResNet(18, width=8).state_dict(), pth)
    data = pth.read_bytes()
    trunc = tmp_path / "truncated.pth"
    trunc.write_bytes(data[: len(data) // 2])
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "gac_jax.weights.convert",
            "torchvision-resnet",
            str(trunc),
            str(tmp_path / "o"),
        ],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(f"error: {trunc}: cannot read as a PyTorch checkpoint")
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1

    foreign = tmp_path / "optimizer.pth"
    torch.save({"epoch": 3, "optimizer": {"lr": 0.1}}, foreign)
    status, _, err = run_cli(["torchvision-resnet", foreign, tmp_path / "o"], capsys)
    assert status == 2 and "not a state dict" in err and "epoch (int)" in err
    status, _, err = run_cli(["gac", tmp_path / "missing.pth", tmp_path / "o"], capsys)
    assert status == 2 and "file not found" in err
    # a ResNet file given to the GAC command
    status, _, err = run_cli(["gac", pth, tmp_path / "o"], capsys)
    assert status == 2 and "cannot tell" in err


def test_module_prefix_is_stripped_and_missing_torch_is_explained(tmp_path, monkeypatch):
    sd = TorchResNet(18, width=4, fc=False).state_dict()
    pth = tmp_path / "ddp.pth"
    torch.save({"state_dict": {f"module.{k}": v for k, v in sd.items()}}, pth)
    loaded = read_torch_state_dict(pth)
    assert list(loaded) == list(sd)
    assert loaded["layer1.0.bn1.num_batches_tracked"].dtype == np.int64
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(pretrained.WeightsError, match=r"pip install 'gac-jax\[torch\]'"):
        read_torch_state_dict(pth)
