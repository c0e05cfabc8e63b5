"""Shared pytest fixtures."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from gac_jax.cpu_backend import apply_default_xla_flags

REPO_ROOT = Path(__file__).resolve().parents[1]
# The optional larger sample set beside the repository; GAC_JAX_TEST_SHARED points elsewhere
# (e.g. at a non-existent folder, to check that the suite runs from a fresh clone alone).
SHARED = Path(os.environ.get("GAC_JAX_TEST_SHARED", REPO_ROOT.parent / "shared"))
KITTI_SAMPLES = SHARED / "data" / "kitti_samples"
# Real KITTI frames vendored in the repository (tests/data/kitti/README.md): 4 labelled object
# frames (split ``labeled``) and the KITTI-depth frame.
VENDORED_KITTI = REPO_ROOT / "tests" / "data" / "kitti"


_SESSION_DIRS: list[str] = []
_SESSION_JIT_CACHE = "GAC_JAX_TEST_SESSION_JIT_CACHE"
# Session fixtures that are expensive to build (a trained run folder ...). Under pytest-xdist
# (``-n 2 --dist loadgroup``, the README's test command) every test file that uses one of them
# runs in one worker, which builds it once; every other file runs whole in one worker, so that
# its module fixtures are built once too. A new expensive session fixture goes in here.
SHARED_SESSION_FIXTURES = ("tiny_detect3d_workdir",)
# Files whose tests time other processes (heartbeats, kill-and-exit deadlines; each runs
# several processes): one worker runs them one after another, never two of them at once.
TIMED_PROCESS_FILES = ("test_multihost.py", "test_stopping.py", "test_worker_lifetime.py")


def pytest_configure(config):
    """A fresh embedded-dataset cache and one XLA compilation cache per test session.

    ``GAC_JAX_CACHE`` points at an empty temporary folder, so the suite runs as on a fresh
    machine: it neither reads nor writes the user's ``~/.cache/gac_jax`` (what a test needs
    generated, it generates). Tests compile the same tiny models many times (in-process
    and in the train.py subprocesses of the kill/resume tests); the compilation cache makes
    repeats cheap. Both live in fresh temporary folders (subprocesses inherit them), so no
    state survives the session.
    """
    os.environ["GAC_JAX_CACHE"] = tempfile.mkdtemp(prefix="gac_jax_test_cache_")
    _SESSION_DIRS.append(os.environ["GAC_JAX_CACHE"])
    # Under pytest-xdist each worker process has its own dataset cache (two processes must not
    # generate one dataset folder at once) but all share the controller's compilation cache.
    _JIT_CACHE = os.environ.get(_SESSION_JIT_CACHE) if "PYTEST_XDIST_WORKER" in os.environ else None
    if _JIT_CACHE is None:
        _JIT_CACHE = tempfile.mkdtemp(prefix="gac_jax_test_jit_cache_")
        _SESSION_DIRS.append(_JIT_CACHE)
        os.environ[_SESSION_JIT_CACHE] = _JIT_CACHE  # inherited by the xdist workers
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _JIT_CACHE
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    # Tiny test models compile about twice as fast without XLA's expensive CPU passes;
    # results stay within float tolerance (the tests compare with tolerances anyway).
    flags = os.environ.get("XLA_FLAGS", "")
    for flag in ("--xla_backend_optimization_level=0", "--xla_llvm_disable_expensive_passes=true"):
        if flag.split("=")[0] not in flags:
            flags = f"{flags} {flag}".strip()
    os.environ["XLA_FLAGS"] = flags
    # The entry points' own CPU flags, so that code run in this process compiles exactly
    # like the train.py subprocesses it is compared with (bit-level resume checks).
    apply_default_xla_flags(os.environ)


@pytest.hookimpl(tryfirst=True)  # before xdist's worker reads the marks
def pytest_collection_modifyitems(config, items):
    """Groups the tests for pytest-xdist's ``--dist loadgroup`` (see SHARED_SESSION_FIXTURES);
    a test's own ``xdist_group`` mark wins. Nothing changes without xdist."""
    if not getattr(config.option, "loadgroup", False):  # set in xdist's workers
        return
    files: dict[str, str] = {}
    for item in items:
        path = item.nodeid.split("::")[0]
        shared = [f for f in SHARED_SESSION_FIXTURES if f in getattr(item, "fixturenames", ())]
        if Path(path).name in TIMED_PROCESS_FILES:
            files[path] = "timed_processes"
        elif shared or path not in files:
            files[path] = shared[0] if shared else path
    for item in items:
        if item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(files[item.nodeid.split("::")[0]]))


def pytest_unconfigure(config):
    for path in _SESSION_DIRS:
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="session")
def kitti_samples() -> Path:
    """Root of the vendored real KITTI frames (``tests/data/kitti``): ``object/`` (4 labelled
    frames, split ``labeled``) and ``depth/`` (the KITTI-depth frame)."""
    if not (VENDORED_KITTI / "object" / "training" / "calib").is_dir():
        raise FileNotFoundError(f"vendored KITTI frames missing at {VENDORED_KITTI}")
    return VENDORED_KITTI


@pytest.fixture(scope="session")
def kitti_object_root(kitti_samples: Path) -> Path:
    """KITTI object root of the vendored labelled real frames (split ``labeled``)."""
    return kitti_samples / "object"


@pytest.fixture(scope="session")
def kitti_samples_full() -> Path:
    """The larger optional set ``../shared/data/kitti_samples`` (13 labelled frames, split
    ``labeled``; 5 unlabelled ones, split ``unlabeled``, one with a real right image).

    Only for the few tests that need more than the vendored frames; skips if absent.
    """
    if not (KITTI_SAMPLES / "object" / "training" / "calib").is_dir():
        pytest.skip(
            f"needs the 13-frame / unlabelled KITTI set of ../shared (not found at {KITTI_SAMPLES})"
        )
    return KITTI_SAMPLES


def tiny_train_args(root: Path, workdir: Path) -> list[str]:
    """``train.py`` arguments of the ``:tiny`` detector on the vendored real frames (split
    ``labeled``, left images) in ``workdir``; tests append their own overrides."""
    return [
        "--task",
        "detect3d",
        "--config",
        str(REPO_ROOT / "configs" / "detect3d_default.py:tiny"),
        "--workdir",
        str(workdir),
        "data.source=kitti",
        f"data.root={root}",
        "data.train_split=labeled",
        "data.val_split=labeled",
        "data.use_right_image=False",
    ]


TINY_DETECT3D_OVERRIDES = (
    "data.source=kitti",
    "data.train_split=labeled",
    "data.val_split=labeled",
    "data.use_right_image=False",
    "eval.score_threshold=0.0",
    "eval.num_pictures=2",
)


@pytest.fixture(scope="session")
def tiny_detect3d_workdir(kitti_object_root: Path, tmp_path_factory) -> Path:
    """A detection workdir trained 2 steps (``configs/detect3d_default.py:tiny`` on the vendored
    real frames, score threshold 0), evaluated at the end: ``results/step_2/{data,pictures}``.

    Shared by the inference tests (evaluate.py model mode, gac_jax.cli.predict); treat it as
    read-only (copy it to change it).
    """
    from gac_jax.config import apply_overrides, load_config
    from gac_jax.trainers import detect3d

    config = load_config(str(REPO_ROOT / "configs" / "detect3d_default.py:tiny"))
    overrides = [*TINY_DETECT3D_OVERRIDES, f"data.root={kitti_object_root}", "train.num_steps=2"]
    apply_overrides(config, overrides)
    workdir = tmp_path_factory.mktemp("tiny_detect3d")
    detect3d.train_and_evaluate(config, workdir)
    return workdir


@pytest.fixture(scope="session")
def half_frames(kitti_object_root: Path) -> list:
    """The vendored KITTI frames cut to 368 x 1224 and halved: a stream test's input
    (:func:`tests.stream_cases.half_frames`)."""
    from tests.stream_cases import half_frames

    return half_frames(kitti_object_root)


@pytest.fixture(scope="session")
def half_calib(kitti_object_root: Path, tmp_path_factory) -> Path:
    """The calibration file of :func:`half_frames` (P2 halved)."""
    from tests.stream_cases import write_half_calib

    return write_half_calib(kitti_object_root, tmp_path_factory.mktemp("calib") / "calib.txt")
