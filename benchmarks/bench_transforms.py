"""Loader throughput with the float32 resize (now) vs the former uint8 resize.

Since issue 13, :class:`gac_jax.data.transforms.Resize` casts the image to float32 before
``cv2.resize``, as the authors' chain does. This measures what that costs the input
pipeline: images/s of the single-process loader (PNG decode + transform chain + collate,
``worker_count=0``) for the detector's eval and train chains (configs/detect3d_kitti.py,
288x1280) and the depth network's eval chain with a resize (configs/depth_default.py
geometry on KITTI-depth frames), on the real frames of ``../shared``. "uint8" swaps each
``Resize`` for the former one (uint8 in, uint8 out). The two variants alternate round by
round (same machine load for both); medians (and min) over the rounds are reported.

    python benchmarks/bench_transforms.py [--rounds 7] [--frames 26]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import cv2
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.data import transforms  # noqa: E402

KITTI = REPO.parent / "shared" / "data" / "kitti_samples"


@dataclasses.dataclass
class Uint8Resize(transforms.Resize):
    """The former Resize: ``cv2.resize`` on the uint8 image (re-quantised output)."""

    def __call__(self, sample):
        h, w = sample["image"].shape[:2]
        new_w = self.width if self.width is not None else int(round(w * self.height / h))
        A = transforms.resize_affine((h, w), (self.height, new_w))
        image = cv2.resize(sample["image"], (new_w, self.height), interpolation=self.interpolation)
        depth = None
        if "depth" in sample:
            depth = transforms.warp_depth(sample["depth"], A, (self.height, new_w), self.depth_mode)
        return transforms.apply_affine(sample, A, image, depth)


def with_uint8_resize(chain: transforms.Compose) -> transforms.Compose:
    ops = [
        Uint8Resize(t.height, t.width, t.interpolation, t.depth_mode)
        if type(t) is transforms.Resize
        else t
        for t in chain.transforms
    ]
    assert any(isinstance(t, Uint8Resize) for t in ops), "chain has no Resize"
    return transforms.Compose(ops)


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
        variants = {"float32 (now)": chain, "uint8 (before)": with_uint8_resize(chain)}
        rates: dict[str, list[float]] = {k: [] for k in variants}
        images_per_s(source, chain, arrays, 4)  # warm caches
        for _ in range(args.rounds):
            for key, ch in variants.items():  # interleaved
                rates[key].append(images_per_s(source, ch, arrays, args.frames))
        print(f"\n{name}: images/s, median (min) over {args.rounds} rounds of {args.frames}")
        for key, r in rates.items():
            print(f"  {key:15s} {statistics.median(r):7.1f} ({min(r):.1f})")
        ratio = statistics.median(rates["float32 (now)"]) / statistics.median(
            rates["uint8 (before)"]
        )
        print(f"  float32 / uint8 = {ratio:.3f}")


if __name__ == "__main__":
    main()
