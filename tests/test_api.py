"""The inference API (``from gac_jax import Detector3D, DepthPredictor``) on the tiny trained
workdirs (vendored real KITTI frames).

References: the trainer's own final evaluation of the same checkpoint (its result files, which
``test_evaluate_model`` shows are byte-identical to ``evaluate.py --workdir``'s, and its depth
PNGs, which ``test_train_depth`` shows match ``evaluate.py --task depth``): the API must give
the same lines / maps, through jax and through ONNX Runtime. Also: batch == one by one, the
three stages == predict, one compiled shape for any image size, immutable typed results, and
one named :class:`InputError` per kind of bad input.
"""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from gac_jax.api import (
    PLANE_NORM_TOLERANCE,
    DepthPredictor,
    Detections,
    Detector3D,
    InputError,
)
from gac_jax.data.files import read_depth_png, read_image
from gac_jax.data.kitti import KittiObjectLayout, format_label, read_calib, read_split
from gac_jax.data.sources import KittiDepthSource
from gac_jax.drawing.boxes import draw_detections
from gac_jax.evaluation.depth_evaluator import prediction_relpath, quantize_depth
from gac_jax.geometry import level_plane
from tests.test_runtimes import assert_same_results

REPO = Path(__file__).resolve().parents[1]


def labeled_frames(root: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(frame id, RGB image, P2) of the vendored labelled frames."""
    layout = KittiObjectLayout(root)
    ids = read_split(root / "ImageSets" / "labeled.txt")
    return [(f, read_image(layout.image(f)), read_calib(layout.calib(f)).P2) for f in ids]


@pytest.fixture(scope="module")
def frames(kitti_object_root):
    return labeled_frames(kitti_object_root)


@pytest.fixture(scope="module")
def detector(tiny_detect3d_workdir):
    return Detector3D.from_workdir(tiny_detect3d_workdir, batch_size=2)


def reference_lines(workdir: Path, frame_id: str) -> list[str]:
    return (workdir / "results" / "step_2" / "data" / f"{frame_id}.txt").read_text().splitlines()


def test_import_gac_jax_stays_cheap_and_exports_the_api():
    code = (
        "import sys, gac_jax; assert 'jax' not in sys.modules, 'import gac_jax loaded jax'; "
        "from gac_jax import Detector3D, DepthPredictor, Detections, InputError; "
        "assert issubclass(InputError, ValueError); print(Detector3D.__module__)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "gac_jax.api.detector"


def test_predict_gives_the_evaluation_result_lines(detector, frames, tiny_detect3d_workdir):
    assert detector.class_names == ("Car",) and detector.input_size == (64, 256)
    assert (detector.runtime, detector.precision, detector.step) == ("jax", "f32", 2)
    total = 0
    for fid, image, P2 in frames:
        det = detector.predict(image, P2)
        assert det.to_kitti_lines() == reference_lines(tiny_detect3d_workdir, fid), fid
        total += len(det)
    assert total > len(frames)  # score threshold 0: the check sees real objects
    # predict_batch (3 images: a full chunk of 2 and a padded one) == predict per frame
    sizes = [image[: 300 + 20 * i] for i, (_, image, _) in enumerate(frames[:3])]
    P2s = [P2 for _, _, P2 in frames[:3]]
    batch = detector.predict_batch(sizes, P2s)
    for got, image, P2 in zip(batch, sizes, P2s, strict=True):
        one = detector.predict(image, P2)
        assert got.to_kitti_lines() == one.to_kitti_lines()
        np.testing.assert_array_equal(got.locations, one.locations)
        assert np.all(got.boxes_2d[:, [2, 3]] <= [image.shape[1] - 1, image.shape[0] - 1])
    # the three stages are predict; an explicit level plane at the config's height is None
    _, image, P2 = frames[0]
    prepared = [detector.prepare(image, P2, level_plane(detector.config.model.gac.camera_height))]
    staged = detector.finish(detector.infer(prepared), prepared)[0]
    assert staged.to_kitti_lines() == reference_lines(tiny_detect3d_workdir, frames[0][0])
    # one compiled shape for every image size and batch length seen above, warm-up included
    assert detector.warmup() > 0
    detector.predict(image[:200], P2)  # another image size: the same compiled shape
    assert detector._predict._cache_size() == 1


def test_stages_from_threads_give_the_serial_results(detector, frames):
    """prepare and finish on a thread pool (as a video pipeline runs them), infer meanwhile
    from two threads: the results of serial predict calls."""
    serial = [detector.predict(image, P2).to_kitti_lines() for _, image, P2 in frames]
    with ThreadPoolExecutor(3) as pool:
        prepared = list(pool.map(lambda f: detector.prepare(f[1], f[2]), frames))
        halves = [prepared[:2], prepared[2:]]
        raws = list(pool.map(detector.infer, halves))
        finished = pool.map(
            lambda hr: detector.finish(hr[1], hr[0]), zip(halves, raws, strict=True)
        )
        got = [d.to_kitti_lines() for part in finished for d in part]
    assert got == serial


def test_other_image_sizes_come_back_in_their_own_pixels(detector, frames):
    """A frame whose part below the cropped top rows is upscaled 1.5x (P2 adjusted): the
    network sees the same view up to resampling, and the boxes come back 1.5x larger."""
    _, image, P2 = frames[1]
    top = int(detector.config.data.crop_top)
    h, w = image.shape[:2]
    low = cv2.resize(image[top:], (w * 3 // 2, (h - top) * 3 // 2), interpolation=cv2.INTER_AREA)
    big = np.concatenate([np.zeros((top, low.shape[1], 3), np.uint8), low])
    sx, sy = low.shape[1] / w, low.shape[0] / (h - top)
    A = np.array([[sx, 0, 0], [0, sy, top - sy * top], [0, 0, 1.0]])  # image -> big pixels
    a, b = detector.predict(image, P2), detector.predict(big, A @ P2)
    assert len(a) > 0 and len(b) > 0
    corners = np.stack([a.boxes_2d[:, :2], a.boxes_2d[:, 2:]], axis=1)  # (N, 2, 2) u, v
    mapped = (corners @ A[:2, :2].T + A[:2, 2]).reshape(-1, 4)
    # the best box of the big image is one of the original's, mapped (a few pixels apart)
    assert np.abs(mapped - b.boxes_2d[0]).max(axis=1).min() < 4.0
    np.testing.assert_allclose(
        b.locations[0], a.locations[np.abs(mapped - b.boxes_2d[0]).max(axis=1).argmin()], atol=0.3
    )
    assert detector.prepare(np.concatenate([big, big], axis=1), A @ P2).cut_off
    assert not detector.prepare(big, A @ P2).cut_off


def test_detections_are_typed_immutable_and_convert(detector, frames, tmp_path):
    fid, image, P2 = frames[0]
    det = detector.predict(image, P2)
    n = len(det)
    assert det.names.shape == (n,) and det.boxes_2d.shape == (n, 4)
    assert det.dimensions.shape == det.locations.shape == (n, 3)
    with pytest.raises(ValueError, match="read-only"):
        det.scores[0] = 1.0
    with pytest.raises(AttributeError):
        det.scores = det.scores[:1]
    objects = list(det)
    assert len(objects) == n and objects[0] == det[0]
    assert objects[0].name == "Car" and objects[0].score == det.scores[0]
    assert objects[0].location == tuple(det.locations[0])
    kitti = det.to_kitti_objects()
    assert format_label(kitti, with_score=True).splitlines() == det.to_kitti_lines()
    assert Detections.from_kitti_objects(kitti).to_kitti_lines() == det.to_kitti_lines()
    record = json.loads(json.dumps(det.to_dict()))["objects"][0]
    assert record["name"] == "Car" and record["box_2d"] == list(det[0].box_2d)
    assert set(record) == {
        "name", "score", "box_2d", "dimensions", "location", "rotation_y", "alpha",
    }  # fmt: skip
    drawn = draw_detections(image, P2, kitti)
    assert drawn.shape == image.shape and not np.array_equal(drawn, image)
    assert len(Detections.empty()) == 0 and Detections.empty().to_kitti_lines() == []
    assert repr(det).startswith(f"Detections({n} objects; Car: {n}")


def test_every_bad_input_raises_one_named_input_error(detector, frames, tiny_detect3d_workdir):
    _, image, P2 = frames[0]

    def bad(argument, call, *needles):
        with pytest.raises(InputError) as info:
            call()
        assert info.value.argument == argument, str(info.value)
        assert str(info.value).startswith(f"{argument}: ")
        assert "\n" not in str(info.value)
        for needle in needles:
            assert needle in str(info.value), (needle, str(info.value))

    bad("image", lambda: detector.predict(image.astype(np.float32), P2), "uint8", "float32")
    bad("image", lambda: detector.predict(image[..., 0], P2), "(H, W, 3)")
    bad("image", lambda: detector.predict(np.dstack([image, image[..., :1]]), P2), ", 4)")
    bad("image", lambda: detector.predict(image.tolist(), P2), "numpy", "list")
    bad("image", lambda: detector.predict(image[:5], P2), "at least")  # tiny: crop_top rows
    bad("P2", lambda: detector.predict(image, P2[:, :3]), "(3, 4)", "(3, 3)")
    bad("P2", lambda: detector.predict(image, np.where(P2 == 0, np.nan, P2)), "non-finite")
    bad("P2", lambda: detector.predict(image, "P2"), "(3, 4)")
    bad("plane", lambda: detector.predict(image, P2, [0, -1, 0]), "4 numbers")
    bad("plane", lambda: detector.predict(image, P2, [0, -1, np.inf, 1.65]), "non-finite")
    bad(
        "plane",
        lambda: detector.predict(image, P2, [0, -2, 0, 3.3]),
        "length 2",
        f"tolerance {PLANE_NORM_TOLERANCE:g}",
    )
    bad("plane", lambda: detector.predict(image, P2, [0, 1, 0, -1.65]), "point up")
    detector.predict(image, P2, [0, -1 - 0.5 * PLANE_NORM_TOLERANCE, 0, 1.65])  # within
    for d in (0.0, -1.65):  # the ground through or above the camera
        bad("plane", lambda d=d: detector.predict(image, P2, [0, -1, 0, d]), "above the ground")
    # 4000 x 10: resized to the input height it would have no column (cv2.error before)
    tall = np.zeros((4000, 10, 3), np.uint8)
    bad("image", lambda: detector.predict(tall, P2), "4000x10", "0 pixels wide")
    flat = P2.copy()
    flat[2] = 0  # numpy's LinAlgError before
    bad("P2", lambda: detector.predict(image, flat), "singular")
    bad("P2s[0]", lambda: detector.predict_batch([image], [flat]), "singular")
    outside = P2.copy()
    outside[0, 2] = image.shape[1] + 100  # the principal point right of the image
    bad("P2", lambda: detector.prepare(image, outside), "does not fit", "outside")
    bad("P2s", lambda: detector.predict_batch([image, image], [P2]), "1 projection", "2 images")
    bad("planes", lambda: detector.predict_batch([image], [P2], [None, None]), "2 planes")
    bad("images[1]", lambda: detector.predict_batch([image, image[..., :2]], [P2, P2]), "RGB")
    bad("images", lambda: detector.predict_batch(image, [P2]), "sequence of images")
    bad("prepared", lambda: detector.infer([]), "non-empty")
    wd = tiny_detect3d_workdir
    bad("workdir", lambda: Detector3D.from_workdir(wd / "missing"), "not a folder")
    bad("workdir", lambda: Detector3D.from_workdir(REPO / "tests"), "config.json")
    bad("step", lambda: Detector3D.from_workdir(wd, step=7), "no checkpoint step 7", "[2]")
    bad("step", lambda: Detector3D.from_workdir(wd, step=-1), "integer >= 0")
    bad("runtime", lambda: Detector3D.from_workdir(wd, runtime="tensorrt"), "jax, onnxruntime")
    bad("precision", lambda: Detector3D.from_workdir(wd, precision="fp16"), "f32, bf16, int8")
    bad(
        "precision",
        lambda: Detector3D.from_workdir(wd, runtime="onnxruntime", precision="int8"),
        "OpenVINO",
    )
    bad("threads", lambda: Detector3D.from_workdir(wd, threads=1), "taskset")
    bad("batch_size", lambda: Detector3D.from_workdir(wd, batch_size=0), ">= 1")
    bad("score_threshold", lambda: Detector3D.from_workdir(wd, score_threshold="x"), "number")
    bad("weights", lambda: Detector3D.from_weights(wd / "nope", "x.py"), "not found")


def test_score_threshold_and_converted_weights(tiny_detect3d_workdir, frames, tmp_path):
    """``score_threshold`` filters like the config's; converted weights + config give the
    workdir's results (priors computed into the given workdir)."""
    from gac_jax.training.checkpointing import Checkpoints
    from gac_jax.weights import pretrained
    from tests.conftest import TINY_DETECT3D_OVERRIDES

    fid, image, P2 = frames[0]
    with pytest.warns(UserWarning, match="XLA:CPU has no native bf16"):
        bf16 = Detector3D.from_workdir(tiny_detect3d_workdir, precision="bf16")
    assert bf16._detector.model.dtype == jnp.bfloat16 and bf16.precision == "bf16"
    det = Detector3D.from_workdir(tiny_detect3d_workdir, score_threshold=0.5)
    kept = det.predict(image, P2)
    assert det.config.eval.score_threshold == 0.5 and np.all(kept.scores > 0.5)
    with Checkpoints(tiny_detect3d_workdir) as ckpts:
        variables = ckpts.restore_variables()
    weights = tmp_path / "weights"
    pretrained.save_converted(weights, variables, {"kind": "gac_detector", "model": {}})
    from gac_jax.config import apply_overrides, load_config

    config = load_config(str(REPO / "configs" / "detect3d_default.py:tiny"))
    root = tiny_detect3d_workdir  # the fixture's data root is in its config.json
    apply_overrides(config, [*TINY_DETECT3D_OVERRIDES, f"data.root={_data_root(root)}"])
    converted = Detector3D.from_weights(weights, config, workdir=tmp_path / "wd")
    assert converted.step is None and (tmp_path / "wd" / "anchor_priors.npz").is_file()
    lines = converted.predict(image, P2).to_kitti_lines()
    assert lines == reference_lines(tiny_detect3d_workdir, fid)


def _data_root(workdir: Path) -> str:
    return json.loads((workdir / "config.json").read_text())["data"]["root"]


def test_exported_runtimes_give_the_jax_lines(tiny_detect3d_workdir, frames, tmp_path):
    """ONNX Runtime (exporting on first use) and OpenVINO (reusing that export) give the
    evaluation's result lines to their printed precision."""
    pytest.importorskip("onnxruntime", reason="deploy extra not installed")
    wd = tmp_path / "wd"  # the export is written into the workdir: a copy
    shutil.copytree(tiny_detect3d_workdir, wd, ignore=shutil.ignore_patterns("eval", "export"))
    images = [image for _, image, _ in frames]
    P2s = [P2 for _, _, P2 in frames]
    ref = tmp_path / "ref"
    ref.mkdir()
    for fid, _, _ in frames:
        shutil.copy(wd / "results" / "step_2" / "data" / f"{fid}.txt", ref)
    runtimes = ["onnxruntime"]
    if importlib.util.find_spec("openvino") is not None:
        runtimes.append("openvino")
    for runtime in runtimes:
        det = Detector3D.from_workdir(wd, runtime=runtime, threads=1, batch_size=2)
        assert (wd / "export" / "step2" / "model.onnx").is_file()
        assert det.runtime == runtime and det.load_s > 0
        out = tmp_path / runtime
        out.mkdir()
        for (fid, _, _), got in zip(frames, det.predict_batch(images, P2s), strict=True):
            (out / f"{fid}.txt").write_text("".join(f"{ln}\n" for ln in got.to_kitti_lines()))
        assert_same_results(out, ref)  # to the printed precision
        one = det.predict(images[0], P2s[0])
        assert one.to_kitti_lines() == (out / f"{frames[0][0]}.txt").read_text().splitlines()


# ----------------------------------------------------------------------------- depth


@pytest.fixture(scope="module")
def depth_workdir(kitti_samples, tmp_path_factory) -> Path:
    """A depth workdir trained 2 steps, evaluated at the end (``results/step_2/depth``)."""
    from gac_jax.trainers import depth
    from tests.test_train_depth import tiny_config

    config = tiny_config(kitti_samples / "depth", "train.num_steps=2")
    workdir = tmp_path_factory.mktemp("api_depth")
    depth.train_and_evaluate(config, workdir)
    return workdir


def test_depth_equals_the_evaluation_pngs(depth_workdir, kitti_samples):
    net = DepthPredictor.from_workdir(depth_workdir, batch_size=2)
    assert net.step == 2 and net.input_size == (64, 256)
    source = KittiDepthSource(kitti_samples / "depth", "train", (2, 3))
    samples = [source[i] for i in range(len(source))]
    assert len(samples) == 2
    batch = net.predict_batch(
        [s["image"] for s in samples], [s["P2"] for s in samples], [s.get("plane") for s in samples]
    )
    for sample, depth in zip(samples, batch, strict=True):
        one = net.predict(sample["image"], sample["P2"], sample.get("plane"))
        assert depth.shape == sample["image"].shape[:2] and depth.dtype == np.float32
        np.testing.assert_array_equal(depth, one)
        png = prediction_relpath(sample["frame_id"], sample["camera"])
        written = read_depth_png(depth_workdir / "results" / "step_2" / "depth" / png)
        # the PNG is round(256 z): the same value, or one step off where XLA rounds otherwise
        steps = np.abs(quantize_depth(depth).astype(np.int64) - np.round(written * 256))
        assert steps.max() <= 1 and steps.mean() < 0.01, (steps.max(), steps.mean())
    assert net.warmup() > 0
    assert net._predictor._predict._cache_size() == 1
    # the plane is a live input: a tilted road changes the map, the level one does not
    s = samples[0]
    level = net.predict(s["image"], s["P2"], level_plane(net.config.model.gac.camera_height))
    np.testing.assert_array_equal(level, net.predict(s["image"], s["P2"]))
    tilt = np.array([0.0, -np.cos(0.05), np.sin(0.05), 1.2])  # a pitched camera, lower
    changed = np.abs(np.log(net.predict(s["image"], s["P2"], tilt)) - np.log(level))
    assert changed.max() > 0  # (barely: the 2-step network hardly uses it yet)
    np.testing.assert_array_equal(
        net.prepare(s["image"], s["P2"], tilt).arrays["plane"], tilt.astype(np.float32)
    )
    assert np.isnan(net.prepare(s["image"], s["P2"]).arrays["plane"]).all()  # the model's level
    with pytest.raises(InputError, match="^P2: "):
        net.predict(s["image"], s["P2"][:2])
    with pytest.raises(InputError, match="^step: "):
        DepthPredictor.from_workdir(depth_workdir, step=5)


def test_a_workdir_of_the_other_task_is_named(depth_workdir, tiny_detect3d_workdir):
    with pytest.raises(InputError, match="^workdir: .*not a detector run"):
        Detector3D.from_workdir(depth_workdir)
    with pytest.raises(InputError, match="^workdir: .*prior_mean.json"):
        DepthPredictor.from_workdir(tiny_detect3d_workdir)
