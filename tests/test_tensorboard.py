"""TensorBoard event files: written without TensorFlow, read back with TensorBoard's own reader."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("tensorboard")  # a dependency of the project (pyproject.toml)
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # noqa: E402

from gac_jax.training.metrics_writer import MetricsWriter  # noqa: E402
from gac_jax.training.tensorboard_writer import TensorBoardWriter, flatten_scalars  # noqa: E402


def read(logdir) -> EventAccumulator:
    acc = EventAccumulator(str(logdir), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    return acc


def test_flatten_names_kitti_difficulties_and_skips_text():
    values = {
        "metrics": {"ap40": {"Car": {"0.70": {"3d": [1.0, 2.0, 3.0]}}}, "silog": 14.2},
        "timings": {"model": 0.5},
        "num_frames": 13,
        "note": "text",
        "sizes": [4, 5, 6],
        "missing": None,
    }
    assert flatten_scalars(values, "eval") == {
        "eval/metrics/ap40/Car/0.70/3d/easy": 1.0,
        "eval/metrics/ap40/Car/0.70/3d/moderate": 2.0,
        "eval/metrics/ap40/Car/0.70/3d/hard": 3.0,
        "eval/metrics/silog": 14.2,
        "eval/timings/model": 0.5,
        "eval/num_frames": 13.0,
        "eval/sizes/0": 4.0,
        "eval/sizes/1": 5.0,
        "eval/sizes/2": 6.0,
    }


def test_scalars_images_and_resume_read_back(tmp_path):
    writer = MetricsWriter(tmp_path, tensorboard=True)
    for step in range(1, 6):
        writer.write(step, loss=1.0 / step, lr=0.1)
    image = np.zeros((6, 8, 3), np.uint8)
    image[..., 0] = 255  # red
    writer.tensorboard.image(5, "eval/pictures/red", image)
    writer.close()
    acc = read(tmp_path / "tensorboard")
    assert {"train/loss", "train/lr"} <= set(acc.Tags()["scalars"])
    assert [e.step for e in acc.Scalars("train/loss")] == [1, 2, 3, 4, 5]
    np.testing.assert_allclose([e.value for e in acc.Scalars("train/loss")], 1 / np.arange(1, 6))
    (picture,) = acc.Images("eval/pictures/red")
    assert (picture.width, picture.height) == (8, 6)
    import cv2

    decoded = cv2.imdecode(np.frombuffer(picture.encoded_image_string, np.uint8), 1)
    np.testing.assert_array_equal(decoded[..., ::-1], image)  # BGR on disk -> RGB

    # Resumed from step 3: the steps the interrupted run wrote after it are discarded.
    writer = MetricsWriter(tmp_path, resume_step=3, tensorboard=True)
    for step in (4, 5):
        writer.write(step, loss=10.0 * step)
    writer.close()
    acc = read(tmp_path / "tensorboard")
    loss = {e.step: e.value for e in acc.Scalars("train/loss")}
    assert loss == pytest.approx({1: 1.0, 2: 0.5, 3: 1 / 3, 4: 40.0, 5: 50.0})


def test_no_tensorflow_or_torch_is_imported(tmp_path):
    code = (
        "import sys\n"
        "from gac_jax.training.tensorboard_writer import TensorBoardWriter\n"
        f"w = TensorBoardWriter({str(tmp_path)!r}); w.scalars(1, {{'a': 1.0}}); w.close()\n"
        "bad = [m for m in ('tensorflow', 'torch') if m in sys.modules]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_training_writes_curves_and_evaluation_pictures(tiny_detect3d_workdir):
    """The shared tiny run (2 steps, evaluated at the end) has its curves and pictures."""
    acc = read(tiny_detect3d_workdir / "tensorboard")
    scalars = set(acc.Tags()["scalars"])
    expected = {
        "train/loss",
        "train/lr",
        "train/images_per_s",
        "compile/compile_s",
        "compile/memory_bytes/total",
        "train/data_wait",
        "eval/metrics/ap40/Car/0.70/3d/moderate",
        "eval/metrics/ap11/Car/0.70/bbox/easy",
    }
    assert expected <= scalars, expected - scalars
    assert [e.step for e in acc.Scalars("train/loss")] == [1, 2]
    assert [e.step for e in acc.Scalars("eval/metrics/ap40/Car/0.70/3d/moderate")] == [2]
    images = acc.Tags()["images"]
    assert "eval/pictures/grid" in images and len(images) >= 2
    assert acc.Images(images[0])[0].step == 2


def test_writer_refuses_non_images(tmp_path):
    writer = TensorBoardWriter(tmp_path)
    with pytest.raises(ValueError, match="uint8"):
        writer.image(0, "x", np.zeros((4, 4, 3), np.float32))
    writer.close()
