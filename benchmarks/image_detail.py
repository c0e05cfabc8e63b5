"""How much fine detail and contrast real and generated frames hold, as the network sees them.

A detector trained on generated frames meets real ones whose pixels have other statistics. This
prints, for the band of rows around the horizon (where the default detector's false positives
on real frames lie), at the network's input size (the config's test transform: crop the top,
resize, crop the width):

* detail at three scales: the mean absolute difference of Gaussians of the grey image at
  about 1, 2-4 and 4-8 pixels (grey levels);
* contrast: the standard deviation of the grey band;

and what the camera effects cost per image on one thread (median ms).

Medians over the real labelled KITTI frames of ``../shared`` and over generated frames, as
written and after the training's camera effects (``data.camera_effects`` and, if the config
turns it on, or ``--sharpen-contrast on``, ``data.sharpen_contrast``).

    python benchmarks/image_detail.py [--generated DIR] [--frames 60] [--config C]
        [--sharpen-contrast config|on|off]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from gac_jax.builders.datasets import synthetic_dataset_dir  # noqa: E402
from gac_jax.builders.detect3d import eval_transform  # noqa: E402
from gac_jax.config import load_config  # noqa: E402
from gac_jax.data import camera_effects  # noqa: E402

BAND = (0.125, 0.47)  # rows of the network input around the horizon (KITTI: rows 120-175)
SCALES = (0.0, 1.0, 2.0)  # difference of Gaussians: sigma s against 2 s (s = 0: the pixel)


def statistics(image: np.ndarray) -> np.ndarray:
    """(4,) detail at three scales and contrast of an (H, W, 3) RGB image's horizon band."""
    grey = cv2.cvtColor(np.clip(image, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
    h = grey.shape[0]
    band = grey[int(BAND[0] * h) : int(BAND[1] * h)].astype(np.float32)
    out = []
    for s in SCALES:
        fine = cv2.GaussianBlur(band, (0, 0), s) if s else band
        coarse = cv2.GaussianBlur(band, (0, 0), max(2.0 * s, 1.0))
        out.append(float(np.abs(fine - coarse).mean()))
    return np.array([*out, float(band.std())])


def network_view(path: Path, transform) -> np.ndarray:
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
    sample = {"image": image, "P2": np.eye(3, 4), "image_transform": np.eye(3)}
    return np.asarray(transform(sample)["image"], np.float32)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--samples", type=Path, default=REPO.parent / "shared/data/kitti_samples")
    p.add_argument("--generated", type=Path, help="a generated dataset (default: the config's)")
    p.add_argument("--frames", type=int, default=60, help="generated frames to measure")
    p.add_argument("--config", default=str(REPO / "configs/detect3d_default.py"))
    p.add_argument(
        "--sharpen-contrast",
        choices=("config", "on", "off"),
        default="config",
        help="contrast and sharpening in the camera effects: as the config says, or on / off",
    )
    p.add_argument("--draws", type=int, default=2, help="camera-effect draws per frame")
    args = p.parse_args()
    config = load_config(args.config)
    if args.sharpen_contrast != "config":
        config.data.sharpen_contrast = args.sharpen_contrast == "on"
    transform = eval_transform(config, normalize=False)
    real_dir = args.samples / "object" / "training" / "image_2"
    real = sorted(real_dir.glob("*.png"))
    if not real:
        sys.exit(f"{real_dir}: no real frames (the real KITTI samples are not beside the repo)")
    gen_root = args.generated or synthetic_dataset_dir(config.data)
    generated = sorted((gen_root / "training" / "image_2").glob("*.png"))[: args.frames]
    if not generated:
        sys.exit(f"{gen_root}: no generated frames (run train.py once, or pass --generated)")
    print(one_line(describe_machine("numpy", "cv2")))
    effects = camera_effects.from_config(config.data)
    rng = np.random.default_rng(0)
    gen_views = [network_view(f, transform) for f in generated]
    rows = {
        f"real KITTI frames ({len(real)})": [statistics(network_view(f, transform)) for f in real],
        f"generated ({len(generated)} frames)": [statistics(v) for v in gen_views],
        "generated + camera effects of the config": [
            statistics(effects({"image": v, "rng": rng})["image"])
            for v in gen_views
            for _ in range(args.draws)
        ],
    }
    print(f"generated frames: {gen_root}")
    print(f"horizon band of the {config.data.height}x{config.data.width} network input, medians")
    print(f"{'':44s} {'detail 1px':>10s} {'2-4px':>7s} {'4-8px':>7s} {'contrast':>9s}")
    for name, values in rows.items():
        m = np.median(np.array(values), axis=0)
        print(f"{name:44s} {m[0]:10.2f} {m[1]:7.2f} {m[2]:7.2f} {m[3]:9.2f}")
    print(f"camera effects: {effects}")
    # what the effects cost a loader worker per network-size image (one thread)
    cv2.setNumThreads(1)
    plain = camera_effects.CameraEffects()
    for name, chain in (("without contrast and sharpening", plain), ("the config's", effects)):
        times = []
        for k in range(200):
            start = time.perf_counter()
            chain({"image": gen_views[k % len(gen_views)], "rng": rng})
            times.append(time.perf_counter() - start)
        print(f"camera effects, {name}: median {1000 * np.median(times):.2f} ms per image")


if __name__ == "__main__":
    main()
