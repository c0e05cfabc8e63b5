"""Input-pipeline throughput: images/s of one loader process through each transform chain.

Images/s of the single-process loader (PNG decode + transform chain + collate,
``worker_count=0``, OpenCV on one thread: what one loader worker does) for the detector's
eval and train chains (configs/detect3d_kitti.py, 288x1280; the train chain with its
photometric distortion and flip) and the depth network's eval chain with a resize
(configs/depth_default.py geometry on KITTI-depth frames), on the real frames of
``../shared/data/kitti_samples``. Medians (and min) over the rounds; prints the machine.

    python benchmarks/bench_transforms.py [--rounds 7] [--frames 26]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import cv2
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

KITTI = REPO.parent / "shared" / "data" / "kitti_samples"


class Repeat:
    """A source of ``n`` samples cycling through ``source`` (same decode work per sample)."""

    def __init__(self, source, n: int):
        self.source, self.n = source, n

    def __len__(self):
        return self.n

    def __getitem__(self, i):
        return self.source[i % len(self.source)]


def chains():
    from gac_jax.builders import depth as depth_builders
    from gac_jax.builders import detect3d
    from gac_jax.config import load_config
    from gac_jax.data.sources import KittiDepthSource, KittiObjectSource
    from gac_jax.evaluation.detector_evaluator import InputArrays

    kitti = load_config(str(REPO / "configs" / "detect3d_kitti.py"))
    objects = KittiObjectSource(KITTI / "object", "labeled")
    depth_cfg = load_config(str(REPO / "configs" / "depth_default.py"))
    depth_src = KittiDepthSource(KITTI / "depth", "train", cameras=(2,))

    def depth_arrays(sample):
        return {"image": sample["image"], "depth": sample["depth"], "P2": sample["P2"]}

    yield "detect3d eval (288x1280)", objects, detect3d.eval_transform(kitti), InputArrays()
    train = detect3d.train_transform(kitti)  # incl. photometric distortion and flip
    yield "detect3d train (288x1280)", objects, train, InputArrays()
    d = depth_cfg.data
    if d.height != d.crop_height:
        name = f"depth eval ({d.height}x{d.eval_width})"
        yield name, depth_src, depth_builders.eval_transform(depth_cfg), depth_arrays


def images_per_s(source, chain, arrays, frames: int, batch: int = 2) -> float:
    from gac_jax.data.loader import Loader

    loader = Loader(
        Repeat(source, frames), chain, arrays, batch_size=batch, shuffle=False, num_epochs=1
    )
    t0 = time.perf_counter()
    n = sum(len(b["image"]) for b in loader.iterate())
    return n / (time.perf_counter() - t0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--frames", type=int, default=26)
    args = parser.parse_args()
    cv2.setNumThreads(1)  # the loader's workers each run one thread; measure one
    print(one_line(describe_machine("numpy", "cv2")), "; cv2 threads 1", flush=True)
    for name, source, chain, arrays in chains():
        images_per_s(source, chain, arrays, 4)  # warm caches
        rates = [images_per_s(source, chain, arrays, args.frames) for _ in range(args.rounds)]
        print(
            f"{name}: {statistics.median(rates):.1f} images/s, median (min {min(rates):.1f}) "
            f"over {args.rounds} rounds of {args.frames}",
            flush=True,
        )


if __name__ == "__main__":
    main()
